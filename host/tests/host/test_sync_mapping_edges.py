"""The frame synchroniser at the edges of its mapping rules: frames before the first pulse, frame-0
ties, counter gaps and suspect frames that must (or must not) confirm a jump, the trigger count
restarting, early and future-dated frames, the mapped-ahead check after a restart, the restart hold,
the fixed-rate clock's anchor at exactly two periods, the lag a restarted edge is placed by.

Each test feeds real frames through `FrameSynchronizer` with explicit times (nothing sleeps, nothing
is timed), reusing the frame builders of sync_builders.py: at 64 fps from 1024 s most times are
exact binary fractions, so a boundary ("within", "more than") is tested exactly.
"""

from __future__ import annotations

import sys
from pathlib import Path

from flytrack_host.intake.sync import FixedRateClock, FrameSynchronizer

sys.path.insert(0, str(Path(__file__).parent))  # the frame builders (sync_builders.py)
from sync_builders import (  # noqa: E402
    FPS,
    T0,
    L,
    NotReadyClock,
    OffsetClock,
    P,
    Run,
    cam_frames,
    frame,
    make,
    paused_run,
    stream,
)


def _reasons(r: Run, cam: int | None = None) -> list[tuple[int, int, str]]:
    return [(u.frame.camera_frame, u.trigger_frame, u.reason) for u in r.untracked
            if cam is None or u.frame.camera_index == cam]


# --- frames before the first pulse -----------------------------------------------------------------


def test_a_frame_from_before_the_first_pulse_is_late_never_a_bundle_of_its_own() -> None:
    """Camera 1's first frame (its counter at 10) is tied to trigger frame 0; its frame 9, held up in
    the network, comes right after, before camera 2's frame 0: it maps to trigger frame -1, which no
    bundle can be. It is late (recorded, not tracked), with and without synchronize(), and every
    bundle is of a pulse >= 0."""
    for sync_first in (False, True):
        r = make()
        if sync_first:
            r.sync.synchronize()
        frames = stream({0: 0, 1: 10, 2: 0}, range(20), lag={2: L + 0.001}) + [frame(1, 9, T0 + L + 0.0005)]
        r.feed(frames, poll_every=P)
        assert _reasons(r) == [(9, -1, "late")], sync_first
        assert [b.bundle.trigger_frame for b in r.bundles] == list(range(20)), sync_first
        assert r.sync.stats()[1].late == 1


def test_without_synchronize_a_camera_first_seen_exactly_0_9_period_later_is_still_frame_0() -> None:
    """Cameras already running (no synchronize()): the tie spans 0.9 period, ends included. Host
    times from 0 so that the spacing is exactly 0.9 period."""
    for dt, want in ((0.9 / FPS, 0), (0.9 / FPS + 2.0**-20, 1)):
        s = FrameSynchronizer([0, 1], FPS)
        r = Run(s)
        r.add(frame(0, 0, 0.0))
        r.add(frame(1, 70, dt))
        got = [tf for tf, p in list(s.pending.items()) + [(b.bundle.trigger_frame, b) for b in r.bundles]
               if 1 in p.frames]
        assert got == [want], (dt, got)


def test_with_no_clock_estimate_a_camera_first_seen_after_the_tie_joins_the_newest_trigger_frame() -> None:
    """No trigger clock estimate; camera 0 sent trigger frame 0 and then lost its next frames. Camera 1,
    first seen a period later (past the 0.9-period tie), cannot be placed by time: it joins the newest
    trigger frame, 0, in camera 0's bundle."""
    r = make(cams=(0, 1), clock=NotReadyClock())
    r.add(frame(0, 0, T0 + L))
    r.add(frame(1, 300, T0 + L + P))
    assert [sorted(b.frames) for b in r.bundles] == [[0, 1]] and r.bundles[0].bundle.trigger_frame == 0
    assert r.bundles[0].frames[1].camera_frame == 300


# --- future-dated frames ------------------------------------------------------------------------


def test_a_future_tolerance_below_two_frames_still_accepts_the_next_two_trigger_frames() -> None:
    """future_tolerance_s 0 with no clock estimate: the tolerance is at least 2 frames, so a frame 2
    ahead of the newest accepted trigger frame is taken, one 3 ahead is future-dated."""
    r = make(clock=NotReadyClock(), future_tolerance_s=0.0)
    for cam in (0, 1, 2):
        r.add(frame(cam, 0, T0 + L, 0))
    r.add(frame(1, 1, T0 + L + P, 3))
    r.add(frame(0, 1, T0 + L + P, 2))
    assert [(u.frame.camera_index, u.trigger_frame, u.reason) for u in r.untracked] == [(1, 3, "future")]
    assert 2 in r.sync.pending


