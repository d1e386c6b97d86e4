"""The simulated rig: flying insects, rendered cameras, and the orchestration that feeds them through
the real trigger firmware, edge extractors and host (`flytrack demo`), and the long run of it that
watches memory, queues and latency over an hour (`make soak`, sim/soak.py).

May import: util, protocol, geometry, tracking, rig, intake, trigger, recording, live, actuation, edges, dvs,
pipeline, calibration, io.
"""
