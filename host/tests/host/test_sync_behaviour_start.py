"""The frame synchroniser at the start and when a camera joins late, behaviour by behaviour: the
frame-0 tie after synchronize() and without it, at 64 fps and at 1 fps; a late joiner placed by the
other cameras' lag, also when a camera never sent or one frame was held up in the network; a
camera without numbers first seen when an edge-numbered one is at frame 1.

Frames are fed with explicit times (nothing timed, nothing slept), built by sync_builders.py: 64 fps
from T0 = 1024 s, so most times are exact binary fractions and a boundary is tested exactly.
"""

from __future__ import annotations

import sys
from pathlib import Path

from flytrack_host.intake.sync import FixedRateClock

sys.path.insert(0, str(Path(__file__).parent))  # the builders these tests share (sync_builders.py)
from sync_builders import FPS, T0, L, P, cam_frames, frame, make, stream  # noqa: E402


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
