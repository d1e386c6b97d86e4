"""The simulated rig: flying insects, rendered cameras, and the orchestration that feeds them through
the real trigger firmware, edge extractors and host (`flytrack demo`).

May import: util, protocol, geometry, tracking, rig, intake, trigger, recording, live, actuation, edges, dvs,
pipeline, calibration, io.
"""
