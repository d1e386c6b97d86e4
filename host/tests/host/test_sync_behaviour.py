"""The frame synchroniser, behaviour by behaviour: what a bundle waits for and when it closes, frames
that share a bundle, the frame-0 tie, future and misnumbered frames, clock jumps seen by several
cameras, the lag estimate that places late joiners, the drift check's baseline.

Times are fed explicitly (no sleeping, nothing timed). At 64 fps (a period of 1/64 s) from a start at
1024 s most times are exact binary fractions, so a boundary ("within", "more than") is tested exactly.
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


# --- a bundle's deadline, the cameras it waits for, how it closed -------------------------------


def test_a_frame_resent_while_its_bundle_is_open_is_a_duplicate_each_time() -> None:
    """Camera 1's frames 10 and 20 are delivered again (held up in the network) after its next frame,
    while their bundles still wait for camera 2: each copy is reported as a duplicate, counted, and
    the first copy stays in the bundle."""
    r = make(deadline_fraction=1.5)
    frames = stream({0: 0, 1: 0, 2: 0}, range(30))
    for f in frames:
        if f.camera_index == 2 and f.camera_frame in (10, 20):
            f.recv_time += 0.004  # within the deadline
        if f.camera_index == 1 and f.camera_frame in (11, 21):
            f.recv_time -= P - 0.0002  # its next frame came right after, bunched
    frames += [frame(1, k, T0 + k * P + L + 0.0005) for k in (10, 20)]
    r.feed(frames, poll_every=P)
    assert [(u.frame.camera_index, u.trigger_frame, u.reason) for u in r.untracked] == [
        (1, 10, "duplicate"), (1, 20, "duplicate")]
    assert r.sync.stats()[1].duplicate == 2 and r.sync.stats()[1].tracked == 30
    by_tf = r.by_tf()
    assert all(by_tf[k].frames[1].recv_time == T0 + k * P + L for k in (10, 20))
    assert all(by_tf[k].closed_by == "complete" for k in range(30))


def test_an_edge_repeating_a_trigger_number_sends_a_suspect_frame_not_a_second_copy() -> None:
    """An edge-numbered camera whose next frame carries the same trigger number as its last one (its
    counter moved on, the number did not): that frame is suspect (a discontinuity), not tracked."""
    r = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(20), edge=True)
    for f in frames:
        if f.camera_index == 1 and f.camera_frame == 10:
            f.trigger_frame = 9
    r.feed(frames, poll_every=P)
    assert [(u.frame.camera_index, u.frame.camera_frame, u.reason) for u in r.untracked] == [
        (1, 10, "discontinuity")]
    st = r.sync.stats()[1]
    assert (st.suspect, st.duplicate, st.tracked) == (1, 0, 19)


def test_a_bundle_opened_ahead_of_every_other_camera_waits_for_them_up_to_the_dead_timeout() -> None:
    """Cameras 1 and 2 have delivered up to frame 9. Camera 0's frame 10 (one ahead: the usual case)
    gets the usual deadline, half a period; its frame 11 (two ahead of every other camera) waits for
    them up to dead_timeout_s, so a frame numbered wrongly cannot close (and make late) bundles the
    others have not delivered yet. Once another camera reaches it, the usual deadline applies."""
    r = make()
    r.feed(stream({0: 0, 1: 0, 2: 0}, range(10)), poll_every=P)
    assert len(r.bundles) == 10
    t10, t11 = T0 + 10 * P + L, T0 + 11 * P + L
    r.add(frame(0, 10, t10))
    assert r.sync.next_deadline() == t10 + P / 2
    r.add(frame(0, 11, t10 + 0.001))
    assert r.sync.next_deadline() == t10 + P / 2  # bundle 10's; 11's is later
    assert max(p.deadline for p in r.sync.pending.values()) == t10 + 0.001 + 0.5
    r.poll(t10 + P / 2)
    assert [(b.bundle.trigger_frame, b.closed_by, b.bundle.missing_cameras) for b in r.bundles[10:]] == [
        (10, "deadline", (1, 2))]
    assert r.poll(t10 + 0.4) == []  # 11 still waits
    r.add(frame(1, 10, t11 - 0.001))  # camera 1's 10: late
    r.add(frame(1, 11, t11))  # camera 1 reached 11: half a period from now
    assert r.sync.next_deadline() == t11 + P / 2
    assert r.poll(t11 + P / 2 - 2.0**-12) == []
    r.poll(t11 + P / 2)
    assert [(b.bundle.trigger_frame, b.closed_by, b.bundle.missing_cameras) for b in r.bundles[11:]] == [
        (11, "deadline", (2,))]
    assert [(u.frame.camera_index, u.trigger_frame, u.reason) for u in r.untracked] == [(1, 10, "late")]


def test_bundles_waiting_for_cameras_that_fell_silent_close_when_those_are_declared_dead() -> None:
    """Cameras 1 and 2 stop after frame 9; camera 0's bundles from 11 on wait for them (they are ahead
    of every other camera). When the two are declared dead (0.5 s of silence), every waiting bundle
    is closed at that poll: by deadline, with no camera missing (dead ones are not waited for), and
    counted as closed by deadline, not complete."""
    r = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(10)) + stream({0: 0}, range(10, 60))
    r.feed([f for f in frames if f.recv_time < T0 + 9 * P + 0.5], poll_every=P)
    waiting = sorted(r.sync.pending)
    assert waiting == list(range(11, 41)) and r.sync.bundles_complete == 10
    assert r.sync.bundles_deadline == 1  # bundle 10, one ahead: the usual deadline
    out = r.poll(T0 + 9 * P + L + 0.5 + 2.0**-10)
    assert [(e.kind, e.camera_index) for e in out if isinstance(e, SyncEvent)] == [("dead", 1), ("dead", 2)]
    closed = [b for b in out if isinstance(b, SyncedBundle)]
    assert [b.bundle.trigger_frame for b in closed] == waiting and not r.sync.pending
    assert all(b.closed_by == "deadline" and b.bundle.missing_cameras == () for b in closed)
    assert (r.sync.bundles_complete, r.sync.bundles_deadline) == (10, 1 + len(waiting))
    # From then on camera 0's bundles are complete on its own.
    r.feed([f for f in frames if f.recv_time >= T0 + 9 * P + 0.5], poll_every=P)
    assert all(b.closed_by == "complete" for b in r.bundles[-10:])


def test_a_camera_is_dead_only_once_silent_for_longer_than_the_dead_timeout() -> None:
    """Exactly dead_timeout_s (0.5 s) of silence is not yet dead; any longer is."""
    s = FrameSynchronizer([0, 1], FPS, start_time=T0)
    assert s.poll(T0 + 0.5) == [] and s.live_cameras() == [0, 1]
    assert [(e.kind, e.camera_index) for e in s.poll(T0 + 0.5 + 2.0**-20)] == [("dead", 0), ("dead", 1)]
    assert s.live_cameras() == []


def test_how_a_bundle_closed_when_several_close_at_once() -> None:
    """A poll closing several bundles: all by deadline; flush() closing several: all by flush; a bundle
    completed while older ones still wait closes them by deadline."""
    r = make()
    r.feed([f for f in stream({0: 0, 1: 0, 2: 0}, range(4)) if f.camera_index != 2])  # no polls
    r.poll(T0 + 4 * P)
    assert [(b.bundle.trigger_frame, b.closed_by) for b in r.bundles] == [(k, "deadline") for k in range(4)]
    r.feed([f for f in stream({0: 0, 1: 0, 2: 0}, range(4, 8)) if f.camera_index != 2])
    out = r.sync.flush()
    assert [(b.bundle.trigger_frame, b.closed_by) for b in out] == [(k, "flush") for k in range(4, 8)]
    r.feed([f for f in stream({0: 0, 1: 0, 2: 0}, range(8, 10)) if not (f.camera_index == 2 and f.camera_frame == 8)])
    assert [(b.bundle.trigger_frame, b.closed_by) for b in r.bundles[4:]] == [(8, "deadline"), (9, "complete")]
    assert r.bundles[4].bundle.missing_cameras == (2,)


# --- the frame-0 tie and late joiners -----------------------------------------------------------


def test_the_tie_after_synchronize_spans_exactly_the_tie_window() -> None:
    """A camera first seen exactly tie_window_s (0.5 s) after the first camera is still trigger frame
    0; a little later it is a late joiner, placed by its arrival."""
    for extra, want in ((0.0, 0), (2.0**-12, 32)):
        r = make()
        r.sync.synchronize()
        r.feed(stream({0: 0, 1: 0}, range(40)), poll_every=P)
        r.add(frame(2, 900, T0 + L + 0.5 + extra))
        got = [u.trigger_frame for u in r.untracked if u.frame.camera_index == 2]
        got += [tf for tf, cf in cam_frames(r, 2).items() if cf == 900]
        assert got == [want], (extra, got)


def test_without_synchronize_a_camera_first_seen_most_of_a_period_later_is_the_next_frame() -> None:
    """Cameras already running: the tie spans 0.9 period only. A camera whose first frame comes 0.95
    period after the first camera's answers the next pulse; one first seen 0.3 s after a camera that
    sent a single frame is placed by arrival (trigger frame 19), not tied to frame 0."""
    r = make()
    frames = stream({0: 0, 2: 0}, range(20))
    frames += [frame(1, 500 + k, T0 + L + 0.95 * P + (k - 1) * P) for k in range(1, 20)]
    r.feed(frames, poll_every=P)
    assert all(cam_frames(r, 1)[k] == 500 + k for k in range(1, 20))
    r = make()
    r.add(frame(0, 0, T0 + L))
    r.add(frame(1, 77, T0 + L + 0.3))
    assert r.sync.max_accepted == 19 and 19 in r.sync.pending and r.sync.pending[19].frames[1].camera_frame == 77


def test_at_one_frame_per_second_the_tie_spans_most_of_a_period() -> None:
    """At 1 fps the tie window after synchronize() is 0.9 period (longer than tie_window_s): a camera
    first seen 0.8 s after the first is frame 0; one first seen a whole period later is frame 1."""
    for dt, want in ((0.8, 0), (1.0, 1)):
        r = make(fps=1.0)
        r.sync.synchronize()
        r.add(frame(0, 0, T0 + L))
        r.add(frame(1, 40, T0 + L + dt))
        r.add(frame(0, 1, T0 + L + 1.0 + 0.001))
        tf_of_1 = [tf for tf, p in list(r.sync.pending.items()) + [(b.bundle.trigger_frame, b) for b in r.bundles]
                   if 1 in p.frames]
        assert tf_of_1 == [want], (dt, tf_of_1)


def test_a_late_joiner_in_a_rig_with_a_camera_that_never_sent_is_placed_by_the_others_lag() -> None:
    """Camera 3 never sends; camera 2 joins at trigger frame 30: placed by its arrival minus the lag of
    the cameras that did send (8 ms after each pulse, known from a clock that knows the pulses)."""
    r = make(cams=(0, 1, 2, 3), clock=FixedRateClock(FPS, start_time=T0), dead_timeout_s=0.1)
    lag = {0: 0.008, 1: 0.008, 2: 0.008}
    frames = stream({0: 0, 1: 0}, range(60), lag=lag) + stream({2: 400}, range(30, 60), lag=lag)
    r.feed(frames, poll_every=P)
    got = cam_frames(r, 2)
    assert all(got[k] == 400 + k for k in range(31, 60)), got
    # Its first frame came after the others completed bundle 30 (it was not waited for): late.
    assert [(u.frame.camera_frame, u.trigger_frame, u.reason) for u in r.untracked] == [(430, 30, "late")]


def test_a_single_camera_rig_restarted_edge_is_placed_by_its_own_arrival() -> None:
    """One camera (no other camera's lag to take off): its restarted edge is placed at the pulse
    nearest its arrival, and the trigger frames it missed while down are counted."""
    r = make(cams=(0,))
    frames = stream({0: 0}, range(50))
    for k in range(60, 100):
        f = frame(0, k - 60, T0 + k * P + L)
        f.restarted = k == 60
        frames.append(f)
    r.feed(frames, poll_every=P)
    st = r.sync.stats()[0]
    assert (st.restarts, st.missed) == (1, 10)
    assert all(cam_frames(r, 0)[k] == k - 60 for k in range(60, 100))


# --- future-dated, late, misnumbered frames --------------------------------------------------------


def test_without_a_clock_estimate_a_number_more_than_the_tolerance_ahead_is_future_dated() -> None:
    """No trigger clock estimate yet: a frame numbered more than future_tolerance_s (0.5 s = 32
    frames) ahead of the newest accepted trigger frame is future-dated, even right after frame 0;
    exactly 32 ahead is accepted."""
    r = make(clock=NotReadyClock())
    for cam in (0, 1, 2):
        r.add(frame(cam, 0, T0 + L, 0))
    r.add(frame(1, 1, T0 + L + P, 33))
    r.add(frame(0, 1, T0 + L + P, 32))
    assert [(u.frame.camera_index, u.trigger_frame, u.reason) for u in r.untracked] == [(1, 33, "future")]
    assert r.sync.stats()[1].future == 1 and 32 in r.sync.pending and r.sync.max_accepted == 32


def test_a_trigger_time_exactly_the_tolerance_ahead_is_not_future_dated() -> None:
    """With a clock: a frame whose trigger time is exactly future_tolerance_s (0.5 s) after its arrival
    is accepted; 1/64 s more is future-dated."""
    r = make(clock=OffsetClock())
    for cam in (0, 1, 2):
        r.add(frame(cam, 0, T0, 0))
    r.add(frame(0, 1, T0, 32))
    r.add(frame(1, 1, T0, 33))
    assert [(u.frame.camera_index, u.trigger_frame, u.reason) for u in r.untracked] == [(1, 33, "future")]
    assert 32 in r.sync.pending


def test_a_frame_sent_again_a_few_frames_later_is_late_not_a_discontinuity() -> None:
    """Camera 1 sends its frame 15 again 5 frames later (within late_tolerance_s of its pulse): its
    bundle is closed, so it is reported late; its numbering is intact, so it is no discontinuity and
    the camera goes on being tracked."""
    r = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(40)) + [frame(1, 15, T0 + 20 * P + L + 0.001)]
    r.feed(frames, poll_every=P)
    assert [(u.frame.camera_index, u.trigger_frame, u.reason) for u in r.untracked] == [(1, 15, "late")]
    st = r.sync.stats()[1]
    assert (st.late, st.suspect, st.tracked) == (1, 0, 40)


def test_counter_gaps_up_to_max_gap_continue_the_mapping_longer_ones_are_discontinuities() -> None:
    """max_gap_s = 10 frames: camera 1 (numbered by its counter) skips 9 frames (a gap of 10): tracked
    at once; later it skips 10 (a gap of 11): a discontinuity, its first two frames suspect, the third
    confirms the jump, and its frames then sit in the right bundles again. Camera 2 (numbered by its
    edge) jumps 10 trigger frames ahead of its counter: continues; 11: suspect."""
    r = make(max_gap_s=10 / FPS)
    frames = stream({0: 0}, range(80))
    frames += [f for f in stream({1: 0}, range(80)) if not (20 < f.camera_frame < 30 or 40 < f.camera_frame < 51)]
    frames += [frame(2, k if k < 60 else k - 10, T0 + k * P + L, k) for k in range(80) if not 61 > k > 50]
    r.feed(frames, poll_every=P)
    one = cam_frames(r, 1)
    assert all(one[k] == k for k in range(30, 41)) and all(one[k] == k for k in range(54, 80))
    assert [(u.frame.camera_index, u.frame.camera_frame, u.reason) for u in r.untracked] == [
        (1, 51, "discontinuity"), (1, 52, "discontinuity"), (1, 53, "clock_jump")]
    assert all(cam_frames(r, 2)[k] == k for k in range(20, 51)) and cam_frames(r, 2)[61] == 51
    r = make(max_gap_s=10 / FPS)
    frames = stream({0: 0, 1: 0}, range(40)) + [frame(2, k if k < 10 else k - 11, T0 + k * P + L, k)
                                                 for k in range(40) if not 21 > k > 9]
    r.feed(frames, poll_every=P)
    assert [(u.frame.camera_index, u.frame.camera_frame, u.reason) for u in r.untracked][:1] == [
        (2, 10, "discontinuity")]


def test_a_camera_silent_for_more_than_ten_seconds_comes_back_as_a_discontinuity() -> None:
    """max_gap_s defaults to 10 s: camera 1 silent for 10.2 s comes back with a counter gap above it:
    its first two frames are suspect, the third re-maps it by arrival."""
    r = make(dead_timeout_s=0.5)
    n = 20 + 653 + 10
    frames = stream({0: 0, 2: 0}, range(n)) + [f for f in stream({1: 0}, range(n)) if not 20 <= f.camera_frame < 673]
    r.feed(frames, poll_every=P)
    assert [(u.frame.camera_frame, u.reason) for u in r.untracked if u.frame.camera_index == 1] == [
        (673, "discontinuity"), (674, "discontinuity"), (675, "clock_jump")]
    assert all(cam_frames(r, 1)[k] == k for k in range(676, n))


def test_a_step_of_the_clock_model_keeps_every_continuing_frame_tracked() -> None:
    """The trigger clock model's new snapshot moves every pulse 3 periods later (frames now look 47 ms
    early): frames that continue their camera's counter are never misnumbered, so all stay tracked."""
    clock = OffsetClock()
    r = make(clock=clock)
    frames = stream({0: 0, 1: 0, 2: 0}, range(100))
    r.feed([f for f in frames if f.camera_frame < 50], poll_every=P)
    clock.offset = 3 * P
    r.feed([f for f in frames if f.camera_frame >= 50], poll_every=P)
    assert not r.untracked and not r.events
    assert [b.bundle.trigger_frame for b in r.bundles] == list(range(100))


