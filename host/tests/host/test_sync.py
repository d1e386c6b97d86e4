"""The frame synchroniser: bundling, deadlines, dead cameras, bad frame numbers, clock jumps."""

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
    import re

    import pytest

    for bad in (0.0, -5.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match=f"^fps must be a positive number, not {re.escape(repr(bad))}$"):
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


def test_stats_count_every_frame_once_and_bundles_by_how_they_closed() -> None:
    """Per camera: frames received; tracked (in a bundle), late, duplicate, future; deaths and revivals.
    The counts add up: every frame is tracked or reported untracked with one reason."""
    import dataclasses

    from flytrack_host.intake.sync import CameraSyncStats

    d = make(dead_timeout_s=0.3)
    frames = stream({0: 0, 1: 0, 2: 0}, range(120))
    frames = [f for f in frames if not (f.camera_index == 0 and 40 <= f.camera_frame < 90)]  # 0.5 s gone
    late = next(f for f in frames if f.camera_index == 2 and f.camera_frame == 20)
    late.recv_time += 0.05  # after frame 20's deadline
    dup = frame(1, 30, T0 + 30 * P + 0.004)  # camera 1 sends frame 30 twice
    future = frame(2, 10**6, T0 + 60 * P + 0.003, 60 + 100000)  # an edge number 1000 s ahead
    stranger = frame(7, 5, T0 + 5 * P + 0.003)  # a camera the rig does not have
    d.feed(frames + [dup, future, stranger])
    d.advance(T0 + 120 * P + 0.1)  # all bundles closed, nobody silent for 0.3 s yet
    assert [(u.frame.camera_index, u.trigger_frame, u.reason) for u in d.untracked if u.reason != "late"] == [
        (7, -1, "unknown_camera"), (1, 30, "duplicate"), (2, 100060, "future")]
    assert [(u.frame.camera_index, u.trigger_frame) for u in d.untracked if u.reason == "late"] == [(2, 20)]
    st = {c: dataclasses.asdict(x) for c, x in d.sync.stats().items()}
    zero = {f.name: 0 for f in dataclasses.fields(CameraSyncStats)}  # every other count stays 0
    assert st[0] == {**zero, "frames": 70, "tracked": 70, "deaths": 1, "revivals": 1}
    assert st[1] == {**zero, "frames": 121, "tracked": 120, "duplicate": 1}
    assert st[2] == {**zero, "frames": 121, "tracked": 119, "late": 1, "future": 1}
    assert [(e.kind, e.global_jump) for e in d.events] == [("dead", False), ("alive", False)]
    assert d.events[0].message.startswith("camera 0 silent for 0.3") and d.events[0].message.endswith(" s: marked dead")
    assert d.events[1].message == "camera 0 is sending again"
    complete = sum(b.closed_by == "complete" and not b.bundle.missing_cameras for b in d.bundles)
    assert len(d.bundles) == 120 and d.sync.bundles_complete == complete > 0
    assert d.sync.bundles_deadline == 120 - complete > 0 and d.sync.reanchors == 0


def test_defaults_deadline_dead_timeout_and_start_time() -> None:
    """The defaults: a bundle waits half a period after its first frame; a camera is dead after 0.5 s
    of silence, counted from start_time (0) before it ever sent; the clock is a fixed-rate one."""
    s = FrameSynchronizer([0, 1, 2], FPS)
    assert not [o for o in s.poll(0.49) if isinstance(o, SyncEvent)]
    assert [o.camera_index for o in s.poll(0.51) if isinstance(o, SyncEvent) and o.kind == "dead"] == [0, 1, 2]
    s = FrameSynchronizer([0, 1, 2], FPS)
    s.add(frame(0, 0, 0.100), 0.100)
    s.add(frame(1, 0, 0.101), 0.101)
    assert s.next_deadline() == 0.100 + 0.5 * P
    assert s.poll(0.100 + 0.45 * P) == []
    out = s.poll(0.100 + 0.55 * P)
    assert [(b.bundle.trigger_frame, b.closed_by) for b in out if isinstance(b, SyncedBundle)] == [(0, "deadline")]
    assert isinstance(s.clock, FixedRateClock) and abs(s.frame_time(0) - 0.100) < 1e-12
    # A clock given is used as it is.
    own = FixedRateClock(FPS, start_time=5.0)
    assert FrameSynchronizer([0], FPS, clock=own).clock is own


