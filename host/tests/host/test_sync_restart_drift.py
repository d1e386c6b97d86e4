"""The synchroniser's placement of a restarted edge and its drift check, behaviour by behaviour: when a
restarted edge counts as caught up (paced), the lag it is placed by, its placement without a clock
estimate, the pulses it missed; when a run of arrivals a period off is a drift and when it is a
burst; when the drift baseline is learnt; the lag estimate that places late joiners. Also the
contracts of the output types and the windows the checks read.

Frames are fed with explicit times (nothing timed, nothing slept), built by sync_builders.py:
64 fps from T0 = 1024 s, so most times are exact binary fractions and a boundary is tested exactly.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from flytrack_host.intake.sync import FixedRateClock, FrameSynchronizer, SyncOutput, _LagWindow

sys.path.insert(0, str(Path(__file__).parent))
from sync_builders import FPS, LAG8, T0, L, NotReadyClock, P, Run, cam_frames, frame, make, stream  # noqa: E402

# --- a restarted edge: when it counts as caught up --------------------------------------------------


def _restarted(arrive, n: int = 40, first_tf: int = 30, lag: dict[int, float] | None = None, clock=None,
               sync: bool = False, **kw) -> tuple[Run, int | None]:
    """Cameras 0 and 2 answer every pulse (`lag`, default L, after it); camera 1 answers pulses 0-19,
    then its edge restarts: its camera frame i answers pulse first_tf + i and arrives at arrive(i).
    Fed in arrival order (cameras 0 and 2 first at equal times), no polling. Returns the run and the
    camera frame on whose arrival camera 1 was placed (None: still held after n frames)."""
    r = make(clock=clock if clock is not None else FixedRateClock(FPS, start_time=T0), **kw)
    if sync:
        r.sync.synchronize()
    end = first_tf + n + 20
    frames = stream({0: 0, 2: 0}, range(end), lag=lag) + stream({1: 0}, range(20), lag=lag)
    for i in range(n):
        f = frame(1, i, arrive(i))
        f.restarted = i == 0
        frames.append(f)
    placed_on = None
    for f in sorted(frames, key=lambda f: f.recv_time):
        r.add(f)
        if placed_on is None and r.kinds("restart"):
            placed_on = f.camera_frame
    return r, placed_on


def _pulse(k: int) -> float:
    return T0 + k * P


def test_a_restarted_edge_delivering_in_pairs_is_paced_once_most_of_its_gaps_are_half_a_period() -> None:
    """The new edge has caught up but its link delivers two frames at once (1 ms apart), a pair every
    two periods: half its gaps are short. Camera frame 1 gives the lowest bound (trigger frame 30 for
    its frame 0); the edge counts as paced once 10 frames followed it and most (5) of the last 9 gaps
    were half a period or more: on its 13th frame (frame 12), not its 12th (4 of 9)."""
    r, on = _restarted(lambda i: _pulse(31 + i - i % 2) + L + 0.001 * (i % 2))
    assert on == 12
    assert r.kinds("restart")[0].message == ("camera 1: edge restarted; its camera frame 0 is trigger frame 30 "
                                             "(by arrival); 10 trigger frames missed while it was down")
    got = cam_frames(r, 1)
    assert all(got[30 + i] == i for i in range(13, 40))


def test_gaps_of_exactly_half_a_period_count_as_paced() -> None:
    """The pairs come half a period apart exactly (gaps 0.5 and 1.5 periods): every gap counts as
    paced ("half a period or more"), so the edge is placed on its 12th frame, 10 after the lowest
    bound."""
    r, on = _restarted(lambda i: _pulse(31 + i - i % 2) + L + (0.25 if i % 2 else -0.25) * P)
    assert on == 11
    assert "its camera frame 0 is trigger frame 30 (by arrival); 10 trigger frames missed" in \
        r.kinds("restart")[0].message


def test_a_restarted_edge_delivering_in_threes_is_held_until_restart_hold_frames() -> None:
    """Three frames at once every three periods: only a third of the gaps are half a period or more,
    not most: never paced; held until restart_hold_frames (20) and then placed by its lowest bound,
    which is right (frame 2 of the first batch arrived on time)."""
    r, on = _restarted(lambda i: _pulse(32 + i - i % 3) + L + 0.001 * (i % 3), restart_hold_frames=20)
    assert on == 19
    assert "its camera frame 0 is trigger frame 30 (by arrival)" in r.kinds("restart")[0].message


def test_with_an_even_settle_count_half_the_gaps_paced_is_enough() -> None:
    """restart_settle_frames 5: the edge delivering in pairs has exactly 2 of its last 4 gaps half a
    period or more, always: half counts as paced (it is not held to restart_hold_frames), so it is
    placed 5 frames after its lowest bound."""
    r, on = _restarted(lambda i: _pulse(31 + i - i % 2) + L + 0.001 * (i % 2), restart_settle_frames=5)
    assert on == 6
    assert "its camera frame 0 is trigger frame 30 (by arrival)" in r.kinds("restart")[0].message


# --- a restarted edge: where it is placed ---------------------------------------------------------


def test_without_a_clock_estimate_a_restarted_edge_is_placed_at_the_newest_trigger_frame_delivered() -> None:
    """The trigger clock model has no estimate (a restart of the trigger link), so no held frame gives
    a bound: the edge is placed once 10 frames came paced, its newest frame (camera frame 10) at the
    newest trigger frame the other cameras delivered (40): frame 0 is trigger frame 30, 10 missed."""
    r, on = _restarted(lambda i: _pulse(30 + i) + L, clock=NotReadyClock(), sync=True)
    assert on == 10
    assert r.kinds("restart")[0].message == ("camera 1: edge restarted; its camera frame 0 is trigger frame 30 "
                                             "(by arrival); 10 trigger frames missed while it was down")
    got = cam_frames(r, 1)
    assert all(got[30 + i] == i for i in range(11, 40))


def test_held_frames_without_a_clock_estimate_are_placed_and_recorded_at_stop() -> None:
    """No clock estimate, and the run stops after the restarted edge's 6th frame (still held: fewer
    than 10 came after the first): flush() places it by its newest frame at the newest trigger frame
    delivered (35, camera frame 5) and records every held frame with that numbering."""
    r = make(clock=NotReadyClock())
    r.sync.synchronize()
    frames = stream({0: 0, 2: 0}, range(36)) + stream({1: 0}, range(20))
    for i in range(6):
        f = frame(1, i, _pulse(30 + i) + L)
        f.restarted = i == 0
        frames.append(f)
    r.feed(frames)
    assert not r.kinds("restart")
    r.take(r.sync.flush())
    assert r.kinds("restart")[0].message.startswith("camera 1: edge restarted; its camera frame 0 is trigger "
                                                     "frame 30 (by arrival); 10 trigger frames missed")
    mine = sorted((u.trigger_frame, u.frame.camera_frame) for u in r.untracked if u.frame.camera_index == 1)
    mine += sorted((tf, cf) for tf, cf in cam_frames(r, 1).items() if tf >= 30)
    assert sorted(mine) == [(30 + i, i) for i in range(6)]


def test_a_restarted_edge_is_placed_by_the_fastest_camera_not_the_rigs_median_lag() -> None:
    """Camera 2 sits on a slow link (25 ms after each pulse, over 1.5 periods), camera 0 answers 2 ms
    after it; the restarted edge of camera 1 answers 2.5 ms after. A frame cannot come before its
    pulse plus the least lag: placed by camera 0's lag (frame 0 at trigger frame 30, right), not by
    the median of the others' (13.5 ms would place it a pulse early)."""
    r, on = _restarted(lambda i: _pulse(30 + i) + L + 0.0005, lag={0: L, 1: L, 2: 0.025}, sync=True)
    assert on == 10
    assert "its camera frame 0 is trigger frame 30 (by arrival); 10 trigger frames missed" in \
        r.kinds("restart")[0].message


