"""The host's main loop: receive -> synchronise -> track -> live output, everything recorded.

    pipe = HostPipeline(rig, cameras, on_result=print)
    pipe.start(); ...; summary = pipe.stop()

One module per idea: `host` (the `HostPipeline` loop), `rows` (recording rows), `sink` (the
`ResultSink` seam for live consumers), `dvs` (event cameras), `report` (status line and summary),
`cameras` (calibration), `run` (`flytrack run`). Every name other code imports from
`flytrack_host.pipeline` is re-exported here.

May import: util, protocol, geometry, tracking, rig, intake, trigger, recording, live, actuation, dvs.
"""

from flytrack_host.pipeline.cameras import calibration_problems, load_cameras
from flytrack_host.pipeline.host import (
    MAX_BACKLOG_S,
    RECEIVE_BATCH,
    RECORDING_INCOMPLETE_EXIT,
    STALL_S,
    HostPipeline,
    TrackerFactory,
    default_recording_path,
    default_tracker_factory,
)
from flytrack_host.pipeline.run import run_command
from flytrack_host.pipeline.sink import ResultSink
from flytrack_host.recording.rows import data2d_rows, result_rows

__all__ = [
    "MAX_BACKLOG_S",
    "RECEIVE_BATCH",
    "RECORDING_INCOMPLETE_EXIT",
    "STALL_S",
    "HostPipeline",
    "ResultSink",
    "TrackerFactory",
    "calibration_problems",
    "data2d_rows",
    "default_recording_path",
    "default_tracker_factory",
    "load_cameras",
    "result_rows",
    "run_command",
]