def test_frame_zero_tie_window_after_synchronize_and_without() -> None:
    """After synchronize() every camera's first frame within 0.5 s (tie_window_s) of the first one is
    trigger frame 0; a camera first seen 0.7 s later is a late joiner, placed by its arrival. Without
    synchronize() (cameras already running) the tie spans only 0.9 period."""
    for synced, late_s, want_tf in ((True, 0.45, 0), (True, 0.7, 70), (False, 0.3, 30)):
        d = make()
        if synced:
            d.sync.synchronize()
        frames = stream({0: 0, 1: 0}, range(100))
        frames += [frame(2, 500 + k, T0 + late_s + k * P + 0.002) for k in range(20)]
        d.feed(frames)
        d.advance(T0 + 2)
        # Its first frame's trigger frame, tracked or (tied to frame 0, long closed) reported late.
        tfs = [b.bundle.trigger_frame for b in d.bundles if 2 in b.frames]
        tfs += [u.trigger_frame for u in d.untracked if u.frame.camera_index == 2]
        assert tfs and abs(min(tfs) - want_tf) <= 1, (synced, late_s, tfs[:3])


def test_a_counter_jump_is_confirmed_by_three_frames_and_mapped_by_arrival() -> None:
    """jump_confirm_frames (3): camera 1's counter jumps by 5000; its first two frames in the new
    numbering are suspect (future-dated), the third confirms the jump, not global (only its counter)."""
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(100))
    for f in frames:
        if f.camera_index == 1 and f.camera_frame >= 50:
            f.camera_frame += 5000
    d.feed(frames)
    d.advance(T0 + 2)
    reasons = [u.reason for u in d.untracked if u.frame.camera_index == 1]
    assert reasons == ["future", "future", "clock_jump"]
    jumps = d.kinds("clock_jump")
    assert len(jumps) == 1 and jumps[0].camera_index == 1 and not jumps[0].global_jump
    assert d.sync.stats()[1].future == 2 and d.sync.stats()[1].clock_jumps == 1
    by_tf = {b.bundle.trigger_frame: b for b in d.bundles}
    assert all(by_tf[k].frames[1].camera_frame == k + 5000 for k in range(53, 100))
    # The confirming frame is reported under its new mapping (it answered trigger frame 52).
    assert [u.trigger_frame for u in d.untracked if u.reason == "clock_jump"] == [52]
    # A counter jumping back (restarted without the receiver noticing): a discontinuity, then re-mapped.
    d = make()
    frames = stream({0: 0, 1: 5000, 2: 0}, range(100))
    for f in frames:
        if f.camera_index == 1 and f.camera_frame >= 5050:
            f.camera_frame -= 1000  # numbers far behind those seen: not a late frame
    d.feed(frames)
    d.advance(T0 + 2)
    assert [u.reason for u in d.untracked if u.frame.camera_index == 1] == ["discontinuity", "discontinuity",
                                                                           "clock_jump"]
    assert d.sync.stats()[1].suspect == 2 and d.sync.stats()[1].future == 0