def test_after_synchronize_with_no_clock_estimate_the_first_edge_number_is_taken_whatever_it_is() -> None:
    """synchronize() forgets the old numbering: with no clock estimate there is nothing to call the
    first frame's trigger number future-dated against, however high it is."""
    r = make(clock=NotReadyClock())
    for cam in (0, 1, 2):
        r.add(frame(cam, 0, T0 + L, 0))
    r.sync.synchronize()
    for cam in (0, 1, 2):
        r.add(frame(cam, 1, T0 + L + P, 40))
    assert not r.untracked and r.bundles[-1].bundle.trigger_frame == 40 and len(r.bundles[-1].frames) == 3


# --- counter gaps, suspects, confirming a jump ----------------------------------------------------


def test_a_max_gap_below_two_frames_still_lets_a_single_lost_frame_through() -> None:
    """max_gap_s 0: the gap allowed is at least 2 (one lost frame); a gap of 3 is a discontinuity."""
    r = make(max_gap_s=0.0)
    frames = stream({0: 0, 2: 0}, range(40)) + [f for f in stream({1: 0}, range(40))
                                                 if f.camera_frame not in (10, 20, 21)]
    r.feed(frames, poll_every=P)
    assert _reasons(r, 1)[:1] == [(22, 22, "discontinuity")]
    assert cam_frames(r, 1)[11] == 11


def test_three_suspect_frames_that_disagree_never_confirm_a_jump() -> None:
    """An edge sends three frames with trigger numbers that jump back and forth (60, 50, 65) or repeat
    (60, 60, 61) after 99: consecutive suspects must each move both counters forward to confirm a
    jump, so none is confirmed; the camera's next frames are tracked in their bundles."""
    for nums in ((60, 50, 65), (60, 60, 61)):
        r = make()
        frames = stream({0: 0, 1: 0, 2: 0}, range(150), edge=True)
        for f in frames:
            if f.camera_index == 1 and 100 <= f.camera_frame < 103:
                f.trigger_frame = nums[f.camera_frame - 100]
        r.feed(frames, poll_every=P)
        assert not r.events, nums
        assert _reasons(r) == [(100 + i, n, "discontinuity") for i, n in enumerate(nums)], nums
        assert all(cam_frames(r, 1)[k] == k for k in range(103, 150)), nums


def test_three_replayed_old_frames_out_of_order_never_re_map_a_camera() -> None:
    """Camera 1's edge replays its frames 40, 30, 45 (already tracked) after frame 100: suspect, and no
    jump (they do not go forward one after another); its mapping is kept."""
    r = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(150))
    frames += [frame(1, cf, T0 + 100 * P + L + 0.001 + i * 0.0005) for i, cf in enumerate((40, 30, 45))]
    r.feed(frames, poll_every=P)
    assert not r.events and _reasons(r) == [(40, 40, "discontinuity"), (30, 30, "discontinuity"),
                                            (45, 45, "discontinuity")]
    assert all(cam_frames(r, 1)[k] == k for k in range(150))


def test_suspect_frames_exactly_max_gap_apart_confirm_a_jump() -> None:
    """max_gap 10 frames: camera 1's counter jumps back by 40 and it loses 9 frames of every 10 right
    after: suspects exactly 10 apart still confirm the jump (on the third), and it is re-mapped."""
    r = make(max_gap_s=10 / FPS)
    frames = stream({0: 0, 2: 0}, range(120)) + stream({1: 0}, range(50))
    frames += [frame(1, k - 40, T0 + k * P + L) for k in range(50, 120) if k < 70 and k % 10 == 0 or k >= 70]
    r.feed(frames, poll_every=P)
    assert [(e.kind, e.camera_index) for e in r.events] == [("clock_jump", 1)]
    assert _reasons(r, 1) == [(10, 10, "discontinuity"), (20, 20, "discontinuity"), (30, 70, "clock_jump")]
    assert all(cam_frames(r, 1)[k] == k - 40 for k in range(71, 120))


