"""The frame synchroniser's ahead check, behaviour by behaviour: a camera whose frames come before
their pulses, compared with the other cameras, is moved back; cameras on a slow link or with
different latencies, or a clock model running late, make no camera look ahead.

Frames are fed with explicit times (nothing timed, nothing slept), built by sync_builders.py: 64 fps
from T0 = 1024 s, so most times are exact binary fractions and a boundary is tested exactly.
"""

from __future__ import annotations

import sys
from pathlib import Path

from flytrack_host.intake.sync import FixedRateClock

sys.path.insert(0, str(Path(__file__).parent))  # the builders these tests share (sync_builders.py)
from sync_builders import FPS, T0, L, OffsetClock, P, cam_frames, frame, make, stream  # noqa: E402


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