def test_a_restarted_edge_is_placed_by_what_the_other_cameras_deliver_now() -> None:
    """From pulse 25 every camera's frames come 20 ms later than before (a busier host), while camera
    1's edge is down; it restarts at pulse 30. It is placed by the lag the others have now (their last
    frames), not by the least over the last second (2 ms, which would place it a pulse late)."""
    slow = 0.020

    def lagged(cam: int, k: int) -> float:
        return _pulse(k) + L + (slow if k >= 25 else 0.0) + (0.0005 if cam == 1 else 0.0)

    r = make(clock=FixedRateClock(FPS, start_time=T0))
    frames = [frame(c, k, lagged(c, k)) for k in range(90) for c in (0, 2)]
    frames += [frame(1, k, lagged(1, k)) for k in range(20)]
    for i in range(60):
        f = frame(1, i, lagged(1, 30 + i))
        f.restarted = i == 0
        frames.append(f)
    r.feed(frames)
    assert "its camera frame 0 is trigger frame 30 (by arrival); 10 trigger frames missed" in \
        r.kinds("restart")[0].message


def test_an_edge_placed_ahead_at_restart_hold_is_moved_back_and_its_missed_count_corrected() -> None:
    """restart_hold_frames 11: camera 1's new edge starts 15 pulses late and works off its queue 2 ms
    a frame, so it is still behind when its 11th frame forces the placement, by the lowest bound so
    far: ahead. Once its frames come on time they arrive periods before their mapped pulses, against
    the other cameras: moved back (within 3 s of the restart), and the pulses it missed are counted
    from the right mapping (10), not the ahead one."""
    start = _pulse(45) + L
    r, on = _restarted(lambda i: max(_pulse(30 + i) + L, start + 0.002 * i), n=100, restart_hold_frames=11)
    assert on == 10
    ahead = r.kinds("ahead")
    assert len(ahead) == 1 and ahead[0].message.endswith("ahead of their arrival against the other cameras "
                                                         "(after its restart): re-mapped")
    st = r.sync.stats()[1]
    assert (st.restarts, st.ahead, st.missed) == (1, 1, 10)
    got = cam_frames(r, 1)
    assert all(got[30 + i] == i for i in range(60, 100))