def test_with_jump_confirm_frames_1_a_trigger_count_restart_at_0_is_one_global_jump() -> None:
    """jump_confirm_frames 1: the trigger's count restarting at 0 is confirmed by the first frame that
    carries 0: one global jump (every camera sees it: the others, a little later, take the new
    numbering on their first frame in it), numbered from 0, no camera re-mapped by arrival."""
    r = make(jump_confirm_frames=1)
    frames = stream({0: 0, 1: 0, 2: 0}, range(160), edge=True)
    for f in frames:
        if f.trigger_frame >= 100:
            f.trigger_frame -= 100
    r.feed(frames, poll_every=P)
    assert [(e.camera_index, e.global_jump, e.message) for e in r.events] == [
        (0, True, "camera 0: frame numbers jumped from trigger frame 99 to 0; mapping re-established")]
    new = [b for b in r.bundles if b.bundle.trigger_frame < 60 and b.frames[0].camera_frame >= 100]
    assert [b.bundle.trigger_frame for b in new] == list(range(1, 60))
    assert all(b.frames[c].camera_frame == b.bundle.trigger_frame + 100 for b in new for c in b.frames)


def test_a_camera_3_5_periods_behind_takes_a_trigger_count_restart_on_its_first_new_frame() -> None:
    """The trigger's count restarts at 0 (or jumps to 5000) at pulse 100; camera 2 answers 3.5 periods
    after the others, so when camera 0 confirms the jump (its third frame) camera 2 has sent nothing
    in the new numbering. It takes it on its first frame in it, as a camera a little behind does at
    once: one global jump, not a second one of its own (which would close the bundles the others
    filled since, and bundle the same trigger frames again with camera 2 alone). Every trigger frame
    is bundled once; from new + 3 on every bundle has all three cameras. The same when camera 2's
    last frame before the jump was misnumbered (a suspect far from the new numbering): that one is
    no frame in the new numbering, so it does not make camera 2 follow early."""
    for new_first, wrong_98 in ((0, False), (5000, False), (0, True)):
        r = make(deadline_fraction=6.0)
        frames = stream({0: 0, 1: 0, 2: 0}, range(160), edge=True, lag={0: L, 1: L, 2: L + 3.5 * P})
        for f in frames:
            if f.trigger_frame >= 100:
                f.trigger_frame += new_first - 100
            if wrong_98 and f.camera_index == 2 and f.camera_frame == 98:
                f.trigger_frame = 60  # its last frame before the jump is confirmed, suspect, far from it
        r.feed(frames, poll_every=P)
        assert [(e.kind, e.camera_index, e.global_jump) for e in r.events if e.kind == "clock_jump"] == [
            ("clock_jump", 0, True)], new_first
        after = [b.bundle.trigger_frame for b in r.bundles if min(f.camera_frame for f in b.frames.values()) >= 100]
        assert len(after) == len(set(after)), new_first
        new = [b for b in r.bundles if b.bundle.trigger_frame >= new_first + 3 and b.frames[0].camera_frame >= 100]
        assert [b.bundle.trigger_frame for b in new] == list(range(new_first + 3, new_first + 60)), new_first
        assert all(sorted(b.frames) == [0, 1, 2] for b in new), new_first
        # Its frames of the new numbering sent before it followed are late (their bundles closed with
        # the jump), not suspect: only the misnumbered one is.
        assert (r.sync.stats()[2].clock_jumps, r.sync.stats()[2].suspect) == (0, int(wrong_98)), new_first


# --- early frames ---------------------------------------------------------------------------------


def test_a_camera_s_fourth_frame_claiming_a_pulse_two_ahead_is_early() -> None:
    """Three frames of a camera are enough to know when its frames come: its fourth, numbered by its
    edge two pulses ahead of the one it answered, is early (not tracked in the wrong bundle)."""
    r = make(clock=OffsetClock())
    frames = stream({0: 0, 1: 0, 2: 0}, range(10), edge=True)
    for f in frames:
        if f.camera_index == 1 and f.camera_frame == 3:
            f.trigger_frame = 5
    r.feed(frames, poll_every=P)
    assert _reasons(r) == [(3, 5, "early")]
    assert 1 not in r.by_tf()[5].frames or r.by_tf()[5].frames[1].camera_frame == 5


