"""The frame synchroniser: bundling, deadlines, dead cameras, bad frame numbers, clock jumps."""

from __future__ import annotations

import numpy as np

from flytrack_host.sync import (
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


def test_frame_zero_tie_bundles_every_frame_complete():
    d = make()
    d.feed(stream({0: 100, 1: 5000, 2: 7}, range(50)))
    d.advance(T0 + 1)
    assert [b.bundle.trigger_frame for b in d.bundles] == list(range(50))
    assert all(b.closed_by == "complete" and not b.bundle.missing_cameras for b in d.bundles)
    assert all(set(b.bundle.detections) == {0, 1, 2} for b in d.bundles)
    assert not d.untracked
    # Frame times come from the fixed-rate clock, anchored at the first frame and moved earlier when a
    # bundle's frames come earlier than that anchor allows (0.5 ms of jitter here); the second earliest
    # arrival counts, so one misnumbered frame cannot move it.
    ts = np.array([b.bundle.timestamp for b in d.bundles])
    assert np.all(np.abs(np.diff(ts) - P) <= 0.0005)
    assert all(b.bundle.timestamp <= sorted(f.recv_time for f in b.frames.values())[1] for b in d.bundles)


def test_edge_trigger_frame_is_used():
    d = make()
    d.feed(stream({0: 3, 1: 9, 2: 1}, range(500, 520), tf_from_edge=True))
    assert [b.bundle.trigger_frame for b in d.bundles] == list(range(500, 520))


def test_deadline_closes_incomplete_bundle_and_late_data_is_untracked():
    d = make(deadline_fraction=0.5)
    frames = stream({0: 0, 1: 0, 2: 0}, range(20))
    late = [f for f in frames if f.camera_index == 2 and f.camera_frame == 10][0]
    frames.remove(late)
    late.recv_time += 0.05  # 5 frames late
    d.feed(frames + [late])
    d.advance(T0 + 1)
    b10 = [b for b in d.bundles if b.bundle.trigger_frame == 10][0]
    assert b10.closed_by == "deadline" and b10.bundle.missing_cameras == (2,)
    assert [(u.trigger_frame, u.reason) for u in d.untracked] == [(10, "late")]
    assert d.sync.stats()[2].late == 1
    assert len(d.bundles) == 20


def test_camera_stops_and_comes_back():
    d = make(dead_timeout_s=0.3)
    frames = stream({0: 0, 1: 0, 2: 50}, range(300))
    gone = [f for f in frames if f.camera_index == 2 and 100 <= f.camera_frame - 50 < 200]
    for f in gone:
        frames.remove(f)
    d.feed(frames)
    d.advance(T0 + 300 * P + 0.1)
    assert [e.camera_index for e in d.kinds("dead")] == [2]
    assert [e.camera_index for e in d.kinds("alive")] == [2]
    assert len(d.bundles) == 300
    by_tf = {b.bundle.trigger_frame: b for b in d.bundles}
    # While dead, bundles no longer wait for camera 2: closed complete, and 2 is not "missing".
    assert all(by_tf[k].closed_by == "complete" for k in range(140, 200))
    assert all(2 not in by_tf[k].bundle.detections for k in range(100, 200))
    # When it is back, its frames land in the right bundles again.
    assert all(2 in by_tf[k].bundle.detections for k in range(200, 300))
    assert not d.untracked


def test_duplicate_and_future_dated_frames_are_rejected_and_counted():
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(40), tf_from_edge=True)
    dup = frame(1, 20, T0 + 20 * P + 0.003, 20)
    future = frame(0, 10**6, T0 + 25 * P + 0.0031, 25 + 100000)  # claims a trigger time 1000 s ahead
    d.feed(frames + [dup, future])
    d.advance(T0 + 40 * P + 0.1)
    reasons = sorted(u.reason for u in d.untracked)
    assert reasons == ["duplicate", "future"]
    assert d.sync.stats()[1].duplicate == 1 and d.sync.stats()[0].future == 1
    assert [b.bundle.trigger_frame for b in d.bundles] == list(range(40))
    assert not d.kinds("clock_jump")