# --- the drift check: paced evidence only, and a baseline learnt when steady ----------------------


def _stall_run(release: dict[int, float], spacing: float, n: int = 160, stall: tuple[int, int] = (60, 80),
               **kw) -> Run:
    """Three cameras answer each pulse L after it; every camera stalls over the pulses stall[0] to
    stall[1] - 1, then camera c works off its queue from pulse stall[1] + release[c] periods, one frame
    `spacing` s after the other, and is on time again after it. drift_min_s 0.1: the evidence for a
    drift is 10 trigger frames (drift_frames), fewer than the stall holds."""
    r = make(clock=FixedRateClock(FPS, start_time=T0), drift_min_s=0.1, **kw)
    frames = []
    for c in (0, 1, 2):
        for k in range(n):
            t = _pulse(k) + L
            if k >= stall[0]:
                t = max(t, _pulse(stall[1]) + L + release[c] * P + (k - stall[0]) * spacing)
            frames.append(frame(c, k, t))
    r.feed(frames, poll_every=P)
    return r


@pytest.mark.parametrize("spacing", [0.0001, 0.45 * P])
def test_a_stall_whose_cameras_resume_a_period_apart_is_no_drift(spacing: float) -> None:
    """Every camera stalls 20 periods (a scheduler stall); cameras 0 and 1 resume together, camera 2 a
    period later, each working off its queue (at once, or a frame every 0.45 period: faster than half
    the pulse rate). Over all 20 queued trigger frames camera 2 comes a whole period after the others,
    but its frames came bunched, not paced: no drift, nothing re-mapped, every frame on its pulse."""
    r = _stall_run({0: 0.0, 1: 0.0, 2: 1.0}, spacing)
    assert not r.kinds("drift"), [e.message for e in r.kinds("drift")]
    assert all(cam_frames(r, 2)[k] == k for k in range(100, 160))
    assert {u.frame.camera_frame for u in r.untracked} <= set(range(60, 100))


