"""The frame synchroniser at the start: every camera's first frame tied to trigger frame 0, the tie
window after synchronize() and without it, synchronize() starting the numbering again, and a late
joiner placed by its arrival minus the other cameras' lag.

Frames are built by sync_driver.py: 100 fps from T0 = 1000 s, arrivals 2-2.5 ms after their pulse,
fed in arrival order with every deadline polled as the pipeline does.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from flytrack_host.intake.sync import FixedRateClock, FrameSynchronizer

sys.path.insert(0, str(Path(__file__).parent))  # the builders these tests share (sync_driver.py)
from sync_driver import FPS, T0, Driver, P, frame, make, stream  # noqa: E402


def test_frame_zero_tie_bundles_every_frame_complete():
    d = make()
    d.feed(stream({0: 100, 1: 5000, 2: 7}, range(50)))
    d.advance(T0 + 1)
    assert [b.bundle.trigger_frame for b in d.bundles] == list(range(50))
    assert all(b.closed_by == "complete" and not b.bundle.missing_cameras for b in d.bundles)
    assert all(set(b.bundle.detections) == {0, 1, 2} for b in d.bundles)
    assert not d.untracked
    # Frame times come from the fixed-rate clock, anchored at the first frame and moved earlier when a
    # bundle's frames come earlier than that anchor allows (0.5 ms of jitter here); the second earliest
    # arrival counts, so one misnumbered frame cannot move it.
    ts = np.array([b.bundle.timestamp for b in d.bundles])
    assert np.all(np.abs(np.diff(ts) - P) <= 0.0005)
    assert all(b.bundle.timestamp <= sorted(f.recv_time for f in b.frames.values())[1] for b in d.bundles)


def test_frame_zero_tie_window_after_synchronize_and_without() -> None:
    """After synchronize() every camera's first frame within 0.5 s (tie_window_s) of the first one is
    trigger frame 0; a camera first seen 0.7 s later is a late joiner, placed by its arrival. Without
    synchronize() (cameras already running) the tie spans only 0.9 period."""
    for synced, late_s, want_tf in ((True, 0.45, 0), (True, 0.7, 70), (False, 0.3, 30)):
        d = make()
        if synced:
            d.sync.synchronize()
        frames = stream({0: 0, 1: 0}, range(100))
        frames += [frame(2, 500 + k, T0 + late_s + k * P + 0.002) for k in range(20)]
        d.feed(frames)
        d.advance(T0 + 2)
        # Its first frame's trigger frame, tracked or (tied to frame 0, long closed) reported late.
        tfs = [b.bundle.trigger_frame for b in d.bundles if 2 in b.frames]
        tfs += [u.trigger_frame for u in d.untracked if u.frame.camera_index == 2]
        assert tfs and abs(min(tfs) - want_tf) <= 1, (synced, late_s, tfs[:3])


def test_synchronize_starts_the_numbering_again_from_frame_zero() -> None:
    d = make()
    d.feed(stream({0: 0, 1: 0, 2: 0}, range(50)))
    d.advance(T0 + 50 * P + 0.3)
    d.sync.synchronize()
    n0 = len(d.bundles)
    again = [frame(f.camera_index, f.camera_frame + 1000, f.recv_time + 1.0) for f in stream({0: 0, 1: 0, 2: 0},
                                                                                               range(30))]
    d.feed(again)
    d.advance(T0 + 1.0 + 30 * P + 0.1)
    assert [b.bundle.trigger_frame for b in d.bundles[n0:]] == list(range(30))
    assert all(b.closed_by == "complete" for b in d.bundles[n0:])


def test_a_late_joiner_is_placed_by_arrival_minus_the_other_cameras_lag() -> None:
    """Cameras answer 6 ms after each pulse (more than half a period): a camera first seen later is
    placed at the pulse its frame answered, the others' lag taken off, not the pulse nearest its arrival.
    Without synchronize() a camera first seen 1.3 periods after the first one is no longer frame 0."""
    for first_k, lag_s in ((50, 0.006), (1, 0.002)):
        # A trigger clock that knows when the pulses were (the fixed-rate fallback would take the first
        # arrival, lag included, as frame 0's time).
        d = Driver(FrameSynchronizer((0, 1, 2), FPS, clock=FixedRateClock(FPS, start_time=T0), start_time=T0))
        frames = stream({0: 0, 1: 0}, range(100), lag={0: lag_s, 1: lag_s})
        frames += [frame(2, 700 + k, T0 + k * P + lag_s + 0.0003) for k in range(first_k, 100)]
        if first_k == 1:
            frames[-99].recv_time += 0.001  # 1.3 periods after camera 0's first frame
        d.feed(frames)
        d.advance(T0 + 2)
        by_tf = {b.bundle.trigger_frame: b for b in d.bundles}
        assert all(by_tf[k].frames[2].camera_frame == 700 + k for k in range(first_k + 2, 100)), first_k