def test_future_dated_frames_by_the_clock_and_without_one() -> None:
    """A frame numbered for a trigger time more than 0.5 s (future_tolerance_s) ahead is future-dated;
    0.4 s ahead is only early (claims a pulse not yet seen). Without a clock model (NaN times) the
    same tolerance counts in frames: 60 frames ahead of the newest accepted is future, 10 is accepted."""
    d = make()
    d.feed(stream({0: 0, 1: 0, 2: 0}, range(10), tf_from_edge=True))
    now = T0 + 10 * P
    for ahead, reason in ((60, "future"), (40, "early")):
        out = d.sync.add(frame(0, 100 + ahead, now, 9 + ahead), now)
        assert [u.reason for u in out if isinstance(u, UntrackedFrame)] == [reason], ahead
    # Early (early_fraction 1.5 periods + 5 ms): numbered for trigger frame 12 but arriving 25 ms
    # before its usual lag after that pulse would allow (camera 1 answers its pulses 2-2.5 ms late).
    t = T0 + 9.5 * P + 0.002
    out = d.sync.add(frame(1, 300, t, 12), t)
    assert [u.reason for u in out if isinstance(u, UntrackedFrame)] == ["early"]

    class NoModel:
        def frame_to_host_time(self, frame: int) -> float:
            return float("nan")

    s = FrameSynchronizer([0, 1, 2], FPS, clock=NoModel(), start_time=T0)
    for k in range(5):
        for c in range(3):
            s.add(frame(c, k, T0 + k * P, k), T0 + k * P)
    for ahead, reason in ((60, "future"), (10, None)):
        out = s.add(frame(1, 200 + ahead, T0 + 5 * P, 4 + ahead), T0 + 5 * P)
        assert [u.reason for u in out if isinstance(u, UntrackedFrame)] == ([reason] if reason else []), ahead


def test_a_shift_shorter_than_half_a_second_is_no_drift_by_default() -> None:
    """Drift evidence must span drift_min_s (0.5 s) at 100 fps, not just drift_frames (10) frames: camera
    2 arriving a period late for 0.3 s, then on time again, is never re-mapped."""
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(200))
    for f in frames:
        if f.camera_index == 2 and 80 <= f.camera_frame < 110:
            f.recv_time += P
    d.feed(frames)
    d.advance(T0 + 3)
    assert not d.kinds("drift") and d.sync.stats()[2].drift == 0


def test_a_restarted_edge_counts_each_of_its_frames_once() -> None:
    """An edge restart (restarted=True, counter from 0): its first frames are held until placed (10
    paced frames: recorded late, not tracked), then counted once each: frames received = tracked +
    reported untracked, one restart, 40 frames missed."""
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(100))
    for k in range(100, 200):
        t = T0 + k * P + 0.002
        frames += [frame(0, k, t), frame(2, k, t)]
        if k >= 140:
            f = frame(1, k - 140, t + 0.0005)
            f.restarted = k == 140
            frames.append(f)
    d.feed(frames)
    d.advance(T0 + 200 * P + 0.1)
    st = d.sync.stats()[1]
    sent = 100 + 60
    untracked = sum(1 for u in d.untracked if u.frame.camera_index == 1)
    assert st.frames == sent and st.tracked + untracked == sent and st.tracked >= sent - 12
    assert st.restarts == 1 and st.missed == 40
    ev = [e for e in d.events if e.kind == "restart"]
    assert len(ev) == 1 and "40 trigger frames missed" in ev[0].message


def test_the_fixed_rate_clock_is_reanchored_after_a_fifth_of_a_second_of_late_frames() -> None:
    """Every camera resumes 100 ms late (paced): the clock is re-anchored once, on the 20th late bundle
    (reanchor_s 0.2 s at 100 fps); bundles before keep the old frame times, later ones the new."""
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(200))
    for f in frames:
        if f.camera_frame >= 100:
            f.recv_time += 0.1
    d.feed(frames)
    d.advance(T0 + 200 * P + 0.15)
    ev = d.kinds("reanchor")
    assert len(ev) == 1 and d.sync.reanchors == 1
    assert "at trigger frame 119" in ev[0].message and "came 100 ms after" in ev[0].message
    lag = {b.bundle.trigger_frame: b.bundle.timestamp - (T0 + b.bundle.trigger_frame * P) for b in d.bundles}
    assert all(abs(lag[k] - lag[0]) < 1e-3 for k in range(100, 119))
    assert all(abs(lag[k] - lag[0] - 0.1) < 1e-3 for k in range(119, 200))