def test_frames_numbered_ahead_are_held_for_early_confirm_s_then_confirm_the_jump() -> None:
    """Camera 1's counter jumps 5 frames ahead (its frames now claim pulses that had not happened): its
    frames are early, untracked, until they span early_confirm_s (12 periods here); the frame that
    reaches it confirms the jump, and the camera is re-mapped."""
    r = make(early_confirm_s=12 / FPS)
    frames = stream({0: 0, 2: 0}, range(80)) + [frame(1, k + (5 if k >= 40 else 0), T0 + k * P + L)
                                                 for k in range(80)]
    r.feed(frames, poll_every=P)
    mine = [(u.frame.camera_frame - 5, u.reason) for u in r.untracked if u.frame.camera_index == 1]
    assert mine == [(k, "early") for k in range(40, 52)] + [(52, "clock_jump")], mine
    assert all(cam_frames(r, 1)[k] == k + 5 for k in range(53, 80))


# --- the ahead check: a camera whose frames come before their pulses ------------------------------


def test_cameras_on_a_slow_link_do_not_make_the_on_time_camera_look_ahead() -> None:
    """Cameras 0 and 1 come 50 ms after each pulse (a slow link), camera 2 after 2 ms. Camera 2 is
    ahead of the others, but its frames never come before their own pulses: it is not re-mapped, and
    its bundles wait for the slow cameras (it is ahead of them). (A trigger clock model: the fixed-rate
    fallback would take the slow cameras' arrivals as a pause and re-anchor on them.)"""
    r = make(clock=OffsetClock())
    r.sync.synchronize()
    lag = {0: 0.05, 1: 0.05, 2: L}
    r.feed(stream({0: 0, 1: 0, 2: 300}, range(130), lag=lag), poll_every=P)
    assert not r.kinds("ahead") and r.sync.stats()[2].ahead == 0
    # The first 4 bundles closed at their deadlines (the slow cameras unseen yet), then all complete.
    assert [b.closed_by for b in r.bundles] == ["deadline"] * 4 + ["complete"] * 126
    assert all(cam_frames(r, 2)[k] == 300 + k for k in range(130))


