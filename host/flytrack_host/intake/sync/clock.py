"""The trigger clock the synchroniser maps frames through: the `FrameClock` protocol (frame number ->
host time) and the fixed-rate fallback used when no trigger clock model is given."""

from __future__ import annotations

import math
from typing import Protocol


class FrameClock(Protocol):
    def frame_to_host_time(self, frame: int) -> float: ...


class FixedRateClock:
    """Fallback trigger clock: `start_time + frame / fps`. Anchored on the first frame when
    `start_time` is None (trigger times then equal the first arrival: no trigger-box latency)."""

    def __init__(self, fps: float, start_time: float | None = None):
        if not (fps > 0 and math.isfinite(fps)):
            raise ValueError(f"fps must be a positive number, not {fps!r}")
        self.fps = float(fps)
        self.start_time = start_time

    @property
    def anchored(self) -> bool:
        return self.start_time is not None

    def anchor(self, frame: int, host_time: float) -> None:
        self.start_time = host_time - frame / self.fps

    def frame_to_host_time(self, frame: int) -> float:
        if self.start_time is None:
            return math.nan
        return self.start_time + frame / self.fps