def test_the_drift_baseline_is_learnt_only_once_the_camera_arrives_steadily() -> None:
    """Camera 2 is on a faster link than cameras 0 and 1 (it arrives 0.45 period before them). For its
    first 1.5 s the link is congested: three frames in four come 0.9 period later than usual (0.45
    period after the others). Its arrivals against the others then spread over most of a period, so
    no baseline is learnt from them (one learnt there would sit 0.9 period off and report a drift
    once the link is steady); it is learnt once they are steady: no drift, every frame on its pulse."""
    r = make(clock=FixedRateClock(FPS, start_time=T0), deadline_fraction=1.5)
    frames = stream({0: 0, 1: 0}, range(300), lag={0: L + 0.45 * P, 1: L + 0.45 * P})
    frames += [frame(2, k, _pulse(k) + L + (0.9 * P if k < 96 and k % 4 else 0.0)) for k in range(300)]
    r.feed(frames, poll_every=P)
    assert not r.events, [e.message for e in r.events]
    got = cam_frames(r, 2)
    assert len(got) == 300 and all(got[k] == k for k in range(300))
    assert r.sync.cams[2].rel_base == pytest.approx(-0.45 * P, abs=0.05 * P)


def _drift_frames(cam2: list[tuple[int, float]], n: int = 300, lag2: float = L, **kw) -> Run:
    """Cameras 0 and 1 answer every pulse L after it; camera 2 sends (camera frame, arrival) as given."""
    r = make(clock=FixedRateClock(FPS, start_time=T0), **kw)
    frames = stream({0: 0, 1: 0}, range(n)) + [frame(2, cf, t) for cf, t in cam2]
    r.feed(frames, poll_every=P)
    return r


def test_a_camera_that_counts_an_extra_pulse_is_the_only_one_re_mapped() -> None:
    """Camera 2 arrives 4 ms after the others; a glitch on its trigger line between pulses 99 and 100
    makes it send one frame more, so from then on its counter is one ahead and its frames come a
    period before the others' of the same mapped trigger frame. It alone is re-mapped, by -1 (the
    other cameras, compared with it among others, keep their mapping), and its frames after that sit
    in the bundles of the pulses they answered."""
    cam2 = [(k, _pulse(k) + L + 0.004) for k in range(100)] + [(100, _pulse(99) + 0.5 * P + L + 0.004)]
    cam2 += [(k + 1, _pulse(k) + L + 0.004) for k in range(100, 300)]
    r = _drift_frames(cam2, deadline_fraction=1.5)
    assert [(e.kind, e.camera_index) for e in r.events] == [("drift", 2)], [e.message for e in r.events]
    assert r.events[0].message.startswith("camera 2 drifted by -1 frames")
    got = cam_frames(r, 2)
    assert all(got[k] == k + 1 for k in range(150, 300))
    assert all(cam_frames(r, c)[k] == k for c in (0, 1) for k in range(300))
    # Its numbering carried over to the new mapping: no frame of it taken for a discontinuity.
    assert r.sync.stats()[2].suspect == 0 and r.sync.stats()[2].clock_jumps == 0


def test_a_camera_earlier_than_the_others_that_misses_a_pulse_is_re_mapped() -> None:
    """Camera 2 arrives 6 ms before the others (a faster link: its baseline is below theirs); it misses
    pulse 100, so its frames come a period later than its baseline from then on, only 9.6 ms after the
    others'. Still a whole period off its own baseline: re-mapped by 1."""
    cam2 = [(k - (k >= 100), _pulse(k) + L - 0.006 + 0.0001) for k in range(300) if k != 100]
    r = make(clock=FixedRateClock(FPS, start_time=T0), deadline_fraction=1.5)
    frames = stream({0: 0, 1: 0}, range(300), lag={0: L + 0.006, 1: L + 0.006}) + [frame(2, cf, t) for cf, t in cam2]
    r.feed(frames, poll_every=P)
    assert [(e.kind, e.camera_index) for e in r.events] == [("drift", 2)], [e.message for e in r.events]
    assert all(cam_frames(r, 2)[k] == k - 1 for k in range(150, 300))
    assert r.sync.stats()[2].suspect == 0 and r.sync.stats()[2].clock_jumps == 0