def test_cameras_with_different_latencies_are_not_re_mapped_when_the_clock_model_runs_late() -> None:
    """Camera 2 arrives 10 ms sooner than the others (two thirds of a period), and the trigger clock
    model places every pulse 40 ms late, so every frame seems to come before its pulse: no camera is
    ahead of the others by more than the early threshold, so none is re-mapped."""
    r = make(clock=OffsetClock(0.040), deadline_fraction=1.0)
    lag = {0: L + 0.010, 1: L + 0.010, 2: L}
    r.feed(stream({0: 0, 1: 0, 2: 300}, range(130), lag=lag), poll_every=P)
    assert not r.kinds("ahead") and not r.untracked
    assert all(cam_frames(r, 2)[k] == 300 + k for k in range(130))


def test_a_late_joiner_placed_one_frame_ahead_is_moved_back_by_one() -> None:
    """With early_fraction 0.6 (a frame early by more than 0.6 period counts): camera 2's first frame
    comes a period late, so it is placed one pulse ahead; its frames then come a period before their
    mapped pulses, compared with the others: moved back by one, and tracked in the right bundles."""
    r = make(clock=FixedRateClock(FPS, start_time=T0), early_fraction=0.6, early_slack_s=0.0, max_gap_s=0.25)
    frames = stream({0: 0, 1: 0}, range(120)) + stream({2: 500}, range(41, 120))
    frames.append(frame(2, 540, T0 + 41 * P + L - 0.0001))
    r.feed(frames, poll_every=P)
    assert [e.message for e in r.kinds("ahead")] == [
        "camera 2: frames numbered 1 ahead of their arrival against the other cameras: re-mapped"]
    got = cam_frames(r, 2)
    assert all(got[k] == 500 + k for k in range(70, 120))
    # Its numbering carried over to the new mapping: no discontinuity, no jump afterwards.
    assert {u.reason for u in r.untracked if u.frame.camera_index == 2} <= {"late"}
    assert r.sync.stats()[2].clock_jumps == 0


