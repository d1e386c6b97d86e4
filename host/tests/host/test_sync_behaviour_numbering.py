"""The frame synchroniser's checks of a frame's number, behaviour by behaviour: future-dated frames
with and without a clock estimate, frames sent again (late), counter gaps and long silences
(discontinuities), a step of the clock model, frames numbered ahead (early) until they confirm a
jump, and the early threshold.

Frames are fed with explicit times (nothing timed, nothing slept), built by sync_builders.py: 64 fps
from T0 = 1024 s, so most times are exact binary fractions and a boundary is tested exactly.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))  # the builders these tests share (sync_builders.py)
from sync_builders import FPS, T0, L, NotReadyClock, OffsetClock, P, cam_frames, frame, make, stream  # noqa: E402


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