def test_a_camera_whose_arrivals_jitter_by_a_quarter_period_that_misses_a_pulse_is_re_mapped() -> None:
    """Camera 2's arrivals against the others alternate 0.24 period early and late (a jittery link);
    it misses pulse 100. Its baseline follows the jitter's middle, not its last frame, so every frame
    after the missed pulse sits within 0.4 period of a whole period off it: re-mapped by 1."""
    cam2 = [(k - (k >= 100), _pulse(k) + L + 0.004 + (0.24 * P if k % 2 else -0.24 * P))
            for k in range(300) if k != 100]
    r = _drift_frames(cam2, deadline_fraction=1.5)
    assert [(e.kind, e.camera_index) for e in r.events] == [("drift", 2)], [e.message for e in r.events]
    assert all(cam_frames(r, 2)[k] == k - 1 for k in range(200, 300))


@pytest.mark.parametrize("edge", [False, True])
def test_in_a_three_camera_rig_a_camera_that_misses_two_pulses_is_the_only_one_re_mapped(edge: bool) -> None:
    """Three cameras; camera 2 misses pulses 100 and 101. Each camera is compared with the mean of the
    two others, which camera 2 moves by a whole period: cameras 0 and 1 looked a period early and were
    re-mapped by -1 with it (every camera misnumbered from then on). The camera furthest off is the
    one that drifted: only camera 2 is reported, re-mapped by 2 (or, numbered by its edge, its
    arrivals compared two periods earlier from then on), and every frame sits on its pulse."""
    cam2 = [(k - 2 * (k >= 100), _pulse(k) + L) for k in range(300) if k not in (100, 101)]
    r = make(clock=FixedRateClock(FPS, start_time=T0), deadline_fraction=4.0 if edge else 1.5)
    frames = stream({0: 0, 1: 0}, range(300), edge=edge) + [frame(2, cf, t, cf if edge else -1) for cf, t in cam2]
    r.feed(frames, poll_every=P)
    r.poll(_pulse(310))
    assert [(e.kind, e.camera_index) for e in r.events] == [("drift", 2)], [e.message for e in r.events]
    assert r.events[0].message.startswith("camera 2 drifted by 2 frames")
    assert r.events[0].message.endswith("; re-mapped") != edge
    assert all(cam_frames(r, c)[k] == k for c in (0, 1) for k in range(300))
    assert all(cam_frames(r, 2)[k] == k - (0 if edge else 2) for k in range(150, 300) if k in cam_frames(r, 2))
    assert len(cam_frames(r, 2)) >= 250


def test_in_a_six_camera_rig_two_cameras_given_an_extra_pulse_are_the_only_ones_re_mapped() -> None:
    """Six cameras; a glitch on a trigger line shared by cameras 4 and 5 gives both an extra pulse
    between pulses 99 and 100: from then on their frames come a period before the others' of the same
    mapped trigger frame. Each camera is compared with the median of the five others, which two early
    cameras do not move: only cameras 4 and 5 are re-mapped (by -1), the others keep their mapping."""
    cams = (0, 1, 2, 3, 4, 5)
    r = make(cams=cams, clock=FixedRateClock(FPS, start_time=T0), deadline_fraction=1.5)
    frames = stream({0: 0, 1: 0, 2: 0, 3: 0}, range(300))
    for c in (4, 5):
        frames += [frame(c, k, _pulse(k) + L) for k in range(100)] + [frame(c, 100, _pulse(99) + 0.5 * P + L)]
        frames += [frame(c, k + 1, _pulse(k) + L) for k in range(100, 300)]
    r.feed(frames, poll_every=P)
    assert sorted((e.kind, e.camera_index) for e in r.events) == [("drift", 4), ("drift", 5)], \
        [e.message for e in r.events]
    assert all(cam_frames(r, c)[k] == k for c in (0, 1, 2, 3) for k in range(300))
    assert all(cam_frames(r, c)[k] == k + 1 for c in (4, 5) for k in range(150, 299))