# --- re-mapping by arrival: restarts, counter jumps, trigger count jumps ------------------------------


def _lagged_run(**kw) -> Run:
    """A trigger clock that knows the pulses; every camera answers 8 ms (half a period) after them."""
    return make(clock=FixedRateClock(FPS, start_time=T0), **kw)


LAG8 = {0: 0.008, 1: 0.008, 2: 0.008}


def test_a_restarted_edge_is_placed_by_its_arrival_minus_the_other_cameras_lag() -> None:
    """Camera 1's edge restarts at trigger frame 100 (counter from 0, 20 pulses missed): its frames are
    held until restart_settle_frames (10) came paced without lowering the bound (arrival minus the
    others' 8 ms lag), then placed so that every frame sits on the pulse it answered; the held ones
    are recorded (late, with their right trigger frames), the rest tracked."""
    r = _lagged_run()
    frames = stream({0: 0, 2: 0}, range(160), lag=LAG8) + stream({1: 0}, range(80), lag=LAG8)
    for k in range(100, 160):
        f = frame(1, k - 100, T0 + k * P + 0.008)
        f.restarted = k == 100
        frames.append(f)
    r.feed(frames, poll_every=P)
    assert [e.kind for e in r.events] == ["restart"]
    assert r.events[0].message.endswith("its camera frame 0 is trigger frame 100 (by arrival); "
                                        "20 trigger frames missed while it was down")
    got = cam_frames(r, 1)
    assert all(got[k] == k - 100 for k in range(110, 160)) and not [k for k in got if 100 <= k < 110]
    assert [(u.frame.camera_frame, u.trigger_frame, u.reason) for u in r.untracked] == [
        (k, 100 + k, "late") for k in range(10)]


