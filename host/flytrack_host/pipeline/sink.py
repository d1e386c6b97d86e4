"""The seam for live consumers of the host pipeline's tracked frames."""

from __future__ import annotations

from typing import Protocol

from flytrack_host.tracking.types import FrameResult


class ResultSink(Protocol):
    """A consumer of every tracked frame: a live output (event stream, VR pose) or the actuation rules.

    `on_frame` runs on the tracking thread right after the tracker, so it must only hand the frame on
    (append to a bounded queue, a non-blocking send) and return: a slow sink would delay tracking.
    `frame_time` is the host time of the frame's trigger pulse (the clock model's), `estimate_time` the
    host time the estimate was made; their difference is the trigger-to-estimate latency. An exception
    is caught, counted in `sink_errors` and logged (rate-limited); the sink stays attached. `close` is
    called once when the pipeline stops.
    """

    def on_frame(self, result: FrameResult, frame_time: float, estimate_time: float) -> None: ...

    def close(self) -> None: ...
