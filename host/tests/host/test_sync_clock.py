"""The frame synchroniser's fixed-rate clock: its checks and frame times, re-anchoring after a pause
of every camera (once, twice), and frames coming sooner than the anchor pulling the frame times
back by up to two periods.

Frames are built by sync_driver.py: 100 fps from T0 = 1000 s, arrivals 2-2.5 ms after their pulse,
fed in arrival order with every deadline polled as the pipeline does.
"""

from __future__ import annotations

import sys
from pathlib import Path

from flytrack_host.intake.sync import FixedRateClock

sys.path.insert(0, str(Path(__file__).parent))  # the builders these tests share (sync_driver.py)
from sync_driver import FPS, T0, P, make, stream  # noqa: E402


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