def test_trigger_clock_jump_back_is_detected_and_tracking_goes_on():
    d = make()
    cams = {0: 0, 1: 0, 2: 0}
    frames = stream(cams, range(100), tf_from_edge=True)
    # The trigger count restarts at 0 while the cameras' counters go on.
    after = []
    rng = np.random.default_rng(1)
    for k in range(100, 200):
        for cam in cams:
            t = T0 + k * P + 0.002 + rng.uniform(0, 0.0005)
            after.append(frame(cam, k, t, k - 100))
    d.feed(frames + after)
    d.advance(T0 + 3)
    jumps = d.kinds("clock_jump")
    assert jumps and all(j.global_jump for j in jumps)
    tfs = [b.bundle.trigger_frame for b in d.bundles]
    assert tfs[:100] == list(range(100))
    # Tracking resumed in the new numbering within a few frames.
    assert tfs[100:] == list(range(tfs[100], 100)) and tfs[100] <= 4
    # Nothing lost: every frame is either in a bundle or reported untracked.
    n_bundled = sum(len(b.frames) for b in d.bundles)
    assert n_bundled + len(d.untracked) == 600


def test_camera_counter_restart_is_remapped_by_arrival_time():
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(100))
    for f in frames:
        if f.camera_index == 1 and f.camera_frame >= 60:
            f.camera_frame -= 60  # the camera restarted its counter at trigger frame 60
    d.feed(frames)
    d.advance(T0 + 2)
    assert [e.camera_index for e in d.kinds("clock_jump")] == [1]
    by_tf = {b.bundle.trigger_frame: b for b in d.bundles}
    assert len(by_tf) == 100
    assert all(1 in by_tf[k].bundle.detections for k in range(66, 100))
    # Remapped by arrival time: each of camera 1's frames lands in the bundle of the trigger it
    # answered (it arrived 2.0-2.5 ms after that trigger), not in the bundle its new counter names.
    for k in range(66, 100):
        fr = by_tf[k].frames[1]
        assert fr.camera_frame == k - 60
        assert 0.002 <= fr.recv_time - (T0 + k * P) <= 0.0025 + 1e-9
    # Nothing lost: each of camera 1's 100 frames is in a bundle or reported untracked.
    n_bundled = sum(1 for b in d.bundles if 1 in b.frames)
    n_untracked = sum(1 for u in d.untracked if u.frame.camera_index == 1)
    assert n_bundled + n_untracked == 100, (n_bundled, n_untracked)


def test_camera_that_drifts_is_reported_and_remapped():
    d = make(drift_frames=5, drift_min_s=0.0)
    cams = {0: 0, 1: 0, 2: 0}
    frames = stream(cams, range(200))
    # Camera 2 missed one trigger pulse at frame 80 without its counter showing it.
    for f in frames:
        if f.camera_index == 2 and f.camera_frame >= 80:
            f.camera_frame -= 1
    d.feed(frames)
    d.advance(T0 + 200 * P + 0.1)
    drift = d.kinds("drift")
    assert [e.camera_index for e in drift] == [2]
    by_tf = {b.bundle.trigger_frame: b for b in d.bundles}
    # After re-mapping, camera 2's frames land in the right bundles again.
    for k in range(100, 199):
        fr = by_tf[k].frames.get(2)
        assert fr is not None and abs(fr.recv_time - (T0 + k * P + 0.002)) < 0.001


# --- Contracts `make mutation` found untested (issue 17) ---


def test_fixed_rate_clock_checks_fps_and_maps_frames_to_times() -> None:
    import math

    import pytest

    for bad in (0.0, -5.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="fps must be a positive number"):
            FixedRateClock(bad)
    slow = FixedRateClock(0.5, start_time=10.0)  # half a frame per second is a valid rate
    assert slow.anchored and slow.frame_to_host_time(3) == 16.0
    c = FixedRateClock(FPS)
    assert not c.anchored and math.isnan(c.frame_to_host_time(5))
    c.anchor(50, 2.0)  # frame 50 happened at t = 2 s
    assert c.anchored and abs(c.frame_to_host_time(50) - 2.0) < 1e-12 and abs(c.frame_to_host_time(0) - 1.5) < 1e-12


def test_camera_frame_defaults_describe_a_plain_complete_frame() -> None:
    """Sources that know no edge timing (software trigger, synthetic feeds) leave the defaults: no
    timestamps, no points beyond those given, not truncated, complete, no restart, not an event camera."""
    f = frame(0, 1, 2.0)
    assert (f.device_timestamp_ns, f.edge_recv_ns, f.edge_done_ns, f.total_points) == (0, 0, 0, 0)
    assert (f.truncated, f.incomplete, f.restarted, f.dvs) == (False, False, False, False)