def test_a_misnumbered_frame_is_caught_against_the_camera_s_last_second_not_older_arrivals() -> None:
    """Camera 1's link got 40 ms slower 1.5 s ago. One of its edge's frames then claims the pulse two
    after the one it answered: against the last second of its arrivals it came two periods too soon:
    early, not tracked (against its arrivals of two seconds ago it would have looked on time)."""
    r = make(clock=OffsetClock(), deadline_fraction=4.0)
    lag = {0: L, 1: L, 2: L}
    frames = stream({0: 0, 1: 0, 2: 0}, range(300), edge=True, lag=lag)
    for f in frames:
        if f.camera_index == 1 and f.camera_frame >= 100:
            f.recv_time += 0.040
        if f.camera_index == 1 and f.camera_frame == 200:
            f.trigger_frame = 202
    r.feed(frames, poll_every=P)
    assert _reasons(r, 1) == [(200, 202, "early")]
    assert r.by_tf()[202].frames[1].camera_frame == 202


def test_a_frame_sent_again_exactly_late_tolerance_after_its_pulse_is_a_discontinuity() -> None:
    """Camera 1 sends its frame 15 again: just under late_tolerance_s (0.25 s) after its pulse it is
    merely late; exactly 0.25 s after, it is no longer taken as held up in the network (the number
    was seen already): a discontinuity."""
    for extra, want in ((-2.0**-12, "late"), (0.0, "discontinuity")):
        r = make(clock=OffsetClock())
        frames = stream({0: 0, 1: 0, 2: 0}, range(40), lag={0: 0.0, 1: 0.0, 2: 0.0})
        r.feed(frames + [frame(1, 15, T0 + 15 * P + 0.25 + extra)], poll_every=P)
        assert _reasons(r) == [(15, 15, want)], extra


def test_a_frame_held_up_512_frames_or_more_is_a_discontinuity_fewer_is_late() -> None:
    """Camera 1 lost its frames 400-499 (a gap it continues over). At its frame 999 three of the lost
    frames come in, held up in the network for seconds: numbers never seen, within what it accepted
    lately. One fewer than 512 frames behind (the camera's memory of accepted numbers) is late; 512
    and 549 behind are discontinuities (suspect: a restarted counter repeats old numbers too)."""
    r = make()
    frames = stream({0: 0, 2: 0}, range(1000)) + [f for f in stream({1: 0}, range(1000))
                                                   if not 400 <= f.camera_frame < 500]
    t = T0 + 999 * P + L
    frames += [frame(1, cf, t + 0.0001 * (i + 1)) for i, cf in enumerate((450, 487, 488))]
    r.feed(frames, poll_every=P)
    # (Its frame 500 is late too: it was dead after 1.5 s of silence, so bundle 500 did not wait.)
    assert _reasons(r, 1) == [(500, 500, "late"), (450, 450, "discontinuity"), (487, 487, "discontinuity"),
                              (488, 488, "late")]
    assert [e.kind for e in r.events] == ["dead", "alive"]


# --- the mapped-ahead check: how far ahead is ahead ---------------------------------------------------


def _joiner_placed_one_ahead(clock_offset: float, lag2: float) -> Run:
    """early_fraction 1, early_slack_s 0: the early threshold is exactly a period. Cameras 0 and 1 come
    L after each pulse; camera 2 joins at pulse 40 with its first frame a period late (so it is placed
    one ahead), then comes lag2 after each pulse. The clock model puts every pulse clock_offset late."""
    r = make(clock=OffsetClock(clock_offset), early_fraction=1.0, early_slack_s=0.0, deadline_fraction=1.5)
    frames = stream({0: 0, 1: 0}, range(120)) + [frame(2, 500 + k, T0 + k * P + lag2) for k in range(41, 120)]
    frames.append(frame(2, 540, T0 + 41 * P + lag2 - 0.0001))
    r.feed(frames, poll_every=P)
    return r


def test_a_camera_exactly_the_early_threshold_ahead_of_the_others_is_not_moved_back() -> None:
    """With the clock model 2 periods late every frame seems to come before its pulse; camera 2, one
    ahead, comes exactly a period (the threshold) before the others: not more than the threshold, so
    it keeps its mapping; a quarter of a millisecond more and it is moved back by one."""
    for lag2, moved in ((L, False), (L - 2.0**-12, True)):
        r = _joiner_placed_one_ahead(2 * P, lag2)
        assert [e.kind for e in r.events if e.kind == "ahead"] == (["ahead"] if moved else []), lag2
        assert cam_frames(r, 2)[100] == (600 if moved else 599), lag2


