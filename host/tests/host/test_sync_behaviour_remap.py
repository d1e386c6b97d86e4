"""The frame synchroniser re-mapping a camera by arrival, behaviour by behaviour: a restarted edge
(held until it caught up, placed by its arrival minus the other cameras' lag, or by its own in a
one-camera rig; a restart without a gap), a camera's counter jump (also soon after synchronize()),
and the trigger's count restarting or jumping.

Frames are fed with explicit times (nothing timed, nothing slept), built by sync_builders.py: 64 fps
from T0 = 1024 s, so most times are exact binary fractions and a boundary is tested exactly.
"""

from __future__ import annotations

import sys
from pathlib import Path

from flytrack_host.intake.sync import FixedRateClock

sys.path.insert(0, str(Path(__file__).parent))  # the builders these tests share (sync_builders.py)
from sync_builders import FPS, LAG8, T0, L, P, Run, cam_frames, frame, make, stream  # noqa: E402


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


def _lagged_run(**kw) -> Run:
    """A trigger clock that knows the pulses; every camera answers 8 ms (half a period) after them."""
    return make(clock=FixedRateClock(FPS, start_time=T0), **kw)


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
