"""Event (DVS) cameras at the host: their clusters as 2D observations for the 3D tracker."""