def test_an_early_frame_needs_more_than_the_slack() -> None:
    """early_s = 1.5 periods + 5 ms: numbered for a pulse 17 ms before its camera's usual lag allows
    is within the margin (host jitter); 25 ms is early."""
    for early_ms, reasons in ((17.0, []), (25.0, ["early"])):
        d = make()
        d.feed(stream({0: 0, 1: 0, 2: 0}, range(10), tf_from_edge=True))
        t = T0 + 12 * P + 0.002 - early_ms * 1e-3
        out = d.sync.add(frame(1, 300, t, 12), t)
        assert [u.reason for u in out if isinstance(u, UntrackedFrame)] == reasons, early_ms


def test_a_counter_jumping_ahead_is_early_for_a_fifth_of_a_second_then_confirmed() -> None:
    """Camera 1's counter skips 3 numbers while its frames keep coming on time: they claim pulses 30 ms
    ahead, so they are early (rejected) for early_confirm_s (0.2 s = 20 frames), then the jump is
    confirmed and the camera mapped by arrival again."""
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(200))
    for f in frames:
        if f.camera_index == 1 and f.camera_frame >= 100:
            f.camera_frame += 3
    d.feed(frames)
    d.advance(T0 + 200 * P + 0.1)
    st = d.sync.stats()[1]
    assert st.early == 20 and st.clock_jumps == 1 and st.tracked == 179
    assert [e.kind for e in d.events] == ["clock_jump"] and not d.events[0].global_jump
    by_tf = {b.bundle.trigger_frame: b for b in d.bundles}
    assert all(by_tf[k].frames[1].camera_frame == k + 3 for k in range(121, 200))


def test_synchronize_starts_the_numbering_again_from_frame_zero() -> None:
    d = make()
    d.feed(stream({0: 0, 1: 0, 2: 0}, range(50)))
    d.advance(T0 + 50 * P + 0.3)
    d.sync.synchronize()
    n0 = len(d.bundles)
    again = [frame(f.camera_index, f.camera_frame + 1000, f.recv_time + 1.0) for f in stream({0: 0, 1: 0, 2: 0},
                                                                                               range(30))]
    d.feed(again)
    d.advance(T0 + 1.0 + 30 * P + 0.1)
    assert [b.bundle.trigger_frame for b in d.bundles[n0:]] == list(range(30))
    assert all(b.closed_by == "complete" for b in d.bundles[n0:])


def test_a_camera_that_dies_twice_is_counted_twice() -> None:
    d = make(dead_timeout_s=0.2)
    frames = [f for f in stream({0: 0, 1: 0, 2: 0}, range(200))
              if not (f.camera_index == 2 and (40 <= f.camera_frame < 70 or 120 <= f.camera_frame < 150))]
    d.feed(frames)
    d.advance(T0 + 200 * P + 0.05)
    st = d.sync.stats()[2]
    assert (st.deaths, st.revivals) == (2, 2)
    assert [(e.kind, e.camera_index) for e in d.events] == [("dead", 2), ("alive", 2)] * 2


def test_every_resent_frame_is_a_duplicate() -> None:
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(60))
    frames += [frame(1, k, T0 + k * P + 0.004) for k in (20, 40)]  # camera 1 sends 20 and 40 again
    d.feed(frames)
    d.advance(T0 + 60 * P + 0.1)
    assert [(u.frame.camera_index, u.trigger_frame, u.reason) for u in d.untracked] == [(1, 20, "duplicate"),
                                                                                        (1, 40, "duplicate")]
    assert d.sync.stats()[1].duplicate == 2 and d.sync.stats()[1].tracked == 60


def test_flush_closes_what_is_pending_as_flush() -> None:
    d = make()
    d.feed([f for f in stream({0: 0, 1: 0, 2: 0}, range(5)) if f.camera_index != 2])
    out = d.sync.flush()  # frames 0-3 closed at their deadlines as the frames came; 4 was pending
    assert [(b.bundle.trigger_frame, b.closed_by) for b in out] == [(4, "flush")]
    assert d.sync.flush() == [] and d.sync.next_deadline() is None