def test_a_baseline_is_learnt_from_arrivals_spread_over_exactly_half_a_period() -> None:
    """Camera 2 comes alternately with the others and half a period after them (exactly: 64 fps, binary
    times): a spread of half a period still gives a baseline (its middle), so when it misses pulse 100
    the whole-period move is found and it is re-mapped."""
    cam2 = [(k - (k >= 100), _pulse(k) + L + (0.5 * P if k % 2 else 0.0)) for k in range(300) if k != 100]
    r = _drift_frames(cam2, deadline_fraction=1.5)
    assert [(e.kind, e.camera_index) for e in r.events] == [("drift", 2)], [e.message for e in r.events]
    assert all(cam_frames(r, 2)[k] == k - 1 for k in range(200, 300))


def test_a_move_of_a_period_and_a_quarter_is_still_a_missed_pulse() -> None:
    """Camera 2 misses pulse 100 and its link gets a quarter period slower at the same moment: its
    frames come 1.25 periods later than its baseline (exactly: binary times), the median within a
    quarter period of a whole one and every frame within 0.4: a drift of 1, re-mapped."""
    cam2 = [(k - (k >= 100), _pulse(k) + L + (0.25 * P if k > 100 else 0.0)) for k in range(300) if k != 100]
    r = _drift_frames(cam2, deadline_fraction=1.5)
    assert [(e.kind, e.camera_index) for e in r.events] == [("drift", 2)], [e.message for e in r.events]
    assert all(cam_frames(r, 2)[k] == k - 1 for k in range(200, 300))


def test_a_camera_late_by_a_period_four_frames_in_five_is_not_re_mapped() -> None:
    """Camera 2's link is congested for 2 s: four frames in five come a period late, every fifth on time.
    The median of its arrivals against the others sits a whole period off, but not every frame does:
    a missed pulse moves every frame, so this is no drift, and its mapping is kept."""
    cam2 = [(k, _pulse(k) + L + (P if 50 <= k < 178 and k % 5 else 0.0)) for k in range(300)]
    r = _drift_frames(cam2, deadline_fraction=2.0)
    assert not r.kinds("drift"), [e.message for e in r.kinds("drift")]
    got = cam_frames(r, 2)
    assert len(got) == 300 and all(got[k] == k for k in range(300))


def test_a_camera_that_misses_two_pulses_at_once_is_re_mapped_by_two() -> None:
    """Four cameras; camera 2 misses pulses 100 and 101 (its counter shows neither): re-mapped by 2 in
    one step; the event says by how many frames, how far off its frames came (two periods, 31.2 ms)
    and over how many trigger frames (drift_frames: 32 at 64 fps)."""
    cam2 = [(k - 2 * (k >= 100), _pulse(k) + L) for k in range(300) if k not in (100, 101)]
    r = make(cams=(0, 1, 2, 3), clock=FixedRateClock(FPS, start_time=T0), deadline_fraction=1.5)
    r.feed(stream({0: 0, 1: 0, 3: 0}, range(300)) + [frame(2, cf, t) for cf, t in cam2], poll_every=P)
    assert [e.message for e in r.events] == [
        "camera 2 drifted by 2 frames: its frames arrive 31.2 ms off the other cameras' over 32 trigger "
        "frames; re-mapped"]
    assert all(cam_frames(r, 2)[k] == k - 2 for k in range(150, 300))
    assert r.sync.stats()[2].drift == 1


def test_a_late_joiner_is_placed_by_the_others_usual_lag_not_their_last_frames() -> None:
    """Every other frame of cameras 0 and 1 comes 0.6 period late (host scheduling); camera 2 joins with
    a frame that arrives right after one of those late frames. It is placed by the lag the others
    usually have (a late frame moves the estimate by a tenth of its delay), not by their latest
    frame's (which would place it a pulse early): its frames sit in the bundles of the pulses they
    answered."""
    r = make(clock=FixedRateClock(FPS, start_time=T0), deadline_fraction=1.0)
    frames = [frame(c, k, _pulse(k) + L + (0.6 * P if k % 2 else 0.0)) for k in range(120) for c in (0, 1)]
    frames += [frame(2, 500 + k, _pulse(k) + L - 0.0002) for k in range(60, 120)]
    r.feed(frames, poll_every=P)
    got = cam_frames(r, 2)
    assert all(got[k] == 500 + k for k in range(61, 120)), sorted(got.items())[:3]


