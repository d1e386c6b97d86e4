"""The frame synchroniser when an edge restarts (its counter from 0): each frame counted once, the
pulses missed, a restart whose first frames come late, two restarts, one without a gap, and a late
joiner and its restart each placed ahead and moved back. (A restarted edge on a loaded host, its
frames in bursts: test_sync_restart.py.)

Frames are built by sync_driver.py: 100 fps from T0 = 1000 s, arrivals 2-2.5 ms after their pulse,
fed in arrival order with every deadline polled as the pipeline does.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))  # the builders these tests share (sync_driver.py)
from sync_driver import T0, P, frame, make, stream  # noqa: E402


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