def test_a_late_joiner_is_placed_by_arrival_minus_the_other_cameras_lag() -> None:
    """Cameras answer 6 ms after each pulse (more than half a period): a camera first seen later is
    placed at the pulse its frame answered, the others' lag taken off, not the pulse nearest its arrival.
    Without synchronize() a camera first seen 1.3 periods after the first one is no longer frame 0."""
    for first_k, lag_s in ((50, 0.006), (1, 0.002)):
        # A trigger clock that knows when the pulses were (the fixed-rate fallback would take the first
        # arrival, lag included, as frame 0's time).
        d = Driver(FrameSynchronizer((0, 1, 2), FPS, clock=FixedRateClock(FPS, start_time=T0), start_time=T0))
        frames = stream({0: 0, 1: 0}, range(100), lag={0: lag_s, 1: lag_s})
        frames += [frame(2, 700 + k, T0 + k * P + lag_s + 0.0003) for k in range(first_k, 100)]
        if first_k == 1:
            frames[-99].recv_time += 0.001  # 1.3 periods after camera 0's first frame
        d.feed(frames)
        d.advance(T0 + 2)
        by_tf = {b.bundle.trigger_frame: b for b in d.bundles}
        assert all(by_tf[k].frames[2].camera_frame == 700 + k for k in range(first_k + 2, 100)), first_k


def test_a_restart_whose_first_frames_come_late_is_placed_by_its_frames_on_time() -> None:
    """Camera 1's edge restarts; its first 8 frames come 70 ms late, 6 ms apart (paced: by them alone
    it would be placed 7 pulses too late). Its frames are held until it caught up (10 frames paced
    without a lower bound): placed right at once, no re-mapping needed, 40 frames missed."""
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(100))
    for k in range(100, 260):
        t = T0 + k * P + 0.002
        frames += [frame(0, k, t), frame(2, k, t)]
        if k >= 140:
            cf = k - 140
            f = frame(1, cf, max(T0 + 147 * P + 0.002 + cf * 0.006, t) if cf < 8 else t)
            f.restarted = cf == 0
            frames.append(f)
    d.feed(frames)
    d.advance(T0 + 260 * P + 0.1)
    st = d.sync.stats()[1]
    assert (st.restarts, st.ahead, st.missed, st.frames) == (1, 0, 40, 220)
    assert [e.kind for e in d.events] == ["restart"]
    got = [(b.bundle.trigger_frame, b.frames[1].camera_frame) for b in d.bundles if 1 in b.frames]
    assert all(tf == cf + 140 for tf, cf in got if tf >= 140) and sum(tf >= 140 for tf, _ in got) >= 100


def test_an_edge_restarted_twice_is_numbered_by_arrival_each_time_and_counted_twice() -> None:
    """Camera 1's edge restarts at trigger frame 140 (down 40 frames) and again at 220 (down 20):
    two restarts, 60 frames missed in all, each restart reported with where its counter now sits, and
    its frames land in the bundles of the pulses they answered."""
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(100))
    for k in range(100, 300):
        t = T0 + k * P + 0.002
        frames += [frame(0, k, t), frame(2, k, t)]
        for start, end in ((140, 200), (220, 300)):
            if start <= k < end:
                f = frame(1, k - start, t + 0.0005)
                f.restarted = k == start
                frames.append(f)
    d.feed(frames)
    d.advance(T0 + 300 * P + 0.1)
    st = d.sync.stats()[1]
    assert (st.restarts, st.missed, st.frames, st.clock_jumps) == (2, 60, 240, 0)
    assert [e.message for e in d.kinds("restart")] == [
        "camera 1: edge restarted; its camera frame 0 is trigger frame 140 (by arrival); "
        "40 trigger frames missed while it was down",
        "camera 1: edge restarted; its camera frame 0 is trigger frame 220 (by arrival); "
        "20 trigger frames missed while it was down",
    ]
    got = {b.bundle.trigger_frame: b.frames[1].camera_frame for b in d.bundles if 1 in b.frames}
    assert all(got[tf] == tf - 140 for tf in range(150, 200))  # the first 10 held until placed
    assert all(got[tf] == tf - 220 for tf in range(230, 300))
    assert not any(200 <= tf < 220 for tf in got)