@pytest.mark.parametrize("join", [20, 40])
def test_a_camera_joining_after_a_start_whose_first_frames_queued_is_placed_right(join: int) -> None:
    """Cameras 0 and 1 start with their first 0.3 s of frames queued (delivered at once, 0.3 s after the
    first pulse; tied to frame 0), then on time. Camera 2 joins at pulse `join`, 0.3-0.6 s in. The
    lag estimate starts from those queued frames, but a frame cannot come before its pulse: the first
    on-time frame brings it down at once. Before, it came down 0.2 period a frame, so camera 2 was
    placed 15 (11) pulses behind, where nothing moves a camera back: every frame of it late, none
    tracked. Now every frame of it sits on its pulse."""
    r = make(clock=FixedRateClock(FPS, start_time=T0))
    frames = [frame(c, k, max(_pulse(k) + L, _pulse(0) + 0.3 + 0.0001 * k)) for c in (0, 1) for k in range(200)]
    frames += [frame(2, 500 + k, _pulse(k) + L + 0.0002) for k in range(join, 200)]
    r.feed(frames, poll_every=P)
    got = cam_frames(r, 2)
    assert len(got) >= 200 - join - 1 and all(got[k] == 500 + k for k in got)


# --- host times from zero; the output types; the lag window's cut-off -------------------------------


def test_with_host_times_from_zero_a_camera_mapped_ahead_is_moved_back_within_its_first_second() -> None:
    """Host times counted from 0 (a re-tracked recording's clock): camera 2 joins at pulse 10 with its
    first 8 frames 70 ms late, 6 ms apart, so it is placed 4 pulses ahead. The mapped-ahead check runs
    from the first frame on (not from 1 s of host time): it is moved back within 0.5 s, and its frames
    from pulse 32 on sit in the bundles of the pulses they answered."""
    s = FrameSynchronizer((0, 1, 2), FPS, clock=FixedRateClock(FPS, start_time=0.0))
    r = Run(s)
    frames = [frame(c, k, k * P + L) for k in range(64) for c in (0, 1)]
    frames += [frame(2, 300 + k, max(k * P + L, 10 * P + 0.070 + (k - 10) * 0.006)) for k in range(10, 64)]
    r.feed(frames, poll_every=P)
    assert [e.message for e in r.kinds("ahead")] == [
        "camera 2: frames numbered 4 ahead of their arrival against the other cameras: re-mapped"]
    got = cam_frames(r, 2)
    assert all(got[k] == 300 + k for k in range(32, 64)), sorted(got.items())


def test_every_output_is_a_sync_output_and_a_misspelt_field_fails_loudly() -> None:
    """A consumer dispatches on SyncOutput (bundles, untracked frames, events); the output types take
    no attribute they do not define (slots): `frame.restart = True` for `restarted` raises instead of
    being silently ignored, and no per-frame dict is kept."""
    r = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(5)) + [frame(1, 2, T0 + 5 * P + L)]
    for f in sorted(frames, key=lambda f: f.recv_time):
        assert all(isinstance(o, SyncOutput) for o in r.add(f))
    r.poll(T0 + 2.0)
    assert r.bundles and r.untracked and r.events
    assert not isinstance(frames[0], SyncOutput)
    for obj in (frames[0], r.bundles[0], r.untracked[0], r.events[0]):
        with pytest.raises(AttributeError):
            obj.restart = True  # type: ignore[union-attr]
        assert not hasattr(obj, "__dict__")