def test_a_counter_jump_is_re_mapped_by_arrival_minus_the_other_cameras_lag() -> None:
    """Camera 1's counter jumps by 5000 at trigger frame 100: once confirmed, its frames land in the
    bundles of the pulses they answered (arrival minus the others' 8 ms lag)."""
    r = _lagged_run()
    frames = stream({0: 0, 2: 0}, range(160), lag=LAG8)
    frames += [frame(1, k + (5000 if k >= 100 else 0), T0 + k * P + 0.008) for k in range(160)]
    r.feed(frames, poll_every=P)
    assert [e.kind for e in r.events] == ["clock_jump"]
    got = cam_frames(r, 1)
    assert all(got[k] == k + 5000 for k in range(103, 160))


def test_after_a_trigger_count_restart_frame_times_stay_on_the_pulses() -> None:
    """The trigger's count restarts at 0 at pulse 100 with a fixed-rate clock that knew the pulses: it
    is re-anchored on the restart frame's arrival minus the cameras' 8 ms lag, so the new bundles'
    times are the pulses' times (not 8 ms late)."""
    r = _lagged_run()
    frames = stream({0: 0, 1: 0, 2: 0}, range(160), lag=LAG8, edge=True)
    for f in frames:
        if f.trigger_frame >= 100:
            f.trigger_frame -= 100
    r.feed(frames, poll_every=P)
    assert [(e.kind, e.global_jump) for e in r.events] == [("clock_jump", True)]
    new = [b for b in r.bundles[100:]]
    assert [b.bundle.trigger_frame for b in new] == list(range(3, 60))
    err = [b.bundle.timestamp - (T0 + (b.bundle.trigger_frame + 100) * P) for b in new]
    assert max(abs(e) for e in err) < 0.001, (min(err), max(err))


def _trigger_count_jump(new_first: int) -> Run:
    """Edge-numbered cameras; the trigger's count goes from 99 to `new_first` at pulse 100. Camera 2
    answers 26 ms after each pulse (1.7 periods; the deadline is 3.5 periods), so when camera 0 confirms
    the jump (its third frame) camera 2 has sent one frame in the new numbering; camera 2 never sent
    its frame 99, so that bundle is still open; camera 3 of the rig has never sent."""
    r = make(cams=(0, 1, 2, 3), deadline_fraction=3.5, dead_timeout_s=0.3)
    lag = {0: L, 1: L, 2: L + 0.024}
    frames = stream({0: 0, 1: 0, 2: 0}, range(160), lag=lag, edge=True)
    frames = [f for f in frames if not (f.camera_index == 2 and f.camera_frame == 99)]
    for f in frames:
        if f.trigger_frame >= 100:
            f.trigger_frame += new_first - 100
    r.feed(frames, poll_every=P)
    return r


def test_a_trigger_count_jump_is_reported_once_and_a_camera_behind_follows_on_its_first_frame() -> None:
    """The trigger's count restarts at 0, or jumps to 5000: one global jump (camera 0's); the bundle
    still open then is handed on as flushed; camera 2, behind, with one frame in the new numbering,
    follows at once: its later frames are tracked (the new bundles from 3 on are complete), none
    reported as a jump of its own; the camera that never sent changes nothing."""
    for new_first in (0, 5000):
        r = _trigger_count_jump(new_first)
        assert [(e.kind, e.camera_index, e.global_jump) for e in r.events if e.kind != "dead"] == [
            ("clock_jump", 0, True)], new_first
        b99 = r.by_tf()[99]
        assert (b99.closed_by, sorted(b99.frames)) == ("flush", [0, 1]), new_first
        new = [b for b in r.bundles[r.bundles.index(b99) + 1:] if b.bundle.trigger_frame >= new_first + 3]
        assert [b.bundle.trigger_frame for b in new] == list(range(new_first + 3, new_first + 60)), new_first
        assert all(sorted(b.frames) == [0, 1, 2] for b in new), new_first
        # Its one frame in the new numbering: suspect (or future-dated); the rest tracked, or late (new
        # trigger frames 1 and 2 when the count restarted: the bundles up to the confirming frame count
        # as closed).
        st = r.sync.stats()[2]
        assert (st.clock_jumps, st.suspect + st.future, st.tracked + st.late) == (0, 1, 158), new_first
        assert st.late == (2 if new_first == 0 else 0), new_first