def test_a_camera_whose_frames_come_exactly_the_threshold_before_their_mapped_pulses_is_not_moved_back() -> None:
    """Camera 2 arrives right at its pulses, mapped one ahead: its frames come exactly a period (the
    threshold) before their mapped pulses, more than that ahead of the others (which come L later):
    not before its own pulses by more than the threshold, so it keeps its mapping; with the clock
    model a quarter of a millisecond later it is moved back."""
    for offset, moved in ((0.0, False), (2.0**-12, True)):
        r = _joiner_placed_one_ahead(offset, 0.0)
        assert [e.kind for e in r.events if e.kind == "ahead"] == (["ahead"] if moved else []), offset
        assert cam_frames(r, 2)[100] == (600 if moved else 599), offset


def test_at_16_fps_a_joiner_placed_two_ahead_is_moved_back_on_its_8th_frame() -> None:
    """The ahead check wants 8 of a camera's frames (over at least 0.1 s) before it moves it: at 16
    fps (checked on every frame) camera 2, whose first frame came two periods late (placed two
    ahead), is moved back on the 8th frame it sent, not sooner, not later; its later frames sit in
    the bundles of the pulses they answered."""
    fps = 16.0
    r = make(fps=fps, clock=FixedRateClock(fps, start_time=T0))
    frames = stream({0: 0, 1: 0}, range(80), fps=fps)
    frames += [frame(2, 500 + k, T0 + k / fps + L) for k in range(43, 80)]  # its 541, 542 lost
    frames.append(frame(2, 540, T0 + 42 / fps + L - 0.001))
    sent, moved_on = 0, []
    for f in sorted(frames, key=lambda f: f.recv_time):
        sent += f.camera_index == 2
        before = len(r.kinds("ahead"))
        r.feed([f], poll_every=1 / fps)
        moved_on += [(f.camera_frame, sent)] * (len(r.kinds("ahead")) - before)
    assert moved_on == [(549, 8)]
    assert [e.message for e in r.kinds("ahead")] == [
        "camera 2: frames numbered 2 ahead of their arrival against the other cameras: re-mapped"]
    assert all(cam_frames(r, 2)[k] == 500 + k for k in range(52, 80))  # 550, 551: late (bundles closed)


def test_a_joiner_catching_up_slowly_is_moved_back_the_whole_way_once_caught_up() -> None:
    """Camera 2 joins at pulse 40 with its first frame 100 ms late (placed 6 ahead), then works off
    its queue slowly (a frame every 10 ms, or 14 ms, against a period of 15.6) until it is on time. While it
    catches up its lags keep falling; it is moved back once they stopped (by all 6), not on the way
    (by 5, which would leave it one ahead for good: less than the early threshold, never seen
    again). Its frames then sit in the bundles of the pulses they answered."""
    for spacing, right_from in ((0.01, 80), (0.014, 140)):
        r = make(clock=FixedRateClock(FPS, start_time=T0))
        frames, t = stream({0: 0, 1: 0}, range(200)), 0.0
        for k in range(40, 200):
            t = T0 + k * P + L + 0.1 if k == 40 else max(T0 + k * P + L, t + spacing)
            frames.append(frame(2, 500 + k, t))
        r.feed(frames, poll_every=P)
        assert [e.message for e in r.kinds("ahead")] == [
            "camera 2: frames numbered 6 ahead of their arrival against the other cameras: re-mapped"], spacing
        got = cam_frames(r, 2)
        assert all(got[k] == 500 + k for k in range(right_from, 200)), (spacing, [k for k in got if got[k] != 500 + k])


# --- the fixed-rate clock's anchor at exactly two periods -------------------------------------------


def test_frames_exactly_two_periods_sooner_than_the_anchor_leave_the_frame_times() -> None:
    """The fixed-rate clock is anchored on the first frames (40 ms after their pulse). Frames coming
    sooner by less than two periods pull the frame times back by that much; exactly two periods
    sooner is no late anchor (as more is not): the frame times stay."""
    for drop, moved in ((2 * P - 2.0**-10, True), (2 * P, False)):
        r = make()
        frames = stream({0: 0, 1: 0, 2: 0}, range(100), lag={0: 0.04, 1: 0.04, 2: 0.04})
        for f in frames:
            if f.camera_frame >= 50:
                f.recv_time -= drop
        r.feed(frames, poll_every=P)
        lag = {b.bundle.trigger_frame: b.bundle.timestamp - (T0 + b.bundle.trigger_frame * P) for b in r.bundles}
        assert abs(lag[90] - (0.04 - drop if moved else 0.04)) < 1e-9, (drop, lag[90])
        assert not r.events