def test_the_lag_windows_cut_off_keeps_a_frame_that_arrived_exactly_at_it() -> None:
    """min_lag(since=t) counts the entries that arrived at or after t, as the window's pruning keeps a
    frame exactly lag_window_s old: one arriving exactly at the cut-off is still counted."""
    w = _LagWindow([(10.0, 0.0, 0), (10.5, 0.0, 1), (11.0, 0.0, 2)])
    # Frame f's pulse at 9.99 + 0.5 f: lags 10, 20 and 30 ms.
    assert w.min_lag(9.99, 0, 0.49) == pytest.approx(0.010)
    assert w.min_lag(9.99, 0, 0.49, since=10.5) == pytest.approx(0.020)
    assert w.min_lag(9.99, 0, 0.49, since=10.5000001) == pytest.approx(0.030)
    assert w.min_lag(9.99, 0, 0.49, since=11.5) == float("inf")


def test_an_edge_restarted_again_while_its_first_frames_are_held_loses_none_of_them() -> None:
    """Camera 1's edge restarts at pulse 30, sends 5 frames (held: not caught up yet) and restarts again
    at pulse 60. The 5 held frames are placed by their best bound and recorded (they were dropped
    before), then the second restart is held and placed as usual: two restarts, every frame counted
    once, the first restart's frames on their pulses, 10 + 25 pulses missed."""
    r = make(clock=FixedRateClock(FPS, start_time=T0))
    frames = stream({0: 0, 2: 0}, range(120)) + stream({1: 0}, range(20))
    for start, n in ((30, 5), (60, 50)):
        for i in range(n):
            f = frame(1, i, _pulse(start + i) + L)
            f.restarted = i == 0
            frames.append(f)
    r.feed(frames, poll_every=P)
    r.take(r.sync.flush())
    assert [e.message for e in r.kinds("restart")] == [
        "camera 1: edge restarted; its camera frame 0 is trigger frame 30 (by arrival); 10 trigger frames "
        "missed while it was down",
        "camera 1: edge restarted; its camera frame 0 is trigger frame 60 (by arrival); 25 trigger frames "
        "missed while it was down"]
    recorded = {(u.trigger_frame, u.frame.camera_frame) for u in r.untracked if u.frame.camera_index == 1}
    recorded |= set(cam_frames(r, 1).items())
    assert {(30 + i, i) for i in range(5)} <= recorded and {(60 + i, i) for i in range(50)} <= recorded
    st = r.sync.stats()[1]
    assert (st.frames, st.restarts, st.missed) == (75, 2, 35)


class _RestartingClock:
    """A trigger clock model that knows the pulses (pulse f at T0 + f / FPS) except while `ready` is
    False (the model restarted after a jump and waits for new snapshots)."""

    def __init__(self) -> None:
        self.ready = True

    def frame_to_host_time(self, frame: int) -> float:
        return T0 + frame * P if self.ready else float("nan")


def test_a_restart_held_while_the_clock_model_restarted_is_placed_at_stop_by_its_newest_frame() -> None:
    """Every camera answers 8 ms after its pulse. Camera 1's edge restarts at pulse 30 just as the
    trigger clock model restarts (no estimate): its 5 frames give no bound and are held. The model is
    back by the time the run stops (flush): the held frames are placed by the newest one's arrival
    minus the others' usual lag (8 ms) under the model as it is then: frame 0 at trigger frame 30."""
    clock = _RestartingClock()
    r = make(clock=clock)
    frames = stream({0: 0, 2: 0}, range(38), lag=LAG8) + stream({1: 0}, range(20), lag=LAG8)
    for i in range(5):
        f = frame(1, i, _pulse(30 + i) + 0.008)
        f.restarted = i == 0
        frames.append(f)
    for f in sorted(frames, key=lambda f: f.recv_time):
        clock.ready = f.recv_time < _pulse(29)
        r.add(f)
    assert not r.kinds("restart")
    clock.ready = True
    r.take(r.sync.flush())
    assert r.kinds("restart")[0].message.startswith("camera 1: edge restarted; its camera frame 0 is trigger "
                                                    "frame 30 (by arrival); 10 trigger frames missed")
    recorded = {(u.trigger_frame, u.frame.camera_frame) for u in r.untracked if u.frame.camera_index == 1}
    assert recorded | set(cam_frames(r, 1).items()) >= {(30 + i, i) for i in range(5)}
