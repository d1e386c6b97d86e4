"""Event cameras (DVS): event files and event algorithms through the C library (`events`), DVS clusters
as 2D observations for the 3D tracker (`clusters`), the DVS USB bridge firmware run in simavr (`bridge`),
and wing-beat analysis of a tethered fly (`wingbeat`).

May import: util, protocol, geometry, tracking, intake.
"""
