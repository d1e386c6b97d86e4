"""The synchroniser's state per camera (`_Cam`) and per trigger frame still open (`_Pending`)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from flytrack_host.intake.sync.types import CameraFrame, CameraSyncStats
from flytrack_host.intake.sync.windows import _LagWindow, _Window


@dataclass
class _Cam:
    index: int
    alive: bool
    last_recv: float
    offset: int | None = None  # trigger_frame = camera_frame - offset (when the edge gives none)
    last_cf: int | None = None
    last_tf: int | None = None
    lag_ewma: float | None = None  # arrival lag against the trigger clock (places late joiners)
    rel_base: float | None = None  # usual arrival relative to the other cameras (drift baseline)
    rel_window: _Window = field(default_factory=_Window)  # (trigger frame, d, arrival) of recent frames
    arrival_shift: float = 0.0  # how late (s, whole periods) an edge-numbered camera's frames were found
    seen_cf: deque = field(default_factory=lambda: deque(maxlen=512))  # recent camera frames accepted
    # (arrival, lag to the trigger clock, trigger frame) over ~1 s
    lag_win: _LagWindow = field(default_factory=_LagWindow)
    ahead_check_at: float = 0.0
    restarted_at: float | None = None
    placing: list | None = None  # a restarted edge's first frames, held until it can be placed
    place_best: int | None = None  # the lowest bound on the trigger frame of its camera frame 0 so far
    place_at: int = 0  # index in `placing` of the frame that gave it
    suspects: list[tuple[CameraFrame, int]] = field(default_factory=list)
    stats: CameraSyncStats = field(default_factory=CameraSyncStats)


@dataclass
class _Pending:
    frames: dict[int, CameraFrame]
    first_arrival: float
    deadline: float