def test_an_edge_restart_without_a_gap_misses_nothing() -> None:
    """The edge restarts between two pulses (its counter from 0, no pulse lost): 0 frames missed."""
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(100))
    for k in range(100, 200):
        t = T0 + k * P + 0.002
        frames += [frame(0, k, t), frame(2, k, t)]
        f = frame(1, k - 100, t + 0.0005)
        f.restarted = k == 100
        frames.append(f)
    d.feed(frames)
    d.advance(T0 + 200 * P + 0.1)
    st = d.sync.stats()[1]
    assert (st.restarts, st.missed, st.frames) == (1, 0, 200)
    msg = d.kinds("restart")[0].message
    assert "its camera frame 0 is trigger frame 100 (by arrival); 0 trigger frames missed" in msg
    got = {b.bundle.trigger_frame: b.frames[1].camera_frame for b in d.bundles if 1 in b.frames}
    assert all(got[tf] == tf - 100 for tf in range(110, 200))


def test_a_camera_counter_that_jumps_twice_is_remapped_twice() -> None:
    """Camera 1's counter jumps ahead by 5000 at trigger frame 100 and again at 200: each jump is
    confirmed by 3 frames, reported once (a camera's own jump, not the trigger's), counted, and its
    frames after it go back into the bundles of the pulses they answered."""
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(300))
    for f in frames:
        if f.camera_index == 1 and f.camera_frame >= 100:
            f.camera_frame += 5000
        if f.camera_index == 1 and f.camera_frame >= 5200:
            f.camera_frame += 5000
    d.feed(frames)
    d.advance(T0 + 300 * P + 0.1)
    st = d.sync.stats()[1]
    assert st.clock_jumps == 2 and st.future == 4 and st.restarts == 0
    jumps = d.kinds("clock_jump")
    assert [e.message for e in jumps] == [
        "camera 1: frame numbers jumped from trigger frame 99 to 102; mapping re-established",
        "camera 1: frame numbers jumped from trigger frame 199 to 202; mapping re-established",
    ]
    assert all(e.global_jump is False and e.camera_index == 1 for e in jumps)
    got = {b.bundle.trigger_frame: b.frames[1].camera_frame for b in d.bundles if 1 in b.frames}
    assert all(got[tf] == tf + 5000 for tf in range(103, 200))
    assert all(got[tf] == tf + 10000 for tf in range(203, 300))
    assert all(tf in got for tf in range(100)) and not any(tf in got for tf in (100, 101, 102, 200, 201, 202))


def test_two_pauses_of_every_camera_reanchor_the_clock_twice() -> None:
    """Every camera pauses 700 ms at trigger frame 100 and 300 ms more at 250: two re-anchors (as
    the rig, camera -1), counted, and the bundles' frame times follow the resumed arrivals."""
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(400))
    for f in frames:
        if f.camera_frame >= 100:
            f.recv_time += 0.7
        if f.camera_frame >= 250:
            f.recv_time += 0.3
    d.feed(frames)
    d.advance(T0 + 400 * P + 1.5)
    ev = d.kinds("reanchor")
    assert d.sync.reanchors == 2 and [e.camera_index for e in ev] == [-1, -1]
    assert [e.message for e in ev] == [
        "fixed-rate clock re-anchored at trigger frame 119: frames came 700 ms after their expected time "
        "(a pause of the cameras?)",
        "fixed-rate clock re-anchored at trigger frame 269: frames came 300 ms after their expected time "
        "(a pause of the cameras?)",
    ]
    lag = {b.bundle.trigger_frame: b.bundle.timestamp - (T0 + b.bundle.trigger_frame * P) for b in d.bundles}
    assert len(lag) == 400
    assert all(abs(lag[k] - lag[0] - 0.7) < 1e-3 for k in range(119, 250))
    assert all(abs(lag[k] - lag[0] - 1.0) < 1e-3 for k in range(269, 400))


