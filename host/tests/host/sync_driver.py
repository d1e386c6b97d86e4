"""The frame builders the synchroniser's test_sync_*.py files share (bundles, rejected frames, the start,
jumps, edge restarts, the clock, drift): 100 fps from T0 = 1000 s; `stream` makes the frames of cameras
answering every pulse 2-2.5 ms after it (0.5 ms of jitter from a seeded generator); `Driver` feeds them
in arrival order and polls every deadline before each, as the pipeline's receive timeout does.
"""

from __future__ import annotations

import numpy as np

from flytrack_host.intake.sync import (
    CameraFrame,
    FixedRateClock,
    FrameSynchronizer,
    SyncedBundle,
    SyncEvent,
    UntrackedFrame,
)

FPS = 100.0
P = 1.0 / FPS
T0 = 1000.0
PTS = np.zeros(1, dtype=[("x_dist", "<f4")])


def frame(cam: int, cf: int, t: float, tf: int = -1) -> CameraFrame:
    return CameraFrame(camera_index=cam, camera_frame=cf, trigger_frame=tf, points=PTS, recv_time=t)


class Driver:
    """Feeds frames in arrival order and polls deadlines like the pipeline does."""

    def __init__(self, sync: FrameSynchronizer):
        self.sync = sync
        self.bundles: list[SyncedBundle] = []
        self.untracked: list[UntrackedFrame] = []
        self.events: list[SyncEvent] = []
        self.now = T0

    def _take(self, outs) -> None:
        for o in outs:
            if isinstance(o, SyncedBundle):
                self.bundles.append(o)
            elif isinstance(o, UntrackedFrame):
                self.untracked.append(o)
            else:
                self.events.append(o)

    def feed(self, frames: list[CameraFrame]) -> None:
        for fr in sorted(frames, key=lambda f: f.recv_time):
            self.advance(fr.recv_time)
            self._take(self.sync.add(fr, fr.recv_time))

    def advance(self, t: float) -> None:
        # Poll at every deadline before t, as the pipeline's receive timeout does.
        while True:
            d = self.sync.next_deadline()
            nxt = min(x for x in (d, t) if x is not None) if d is not None else t
            self.now = max(self.now, nxt)
            self._take(self.sync.poll(self.now))
            if nxt >= t:
                return

    def kinds(self, kind: str) -> list[SyncEvent]:
        return [e for e in self.events if e.kind == kind]


def make(cams=(0, 1, 2), **kw) -> Driver:
    return Driver(FrameSynchronizer(cams, FPS, clock=FixedRateClock(FPS), start_time=T0, **kw))


def stream(cams: dict[int, int], frames: range, lag: dict[int, float] | None = None, tf_from_edge=False,
           rng=None) -> list[CameraFrame]:
    """cams: camera index -> camera frame counter at trigger frame 0."""
    rng = rng or np.random.default_rng(0)
    out = []
    for k in frames:
        for cam, off in cams.items():
            t = T0 + k * P + (lag or {}).get(cam, 0.002) + rng.uniform(0, 0.0005)
            out.append(frame(cam, off + k, t, k if tf_from_edge else -1))
    return out