# --- the fixed-rate clock's anchor ------------------------------------------------------------------


def test_host_times_counted_from_zero_keep_the_frame_times_right() -> None:
    """Host times from 0 (the default start_time): the fixed-rate clock anchored at 0.0 is pulled earlier
    by frames coming sooner than the first (by 1 ms), and re-anchored after a pause of every camera
    (0.3 s), by those amounts only."""
    s = FrameSynchronizer([0, 1, 2], FPS)
    r = Run(s)
    frames = [frame(c, k, k * P - (0.001 if k >= 10 else 0.0)) for k in range(40) for c in (0, 1, 2)]
    r.feed(frames, poll_every=P)
    assert [b.bundle.trigger_frame for b in r.bundles] == list(range(40))
    assert all(abs(b.bundle.timestamp - (b.bundle.trigger_frame * P - 0.001)) < 1e-9 for b in r.bundles[10:])
    s = FrameSynchronizer([0, 1, 2], FPS)
    r = Run(s)
    frames = [frame(c, k, k * P + (0.3 if k >= 10 else 0.0)) for k in range(60) for c in (0, 1, 2)]
    r.feed(frames, poll_every=P)
    assert len(r.kinds("reanchor")) == 1 and [b.bundle.trigger_frame for b in r.bundles] == list(range(60))
    assert all(abs(b.bundle.timestamp - (b.bundle.trigger_frame * P + 0.3)) < 1e-9 for b in r.bundles[40:])


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


def test_a_pause_re_anchors_the_fixed_rate_clock_only_when_frames_come_over_two_periods_late() -> None:
    """Every camera pauses and comes back paced 2.5 periods later than before: re-anchored once (then
    the frame times follow the arrivals again); 1.5 periods later: not re-anchored."""
    for late, want in ((2.5, 1), (1.5, 0)):
        r = paused_run(late)
        assert len(r.kinds("reanchor")) == want == r.sync.reanchors, late
        if want:
            assert all(abs(b.bundle.timestamp - (T0 + L + (b.bundle.trigger_frame + late) * P)) < 1e-9
                       for b in r.bundles[50:])


def test_a_late_joiner_after_a_re_anchor_is_placed_by_the_lag_to_the_new_anchor() -> None:
    """Cameras 0 and 1 pause 0.3 s (the clock is re-anchored); 0.5 s later camera 2 joins (camera 3 of
    the rig never sends): placed at the pulses its frames answered."""
    r = make(cams=(0, 1, 2, 3))
    frames = stream({0: 0, 1: 0}, range(120))
    for f in frames:
        if f.camera_frame >= 20:
            f.recv_time += 0.3
    frames += [frame(2, 700 + k, T0 + k * P + L + 0.3 + 0.0002) for k in range(90, 120)]
    r.feed(frames, poll_every=P)
    assert len(r.kinds("reanchor")) == 1
    got = cam_frames(r, 2)
    assert all(got[k] == 700 + k for k in range(91, 120)), sorted(got.items())[:5]


def test_a_restart_without_a_gap_is_placed_once_caught_up_and_counts_nothing_missed() -> None:
    """Camera 1's edge restarts between pulses 99 and 100 (no pulse lost); its first frames come late
    and bunched (8 ms apart, a period is 15.6 ms) until it caught up: held until then, and placed by
    the lowest bound, not by the late first arrivals: frame 0 is trigger frame 100, nothing missed,
    never mapped ahead (so never moved back)."""
    r = make()
    frames = stream({0: 0, 2: 0}, range(200)) + stream({1: 0}, range(100))
    t_prev = 0.0
    for k in range(100, 200):
        t_prev = max(T0 + k * P + L, T0 + 107 * P + L if k == 100 else t_prev + 0.008)
        f = frame(1, k - 100, t_prev)
        f.restarted = k == 100
        frames.append(f)
    r.feed(frames, poll_every=P)
    st = r.sync.stats()[1]
    assert (st.restarts, st.ahead, st.missed) == (1, 0, 0)
    assert [e.kind for e in r.events] == ["restart"]
    assert "its camera frame 0 is trigger frame 100 (by arrival); 0 trigger frames missed" in r.events[0].message
    got = cam_frames(r, 1)
    assert all(got[k] == k - 100 for k in range(150, 200))


def _placed(fps: float, spacing: float, n: int = 40, **kw) -> tuple[int, str] | None:
    """Camera 1's edge restarts (its frame 0 answers trigger frame 30) and sends n frames `spacing`
    apart; returns the camera frame on whose arrival it was placed and the restart message (None:
    still held)."""
    r = make(fps=fps, **kw)
    frames = stream({0: 0, 2: 0}, range(60), fps=fps) + stream({1: 0}, range(20), fps=fps)
    t1 = T0 + 30 / fps + L
    frames += [frame(1, i, t1 + i * spacing) for i in range(n)]
    frames[-n].restarted = True
    for f in sorted(frames, key=lambda f: f.recv_time):
        r.add(f)
        if r.kinds("restart"):
            return f.camera_frame, r.kinds("restart")[0].message
    return None