def _drift_ms(message: str) -> float:
    return float(message.split("its frames arrive ")[1].split(" ms off")[0])


def test_a_camera_that_misses_two_pulses_drifts_twice_and_is_remapped_each_time() -> None:
    """Camera 2 misses a pulse at trigger frame 80 and another at 180 (its counter does not show it):
    two drifts of one frame (about one period, 10 ms), counted, and after each re-map its frames land
    in the bundles of the pulses they answered again."""
    d = make(drift_frames=5, drift_min_s=0.0)
    frames = stream({0: 0, 1: 0, 2: 0}, range(300))
    for f in frames:
        if f.camera_index == 2 and f.camera_frame >= 80:
            f.camera_frame -= 1
        if f.camera_index == 2 and f.camera_frame >= 179:
            f.camera_frame -= 1
    d.feed(frames)
    d.advance(T0 + 300 * P + 0.1)
    st = d.sync.stats()[2]
    assert st.drift == 2 and st.clock_jumps == 0
    drift = d.kinds("drift")
    assert [e.camera_index for e in drift] == [2, 2]
    for e in drift:
        assert e.message.startswith("camera 2 drifted by 1 frames: its frames arrive ")
        assert e.message.endswith(" ms off the other cameras' over 5 trigger frames; re-mapped")
        assert 9.0 <= _drift_ms(e.message) <= 11.0
    by_tf = {b.bundle.trigger_frame: b for b in d.bundles}
    for k in [*range(0, 80), *range(86, 180), *range(186, 299)]:
        fr = by_tf[k].frames.get(2)
        assert fr is not None and abs(fr.recv_time - (T0 + k * P + 0.002)) < 0.001, k


def test_an_edge_numbered_camera_that_drifts_is_reported_once_and_keeps_its_numbers() -> None:
    """Camera 2's edge numbers its frames; from trigger frame 80 they come a period later than the
    other cameras'. Reported as a drift once (not re-mapped: the edge's number wins)."""
    d = make(drift_frames=5, drift_min_s=0.0)
    frames = stream({0: 0, 1: 0, 2: 0}, range(200), tf_from_edge=True)
    for f in frames:
        if f.camera_index == 2 and f.trigger_frame >= 80:
            f.recv_time += P
    d.feed(frames)
    d.advance(T0 + 200 * P + 0.1)
    drift = d.kinds("drift")
    assert d.sync.stats()[2].drift == 1 and len(drift) == 1
    assert drift[0].message.endswith(" ms off the other cameras' over 5 trigger frames")
    assert 9.0 <= _drift_ms(drift[0].message) <= 11.0
    # Its numbers kept: every frame of camera 2 is in the bundle it names, or reported late with it.
    placed = {tf: b.frames[2].camera_frame for b in d.bundles for tf in [b.bundle.trigger_frame] if 2 in b.frames}
    assert all(cf == tf for tf, cf in placed.items()) and len(placed) >= 80
    late = [u for u in d.untracked if u.frame.camera_index == 2]
    assert all(u.reason == "late" and u.trigger_frame == u.frame.trigger_frame for u in late)
    assert len(placed) + len(late) == 200