def test_a_pause_after_which_frames_come_exactly_two_periods_late_does_not_re_anchor() -> None:
    """Every camera pauses and comes back paced exactly two periods later than before: not more than
    two periods, so the fixed-rate clock is not re-anchored; 1/64 of a period more and it is."""
    for late, want in ((2.0, 0), (2.0 + 2.0**-6, 1)):
        r = paused_run(late)
        assert len(r.kinds("reanchor")) == want == r.sync.reanchors, late


def test_the_clock_is_re_anchored_after_reanchor_s_of_late_frames_and_at_least_5() -> None:
    """Every camera pauses 0.3 s from trigger frame 20: re-anchored on the bundle that makes
    reanchor_s (0.2 s = 12 frames) of late paced frames, trigger frame 31; with reanchor_s 0, on the
    5th (the least), trigger frame 24."""
    for kw, at in (({}, 31), ({"reanchor_s": 0.0}, 24)):
        r = make(**kw)
        frames = stream({0: 0, 1: 0, 2: 0}, range(80))
        for f in frames:
            if f.camera_frame >= 20:
                f.recv_time += 0.3
        r.feed(frames, poll_every=P)
        assert [e.message for e in r.events] == [
            f"fixed-rate clock re-anchored at trigger frame {at}: frames came 300 ms after their expected time "
            "(a pause of the cameras?)"], kw


def test_a_stall_of_every_camera_worked_off_in_a_burst_does_not_re_anchor_the_clock() -> None:
    """Every camera stalls 0.5 s at trigger frame 20, then delivers its queued frames faster than half
    a period apart (1 ms, or 0.48 period) until it caught up: a burst, not a paused rig coming back
    late, so the fixed-rate clock keeps its anchor and the frame times stay on the arrivals."""
    for gap in (0.001, 0.48 * P):
        r = make()
        frames, t = [], 0.0
        for k in range(200):
            on_time = T0 + k * P + L
            t = on_time if k < 20 else on_time + 0.5 if k == 20 else max(on_time, t + gap)
            frames += [frame(c, k, t + c * 2.0**-17) for c in (0, 1, 2)]
        r.feed(frames, poll_every=P)
        assert not r.events, gap
        assert all(abs(b.bundle.timestamp - (T0 + b.bundle.trigger_frame * P + L)) < 1e-9 for b in r.bundles), gap


def test_the_early_check_remembers_a_camera_s_arrivals_of_the_last_second_ends_included() -> None:
    """Camera 1 (numbered by its edge) comes 42 ms after each pulse, but its frame 100 came after 2
    ms. After a gap (frames 160-163 lost), its frame 164 comes 2 ms after its pulse too, exactly 1 s
    after frame 100: as early as the camera came within the last second, so not early. A quarter of
    a millisecond later frame 100 is out of that second: frame 164 is then early by more than the
    threshold against 42 ms (rejected, as a camera back on time after a long late spell is)."""
    for extra, want in ((0.0, []), (2.0**-12, [(164, 164, "early")])):
        r = make(clock=OffsetClock(), deadline_fraction=4.0)
        frames = stream({0: 0, 2: 0}, range(200))
        for k in range(200):
            if not 160 <= k < 164:
                t = T0 + 100 * P + L + 1.0 + extra if k == 164 else T0 + k * P + (L if k == 100 else L + 0.040)
                frames.append(frame(1, k, t, k))
        r.feed(frames, poll_every=P)
        assert [x for x in _reasons(r, 1) if x[2] != "late"] == want, extra
        assert not r.events


# --- the mapped-ahead check after a restart ----------------------------------------------------------


def _restart_late_then_caught_up(late: int, restarts: tuple[int, ...] = (100,)) -> Run:
    """Two cameras (so the drift check, which needs three, stays out). Camera 1's edge restarts at
    trigger frame k (no pulse lost: its counter starts again at 0); its frames come paced but 3
    periods late for `late` frames, so it is placed 3 ahead; then it catches up (a short burst) and
    comes on time: its frames now arrive 3 periods before their mapped pulses."""
    r = make(cams=(0, 1))
    n = restarts[-1] + late + 60
    frames = stream({0: 0}, range(n)) + stream({1: 0}, range(restarts[0]))
    for j, first in enumerate(restarts):
        end = restarts[j + 1] if j + 1 < len(restarts) else n
        t_prev = 0.0
        for k in range(first, end):
            on_time = T0 + k * P + L
            t_prev = on_time + 3 * P if k - first < late else max(on_time, t_prev + 0.001)
            f = frame(1, k - first, t_prev)
            f.restarted = k == first
            frames.append(f)
    r.feed(frames, poll_every=P)
    return r