def test_a_restarted_edge_is_placed_after_10_paced_frames_and_held_while_bunched() -> None:
    """Paced frames (one a period): placed on the 11th (restart_settle_frames 10 without a lower
    bound), at the pulse it answered. Frames coming faster than the pulses (an edge working off its
    queue) are held, however long: counted in frames, not seconds; only restart_hold_frames bounds it."""
    assert _placed(32.0, 1 / 32) == (10, "camera 1: edge restarted; its camera frame 0 is trigger frame 30 "
                                         "(by arrival); 10 trigger frames missed while it was down")
    assert _placed(20.0, 1 / 64) is None and _placed(32.0, 1 / 64) is None
    held = _placed(20.0, 1 / 64, restart_hold_frames=20)
    assert held is not None and held[0] == 19  # the hold's bound: placed by the lowest bound so far


# --- the drift check --------------------------------------------------------------------------------


def _drift_run(lag2, n: int = 300, edge: bool = False, skip_at: int | None = None, sync: bool = False,
               **kw) -> Run:
    """Cameras 0 and 1 answer L after each pulse, camera 2 lag2(k) after pulse k; with skip_at, camera
    2 misses that pulse without its counter showing it (its frames from then on carry one less)."""
    r = make(**kw)
    if sync:
        r.sync.synchronize()
    frames = stream({0: 0, 1: 0}, range(n), edge=edge)
    for k in range(n):
        cf = k - (1 if skip_at is not None and k >= skip_at else 0)
        if skip_at is not None and k == skip_at:
            continue
        frames.append(frame(2, cf, T0 + k * P + lag2(k), cf if edge else -1))
    r.feed(frames, poll_every=P)
    return r


def test_a_camera_4_ms_later_than_the_others_that_misses_a_pulse_is_re_mapped() -> None:
    """Camera 2 always comes 4 ms after the others (its own baseline); it misses pulse 100: re-mapped
    once, by one frame, and from then on its frames sit in the bundles of the pulses they answered,
    its numbering carried over (no discontinuity, even with max_gap_s 0.25 s)."""
    r = _drift_run(lambda k: L + 0.004, skip_at=100, max_gap_s=0.25)
    assert [(e.kind, e.camera_index) for e in r.events] == [("drift", 2)]
    assert r.events[0].message.startswith("camera 2 drifted by 1 frames") and r.events[0].message.endswith("re-mapped")
    got = cam_frames(r, 2)
    assert all(got[k] == k - 1 for k in range(150, 300))
    assert {u.reason for u in r.untracked} == {"late"} and r.sync.stats()[2].suspect == 0


def test_a_camera_5_periods_behind_the_others_that_misses_a_pulse_is_still_re_mapped() -> None:
    """Camera 2 comes 86 ms (5.5 periods) after the others: its arrivals are still compared (the check
    waits drift_settle_s, 0.5 s, for a camera's frames), so a pulse it misses is found and re-mapped."""
    r = _drift_run(lambda k: L + 5.5 * P, skip_at=100, sync=True, deadline_fraction=7.0)
    assert [(e.kind, e.camera_index) for e in r.events] == [("drift", 2)]
    got = cam_frames(r, 2)
    assert all(got[k] == k - 1 for k in range(200, 290))


def test_a_latency_step_that_is_not_whole_periods_is_no_drift() -> None:
    """Camera 2's arrivals move 1.35 periods later at trigger frame 100 (its link got slower): not a
    whole number of periods, so not a missed pulse: no drift, its frames keep their mapping."""
    r = _drift_run(lambda k: L + (1.35 * P if k >= 100 else 0.0), deadline_fraction=2.0)
    assert not r.events
    got = cam_frames(r, 2)
    assert len(got) == 300 and all(got[k] == k for k in range(300))


def test_a_camera_whose_latency_creeps_up_slowly_is_followed_not_re_mapped() -> None:
    """Camera 2 comes 3 ms after the others, then ever later, by 12 ms over 8 s (a link filling up):
    its baseline follows, no drift is reported, and its frames keep their mapping."""
    n = 600
    r = _drift_run(lambda k: L + 0.003 + 0.012 * min(1.0, max(0, k - 64) / 512), n=n, deadline_fraction=1.5)
    assert not r.events
    got = cam_frames(r, 2)
    assert len(got) == n and all(got[k] == k for k in range(n))


def test_an_edge_numbered_camera_12_ms_behind_that_falls_a_period_behind_is_reported_once() -> None:
    """Camera 2 numbers its frames by its edge and comes 12 ms after the others; from trigger frame 100
    its frames come a period later still: a drift, reported once (the edge's numbers are kept), its
    baseline moved by that period, so nothing more is reported."""
    r = _drift_run(lambda k: L + 0.012 + (P if k >= 100 else 0.0), n=400, edge=True, deadline_fraction=3.0)
    assert [(e.kind, e.camera_index) for e in r.events] == [("drift", 2)]
    assert not r.events[0].message.endswith("re-mapped")
    assert all(cam_frames(r, 2)[k] == k for k in range(400))


