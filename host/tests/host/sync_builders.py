"""The frame builders the synchroniser's behaviour tests share (test_sync_behaviour_*.py,
test_sync_mapping_edges.py, test_sync_restart_drift.py import them from here).

Times are fed explicitly (no sleeping, nothing timed). At 64 fps (a period of 1/64 s) from a start at
1024 s most times are exact binary fractions, so a boundary ("within", "more than") is tested exactly.
`Run` feeds frames in arrival order and polls only when told; `make` builds one on a fixed-rate clock;
`stream` makes the frames of cameras answering every pulse; `OffsetClock` and `NotReadyClock` stand in
for a trigger clock model; `LAG8` and `paused_run` are set-ups several files use.
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

FPS = 64.0
P = 1.0 / FPS  # 15.625 ms, exact
T0 = 1024.0
PTS = np.zeros(1, dtype=[("x_dist", "<f4")])
L = 2.0**-9  # ~2 ms: how long after its pulse a frame arrives (exact in binary)


def frame(cam: int, cf: int, t: float, tf: int = -1) -> CameraFrame:
    return CameraFrame(camera_index=cam, camera_frame=cf, trigger_frame=tf, points=PTS, recv_time=t)


class Run:
    """Feeds frames in arrival order; polls only when told (each test says when the pipeline polls)."""

    def __init__(self, sync: FrameSynchronizer):
        self.sync = sync
        self.bundles: list[SyncedBundle] = []
        self.untracked: list[UntrackedFrame] = []
        self.events: list[SyncEvent] = []

    def take(self, outs) -> list:
        for o in outs:
            if isinstance(o, SyncedBundle):
                self.bundles.append(o)
            elif isinstance(o, UntrackedFrame):
                self.untracked.append(o)
            else:
                self.events.append(o)
        return outs

    def add(self, f: CameraFrame) -> list:
        return self.take(self.sync.add(f, f.recv_time))

    def poll(self, now: float) -> list:
        return self.take(self.sync.poll(now))

    def feed(self, frames: list[CameraFrame], poll_every: float | None = None) -> None:
        """In arrival order; with poll_every, polls at every deadline passed too (as the receiver does)."""
        for f in sorted(frames, key=lambda f: f.recv_time):
            while poll_every is not None:
                d = self.sync.next_deadline()
                if d is None or d > f.recv_time:
                    break
                self.poll(d)
            self.add(f)

    def kinds(self, kind: str) -> list[SyncEvent]:
        return [e for e in self.events if e.kind == kind]

    def by_tf(self) -> dict[int, SyncedBundle]:
        return {b.bundle.trigger_frame: b for b in self.bundles}


def make(cams=(0, 1, 2), fps: float = FPS, clock=None, **kw) -> Run:
    return Run(FrameSynchronizer(cams, fps, clock=clock if clock is not None else FixedRateClock(fps),
                                 start_time=T0, **kw))


def stream(cams: dict[int, int], ks, lag: dict[int, float] | None = None, edge: bool = False,
           fps: float = FPS) -> list[CameraFrame]:
    """cams: camera -> its counter at trigger frame 0; each frame arrives `lag` (L) after its pulse."""
    out = []
    for k in ks:
        for cam, off in cams.items():
            out.append(frame(cam, off + k, T0 + k / fps + (lag or {}).get(cam, L), k if edge else -1))
    return out


class OffsetClock:
    """A trigger clock model (no fixed-rate re-anchoring): pulse f at T0 + offset + f / fps. `offset`
    may be changed while the run goes on, as a clock model's new snapshot does."""

    def __init__(self, offset: float = 0.0, fps: float = FPS):
        self.offset = offset
        self.fps = fps

    def frame_to_host_time(self, frame: int) -> float:
        return T0 + self.offset + frame / self.fps


class NotReadyClock:
    """A trigger clock model with no estimate yet."""

    def frame_to_host_time(self, frame: int) -> float:
        return float("nan")


def cam_frames(r: Run, cam: int) -> dict[int, int]:
    """trigger frame -> camera frame of `cam` in the bundles."""
    return {b.bundle.trigger_frame: b.frames[cam].camera_frame for b in r.bundles if cam in b.frames}


LAG8 = {0: 0.008, 1: 0.008, 2: 0.008}


def paused_run(late: float) -> Run:
    """Three cameras on a fixed-rate clock, 80 frames; from frame 20 on every frame comes `late`
    periods later than before (a pause, then paced again)."""
    r = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(80))
    for f in frames:
        if f.camera_frame >= 20:
            f.recv_time += late * P
    r.feed(frames, poll_every=P)
    return r