def test_a_restart_found_3_ahead_2_9_s_later_gets_its_missed_count_corrected() -> None:
    """Its restart was counted as 3 missed trigger frames from the wrong (ahead) placement; 2.94 s
    later (late for 180 frames; within 3 s of the restart) the ahead check moves it back by 3, takes those 3 off (none
    missed: the edge restarted between two pulses) and says it was after its restart."""
    r = _restart_late_then_caught_up(180)
    assert [e.message for e in r.events] == [
        "camera 1: edge restarted; its camera frame 0 is trigger frame 103 (by arrival); "
        "3 trigger frames missed while it was down",
        "camera 1: frames numbered 3 ahead of their arrival against the other cameras (after its restart): re-mapped"]
    st = r.sync.stats()[1]
    assert (st.restarts, st.ahead, st.missed) == (1, 1, 0)
    n = 100 + 180
    got = cam_frames(r, 1)
    assert all(got[k] == k - 100 for k in range(n + 20, n + 60))


def test_a_camera_found_ahead_3_s_or_more_after_its_restart_keeps_its_missed_count() -> None:
    """The same found 3.6 s, or exactly 3 s, after the restart (late for 224 or 183 frames; the ahead
    check then fires on a frame 3 s after the restart's first, to the bit): moved back the same, but
    the ahead mapping is no longer put down to the restart: its missed count stays, and the message
    says nothing of a restart. Late for 182 frames it fires 2.94 s after: corrected."""
    for late_frames, corrected in ((224, False), (183, False), (182, True)):
        r = _restart_late_then_caught_up(late_frames)
        note = " (after its restart)" if corrected else ""
        assert r.events[-1].message == ("camera 1: frames numbered 3 ahead of their arrival against the other "
                                        f"cameras{note}: re-mapped"), late_frames
        st = r.sync.stats()[1]
        assert (st.restarts, st.ahead, st.missed) == (1, 1, 0 if corrected else 3), late_frames


def test_a_camera_moved_back_twice_counts_two_aheads() -> None:
    """The edge restarts twice the same way: moved back after each, counted twice, each restart's 3
    wrongly missed frames taken off again."""
    r = _restart_late_then_caught_up(32, restarts=(100, 300))
    assert [e.kind for e in r.events] == ["restart", "ahead", "restart", "ahead"]
    st = r.sync.stats()[1]
    assert (st.restarts, st.ahead, st.missed) == (2, 2, 0)


# --- placing a restarted edge: the lag it is placed by, how long it is held ----------------------


def test_a_restarted_edge_is_placed_by_the_least_lag_of_the_other_cameras_recent_frames() -> None:
    """Every camera's frames come 14 ms after their pulse, every fifth 1 ms after (the link's floor;
    camera 1's fast ones two pulses after the others'). Camera 1's edge restarts at trigger frame
    100: its fast frames bound its placement, by the least lag of the others' last frames, not their
    usual or newest one (either would put it a pulse early): every frame then sits in the bundle of
    the pulse it answered."""
    r = make(clock=FixedRateClock(FPS, start_time=T0), deadline_fraction=1.5)
    frames = []
    for k in range(200):
        lag = 0.001 if k % 5 == 0 else 0.014
        frames += [frame(0, k, T0 + k * P + lag), frame(2, k, T0 + k * P + lag)]
        if k < 80 or k >= 100:
            f = frame(1, k if k < 80 else k - 100, T0 + k * P + (0.001 if k % 5 == 2 else 0.014))
            f.restarted = k == 100
            frames.append(f)
    r.feed(frames, poll_every=P)
    assert [e.message for e in r.events if e.kind != "dead"] == [
        "camera 1: edge restarted; its camera frame 0 is trigger frame 100 (by arrival); "
        "20 trigger frames missed while it was down"]
    got = cam_frames(r, 1)
    assert all(got[k] == k - 100 for k in range(120, 200))