def test_in_a_two_camera_rig_one_misnumbered_frame_does_not_move_the_frame_times() -> None:
    """Two edge-numbered cameras; camera 1's frame for pulse 50 carries number 51 (so it comes a period
    before pulse 51). Frame times follow the second earliest arrival of a bundle, so that one frame
    cannot pull the fixed-rate clock a period earlier: the times stay on the arrivals."""
    r = make(cams=(0, 1), deadline_fraction=1.5)  # bundle 51 waits for camera 0's frame
    frames = stream({0: 0, 1: 0}, range(100), edge=True, lag={0: L, 1: L + 0.0003})
    for f in frames:
        if f.camera_index == 1 and f.camera_frame == 50:
            f.trigger_frame = 51
    r.feed(frames, poll_every=P)
    assert sorted(r.by_tf()[51].frames) == [0, 1]
    err = [b.bundle.timestamp - (T0 + b.bundle.trigger_frame * P + L) for b in r.bundles]
    assert len(r.bundles) == 100 and max(abs(e) for e in err) < 1e-9, (min(err), max(err))


def test_one_frame_held_up_in_the_network_does_not_misplace_a_camera_joining_right_after() -> None:
    """Camera 0's frame 40 comes 0.4 s late. The lag estimate moves by at most 2 periods x 0.1 for it,
    so camera 2, first seen right after that frame, is placed by the others' usual 4 ms lag: its frames
    sit in the bundles of the pulses they answered."""
    lag = {0: 2.0**-8, 1: 2.0**-8}
    r = make(clock=FixedRateClock(FPS, start_time=T0))
    frames = stream({0: 0, 1: 0}, range(100), lag=lag)
    for f in frames:
        if f.camera_index == 0 and f.camera_frame == 40:
            f.recv_time += 0.4
    frames += [frame(2, 300 + k, T0 + k * P + 2.0**-8 + 0.0002) for k in range(66, 100)]
    r.feed(frames, poll_every=P)
    got = cam_frames(r, 2)
    assert all(got[k] == 300 + k for k in range(67, 100)), sorted(got.items())[:3]
    # Its first frame came after the others completed bundle 66 (it was not waited for): late.
    assert [(u.frame.camera_index, u.trigger_frame, u.reason) for u in r.untracked] == [
        (0, 40, "late"), (2, 66, "late")]


def test_a_camera_without_numbers_first_seen_when_an_edge_numbered_one_is_at_frame_1_is_frame_1() -> None:
    """Camera 0's edge numbers its frames and its first is trigger frame 1 (the trigger was running);
    camera 1, numbered by its counter, is first seen right after: not tied to frame 0 but placed by
    arrival at frame 1, and its frames go on in step with camera 0's."""
    r = make(cams=(0, 1))
    frames = [frame(0, 50 + k, T0 + k * P + L, k) for k in range(1, 40)]
    frames += [frame(1, 900 + k, T0 + k * P + L + 0.0003) for k in range(1, 40)]
    r.feed(frames, poll_every=P)
    assert all(cam_frames(r, 1)[k] == 900 + k for k in range(1, 40))
    assert all(b.closed_by == "complete" for b in r.bundles) and len(r.bundles) == 39


def test_an_early_frame_must_come_more_than_the_early_threshold_before_its_camera_usually_does() -> None:
    """early_fraction 1, early_slack_s 0 (the threshold is exactly a period): an edge-numbered frame
    claiming the next pulse arrives exactly a period earlier than its camera's usual lag: not early
    (it is accepted); two periods earlier: early."""
    for ahead, want in ((1, []), (2, ["early"])):
        r = make(clock=OffsetClock(), early_fraction=1.0, early_slack_s=0.0)
        frames = stream({0: 0, 1: 0, 2: 0}, range(20), edge=True)
        for f in frames:
            if f.camera_index == 1 and f.camera_frame == 10:
                f.trigger_frame += ahead
        r.feed([f for f in frames if f.camera_frame <= 10], poll_every=P)
        assert [u.reason for u in r.untracked] == want, ahead


def test_trigger_frames_no_camera_delivered_leave_nothing_behind_and_drift_is_still_checked() -> None:
    """Every camera loses the same trigger frames (60 in a row, then 20 single ones): the drift check
    skips them, keeps no record of them (its memory stays within drift_settle_s of frames), and still
    finds camera 2's missed pulse afterwards."""
    r = make()
    lost = set(range(100, 160)) | set(range(200, 400, 10))
    frames = [f for f in stream({0: 0, 1: 0}, range(600)) if f.camera_frame not in lost]
    frames += [frame(2, k - (1 if k >= 450 else 0), T0 + k * P + L) for k in range(600) if k not in lost and k != 450]
    most = 0
    for f in sorted(frames, key=lambda f: f.recv_time):
        r.feed([f], poll_every=P)
        most = max(most, len(r.sync._arrivals))
    assert [(e.kind, e.camera_index) for e in r.events] == [("drift", 2)]
    assert all(cam_frames(r, 2)[k] == k - 1 for k in range(520, 600))
    # Arrival records: at most those of the frames not settled yet; none once all came and compared.
    assert most <= r.sync.drift_settle + 2 and len(r.sync._arrivals) == 0


def test_a_counter_jump_soon_after_synchronize_is_re_mapped_by_arrival_not_tied_to_frame_0() -> None:
    """After synchronize(), camera 1's counter jumps by 5000 at trigger frame 10 (0.16 s in, inside the
    frame-0 tie window): once confirmed (its third frame), it is mapped by arrival, and its next frames
    sit in the bundles of the pulses they answered."""
    r = make()
    r.sync.synchronize()
    frames = stream({0: 0, 2: 0}, range(60)) + [frame(1, k + (5000 if k >= 10 else 0), T0 + k * P + L)
                                                 for k in range(60)]
    r.feed(frames, poll_every=P)
    assert [(e.kind, e.camera_index) for e in r.events] == [("clock_jump", 1)]
    assert all(cam_frames(r, 1)[k] == 5000 + k for k in range(13, 60))
