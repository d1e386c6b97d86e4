"""The frame synchroniser's fixed-rate clock and its anchor, behaviour by behaviour: host times counted
from zero, a pause that re-anchors the clock only past two periods, a late joiner after a re-anchor,
and one misnumbered frame that must not move the frame times.

Frames are fed with explicit times (nothing timed, nothing slept), built by sync_builders.py: 64 fps
from T0 = 1024 s, so most times are exact binary fractions and a boundary is tested exactly.
"""

from __future__ import annotations

import sys
from pathlib import Path

from flytrack_host.intake.sync import FrameSynchronizer

sys.path.insert(0, str(Path(__file__).parent))  # the builders these tests share (sync_builders.py)
from sync_builders import FPS, T0, L, P, Run, cam_frames, frame, make, paused_run, stream  # noqa: E402


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
