"""FlyTrack host: receives feature packets from edge extractors, synchronises them by trigger frame,
tracks flying animals in 3D, records, serves live estimates and drives stimuli."""

__version__ = "0.1.0"