def _placed(fps: float, spacing: float, n: int = 40, **kw) -> tuple[int, str] | None:
    """Camera 1's edge restarts (its frame 0 answers trigger frame 30) and sends n frames `spacing`
    apart: the camera frame on whose arrival it was placed, and the restart message (None: held)."""
    r = make(fps=fps, **kw)
    frames = stream({0: 0, 2: 0}, range(60), fps=fps) + stream({1: 0}, range(20), fps=fps)
    t1 = T0 + 30 / fps + L
    held = [frame(1, i, t1 + i * spacing) for i in range(n)]
    held[0].restarted = True
    for f in sorted(frames + held, key=lambda f: f.recv_time):
        r.add(f)
        if r.kinds("restart"):
            return f.camera_frame, r.kinds("restart")[0].message
    return None


def test_a_restarted_edge_that_never_catches_up_is_placed_on_its_300th_frame_by_default() -> None:
    """Frames coming faster than the pulses for good (never paced): held up to restart_hold_frames,
    300 by default, then placed by the lowest bound they gave."""
    got = _placed(20.0, 1 / 64, n=320)
    assert got is not None and got[0] == 299


def test_a_hold_shorter_than_the_settle_count_is_one_frame_more_than_it() -> None:
    """restart_hold_frames 1 (less than restart_settle_frames): an edge is held at least
    restart_settle_frames + 1 frames (11), so a bunched start is placed on its 11th frame."""
    got = _placed(20.0, 1 / 64, restart_hold_frames=1)
    assert got is not None and got[0] == 10


def test_a_settle_count_below_two_frames_still_waits_for_two_paced_frames() -> None:
    """restart_settle_frames 1: pacing needs at least two frames after the lowest bound, so a paced
    restart is placed on its third frame, at the pulse it answered."""
    assert _placed(32.0, 1 / 32, restart_settle_frames=1) == (
        2, "camera 1: edge restarted; its camera frame 0 is trigger frame 30 (by arrival); "
           "10 trigger frames missed while it was down")


def test_with_no_clock_estimate_a_restarted_edge_is_placed_after_10_paced_frames() -> None:
    """No trigger clock estimate, so no bound from any held frame: still placed once 10 frames after
    its first came paced (on its 11th), by the newest trigger frame."""
    got = _placed(32.0, 1 / 32, clock=NotReadyClock())
    assert got is not None and got[0] == 10


# --- the drift check's evidence ---------------------------------------------------------------------


def _missed_pulse(fps: float, lag2: float, n: int, **kw) -> Run:
    """Cameras 0 and 1 answer L after each pulse, camera 2 lag2 after (tied to frame 0 by
    synchronize()); camera 2 misses pulse n // 2 without its counter showing it."""
    r = make(fps=fps, **kw)
    r.sync.synchronize()
    frames = stream({0: 0, 1: 0}, range(n), fps=fps)
    frames += [frame(2, k - (k > n // 2), T0 + k / fps + lag2) for k in range(n) if k != n // 2]
    r.feed(frames, poll_every=1 / fps)
    return r


def test_a_missed_pulse_is_judged_over_10_trigger_frames_at_10_fps_and_half_a_second_at_64() -> None:
    """The drift evidence spans drift_frames (10) trigger frames and at least drift_min_s (0.5 s): at
    10 fps that is 10 frames, at 64 fps 32; the message says over how many."""
    for fps, want in ((10.0, 10), (64.0, 32)):
        r = _missed_pulse(fps, L, 200)
        assert [(e.kind, e.camera_index) for e in r.events] == [("drift", 2)], fps
        assert r.events[0].message.endswith(f"over {want} trigger frames; re-mapped"), r.events[0].message
        got = cam_frames(r, 2)
        assert all(got[k] == k - 1 for k in range(160, 200)), fps


def test_a_settle_time_below_3_frames_still_waits_3_frames_for_a_late_camera() -> None:
    """drift_settle_s 0: a trigger frame's arrivals are compared once every camera sent it or 3 frames
    later. Camera 2 comes 2.5 periods after the others; once it missed a pulse its frames come 3.5
    periods after the others' of the same number: still compared, the missed pulse is found. Had it
    come 3.5 periods after them (4.5 once it missed the pulse), its frames would come too late to be
    compared: no drift is reported."""
    for behind, want in ((2.5, [("drift", 2)]), (3.5, [])):
        r = _missed_pulse(FPS, L + behind * P, 300, drift_settle_s=0.0, deadline_fraction=6.0)
        assert [(e.kind, e.camera_index) for e in r.events] == want, behind
