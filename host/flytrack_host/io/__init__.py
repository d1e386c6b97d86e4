"""Import and export of tracking data: Braid's .braidz, flydra's .h5, CSV; offline re-tracking.

May import: util, protocol, geometry, tracking, trigger, recording.
"""