def test_a_late_joiner_placed_ahead_and_its_restart_placed_ahead_are_each_moved_back() -> None:
    """Camera 1 joins at trigger frame 100 with its first 8 frames 70 ms late, 6 ms apart (placed 7
    pulses too late), then restarts its edge at 240 (after 40 missed pulses) the same way: the joiner
    is found ahead and moved back by 7; the restart is held until it caught up and placed right at
    once (40 missed); its frames then sit in the bundles of the pulses they answered."""
    d = make()
    frames = stream({0: 0, 2: 0}, range(400))
    for k in range(100, 400):
        if 200 <= k < 240:
            continue
        t = T0 + k * P + 0.0025
        cf = k if k < 240 else k - 240 + 5000
        first = 100 if k < 240 else 240
        if k < first + 8:
            t = max(T0 + (first + 7) * P + 0.0025 + (k - first) * 0.006, t)
        f = frame(1, cf, t)
        f.restarted = k == 240
        frames.append(f)
    d.feed(frames)
    d.advance(T0 + 400 * P + 0.1)
    st = d.sync.stats()[1]
    assert (st.ahead, st.restarts, st.missed, st.frames) == (1, 1, 40, 260)
    assert [e.message for e in d.kinds("ahead")] == [
        "camera 1: frames numbered 7 ahead of their arrival against the other cameras: re-mapped",
    ]
    got = {b.bundle.trigger_frame: b.frames[1].camera_frame for b in d.bundles if 1 in b.frames}
    assert all(got[tf] == tf for tf in range(130, 200))
    assert all(got[tf] == tf - 240 + 5000 for tf in range(270, 400))


def test_a_trigger_count_restart_is_confirmed_once_and_the_other_cameras_follow_at_once() -> None:
    """The trigger's count restarts at 0 (edge-numbered frames, no synchronize()): camera 0 confirms the
    jump on its third frame (trigger frame 2), a global jump reported once; cameras 1 and 2, already
    seeing the new numbering, follow at once (no jump of their own, 2 suspect frames each), and every
    bundle from trigger frame 3 on is complete."""
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(200), tf_from_edge=True)
    for f in frames:
        if f.trigger_frame >= 100:
            f.trigger_frame -= 100
    d.feed(frames)
    d.advance(T0 + 200 * P + 0.1)
    jumps = d.kinds("clock_jump")
    assert [(e.camera_index, e.global_jump) for e in jumps] == [(0, True)]
    assert jumps[0].message == "camera 0: frame numbers jumped from trigger frame 99 to 2; mapping re-established"
    st = d.sync.stats()
    assert [(st[i].clock_jumps, st[i].suspect) for i in range(3)] == [(1, 2), (0, 2), (0, 2)]
    after = d.bundles[100:]
    assert [b.bundle.trigger_frame for b in after] == list(range(3, 100))
    assert all(sorted(b.frames) == [0, 1, 2] and b.closed_by == "complete" for b in after)
    assert sum(len(b.frames) for b in d.bundles) + len(d.untracked) == 600


def test_frames_coming_sooner_than_the_anchor_pull_the_frame_times_back_by_up_to_two_periods() -> None:
    """The fixed-rate clock is anchored by the first frames' arrival (30 ms after the pulse here). From
    trigger frame 50 every camera's frames come 15 ms sooner: a frame cannot come before its pulse, so
    the anchor was late and the frame times move back 15 ms (two cameras are enough to say so). A step
    of 25 ms (more than two periods) is no late anchor: the frame times stay."""
    for cams in ((0, 1), (0, 1, 2)):
        for drop, expect in ((0.015, 0.015), (0.025, 0.030)):
            d = make(cams)
            frames = stream({c: 0 for c in cams}, range(100), lag={c: 0.03 for c in cams})
            for f in frames:
                if f.camera_frame >= 50:
                    f.recv_time -= drop
            d.feed(frames)
            d.advance(T0 + 100 * P + 0.1)
            lag = {b.bundle.trigger_frame: b.bundle.timestamp - (T0 + b.bundle.trigger_frame * P) for b in d.bundles}
            assert all(abs(lag[k] - expect) < 0.0008 for k in range(60, 100)), (cams, drop, lag[99])
            assert not d.kinds("reanchor")
            assert sum(len(b.frames) for b in d.bundles) + len(d.untracked) == 100 * len(cams)
