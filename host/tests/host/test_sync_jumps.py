"""The frame synchroniser when frame numbers jump: the trigger's count jumping back or restarting
(a global jump, the other cameras following), a camera's counter restarting, jumping by thousands
(confirmed by three frames, twice) or skipping a few (early until confirmed); each re-mapped by
arrival.

Frames are built by sync_driver.py: 100 fps from T0 = 1000 s, arrivals 2-2.5 ms after their pulse,
fed in arrival order with every deadline polled as the pipeline does.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))  # the builders these tests share (sync_driver.py)
from sync_driver import T0, P, frame, make, stream  # noqa: E402


def test_trigger_clock_jump_back_is_detected_and_tracking_goes_on():
    d = make()
    cams = {0: 0, 1: 0, 2: 0}
    frames = stream(cams, range(100), tf_from_edge=True)
    # The trigger count restarts at 0 while the cameras' counters go on.
    after = []
    rng = np.random.default_rng(1)
    for k in range(100, 200):
        for cam in cams:
            t = T0 + k * P + 0.002 + rng.uniform(0, 0.0005)
            after.append(frame(cam, k, t, k - 100))
    d.feed(frames + after)
    d.advance(T0 + 3)
    jumps = d.kinds("clock_jump")
    assert jumps and all(j.global_jump for j in jumps)
    tfs = [b.bundle.trigger_frame for b in d.bundles]
    assert tfs[:100] == list(range(100))
    # Tracking resumed in the new numbering within a few frames.
    assert tfs[100:] == list(range(tfs[100], 100)) and tfs[100] <= 4
    # Nothing lost: every frame is either in a bundle or reported untracked.
    n_bundled = sum(len(b.frames) for b in d.bundles)
    assert n_bundled + len(d.untracked) == 600


def test_camera_counter_restart_is_remapped_by_arrival_time():
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(100))
    for f in frames:
        if f.camera_index == 1 and f.camera_frame >= 60:
            f.camera_frame -= 60  # the camera restarted its counter at trigger frame 60
    d.feed(frames)
    d.advance(T0 + 2)
    assert [e.camera_index for e in d.kinds("clock_jump")] == [1]
    by_tf = {b.bundle.trigger_frame: b for b in d.bundles}
    assert len(by_tf) == 100
    assert all(1 in by_tf[k].bundle.detections for k in range(66, 100))
    # Remapped by arrival time: each of camera 1's frames lands in the bundle of the trigger it
    # answered (it arrived 2.0-2.5 ms after that trigger), not in the bundle its new counter names.
    for k in range(66, 100):
        fr = by_tf[k].frames[1]
        assert fr.camera_frame == k - 60
        assert 0.002 <= fr.recv_time - (T0 + k * P) <= 0.0025 + 1e-9
    # Nothing lost: each of camera 1's 100 frames is in a bundle or reported untracked.
    n_bundled = sum(1 for b in d.bundles if 1 in b.frames)
    n_untracked = sum(1 for u in d.untracked if u.frame.camera_index == 1)
    assert n_bundled + n_untracked == 100, (n_bundled, n_untracked)


def test_a_counter_jump_is_confirmed_by_three_frames_and_mapped_by_arrival() -> None:
    """jump_confirm_frames (3): camera 1's counter jumps by 5000; its first two frames in the new
    numbering are suspect (future-dated), the third confirms the jump, not global (only its counter)."""
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(100))
    for f in frames:
        if f.camera_index == 1 and f.camera_frame >= 50:
            f.camera_frame += 5000
    d.feed(frames)
    d.advance(T0 + 2)
    reasons = [u.reason for u in d.untracked if u.frame.camera_index == 1]
    assert reasons == ["future", "future", "clock_jump"]
    jumps = d.kinds("clock_jump")
    assert len(jumps) == 1 and jumps[0].camera_index == 1 and not jumps[0].global_jump
    assert d.sync.stats()[1].future == 2 and d.sync.stats()[1].clock_jumps == 1
    by_tf = {b.bundle.trigger_frame: b for b in d.bundles}
    assert all(by_tf[k].frames[1].camera_frame == k + 5000 for k in range(53, 100))
    # The confirming frame is reported under its new mapping (it answered trigger frame 52).
    assert [u.trigger_frame for u in d.untracked if u.reason == "clock_jump"] == [52]
    # A counter jumping back (restarted without the receiver noticing): a discontinuity, then re-mapped.
    d = make()
    frames = stream({0: 0, 1: 5000, 2: 0}, range(100))
    for f in frames:
        if f.camera_index == 1 and f.camera_frame >= 5050:
            f.camera_frame -= 1000  # numbers far behind those seen: not a late frame
    d.feed(frames)
    d.advance(T0 + 2)
    assert [u.reason for u in d.untracked if u.frame.camera_index == 1] == ["discontinuity", "discontinuity",
                                                                           "clock_jump"]
    assert d.sync.stats()[1].suspect == 2 and d.sync.stats()[1].future == 0


def test_a_counter_jumping_ahead_is_early_for_a_fifth_of_a_second_then_confirmed() -> None:
    """Camera 1's counter skips 3 numbers while its frames keep coming on time: they claim pulses 30 ms
    ahead, so they are early (rejected) for early_confirm_s (0.2 s = 20 frames), then the jump is
    confirmed and the camera mapped by arrival again."""
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(200))
    for f in frames:
        if f.camera_index == 1 and f.camera_frame >= 100:
            f.camera_frame += 3
    d.feed(frames)
    d.advance(T0 + 200 * P + 0.1)
    st = d.sync.stats()[1]
    assert st.early == 20 and st.clock_jumps == 1 and st.tracked == 179
    assert [e.kind for e in d.events] == ["clock_jump"] and not d.events[0].global_jump
    by_tf = {b.bundle.trigger_frame: b for b in d.bundles}
    assert all(by_tf[k].frames[1].camera_frame == k + 3 for k in range(121, 200))


def test_a_camera_counter_that_jumps_twice_is_remapped_twice() -> None:
    """Camera 1's counter jumps ahead by 5000 at trigger frame 100 and again at 200: each jump is
    confirmed by 3 frames, reported once (a camera's own jump, not the trigger's), counted, and its
    frames after it go back into the bundles of the pulses they answered."""
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(300))
    for f in frames:
        if f.camera_index == 1 and f.camera_frame >= 100:
            f.camera_frame += 5000
        if f.camera_index == 1 and f.camera_frame >= 5200:
            f.camera_frame += 5000
    d.feed(frames)
    d.advance(T0 + 300 * P + 0.1)
    st = d.sync.stats()[1]
    assert st.clock_jumps == 2 and st.future == 4 and st.restarts == 0
    jumps = d.kinds("clock_jump")
    assert [e.message for e in jumps] == [
        "camera 1: frame numbers jumped from trigger frame 99 to 102; mapping re-established",
        "camera 1: frame numbers jumped from trigger frame 199 to 202; mapping re-established",
    ]
    assert all(e.global_jump is False and e.camera_index == 1 for e in jumps)
    got = {b.bundle.trigger_frame: b.frames[1].camera_frame for b in d.bundles if 1 in b.frames}
    assert all(got[tf] == tf + 5000 for tf in range(103, 200))
    assert all(got[tf] == tf + 10000 for tf in range(203, 300))
    assert all(tf in got for tf in range(100)) and not any(tf in got for tf in (100, 101, 102, 200, 201, 202))


def test_a_trigger_count_restart_is_confirmed_once_and_the_other_cameras_follow_at_once() -> None:
    """The trigger's count restarts at 0 (edge-numbered frames, no synchronize()): camera 0 confirms the
    jump on its third frame (trigger frame 2), a global jump reported once; cameras 1 and 2, already
    seeing the new numbering, follow at once (no jump of their own, 2 suspect frames each), and every
    bundle from trigger frame 3 on is complete."""
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(200), tf_from_edge=True)
    for f in frames:
        if f.trigger_frame >= 100:
            f.trigger_frame -= 100
    d.feed(frames)
    d.advance(T0 + 200 * P + 0.1)
    jumps = d.kinds("clock_jump")
    assert [(e.camera_index, e.global_jump) for e in jumps] == [(0, True)]
    assert jumps[0].message == "camera 0: frame numbers jumped from trigger frame 99 to 2; mapping re-established"
    st = d.sync.stats()
    assert [(st[i].clock_jumps, st[i].suspect) for i in range(3)] == [(1, 2), (0, 2), (0, 2)]
    after = d.bundles[100:]
    assert [b.bundle.trigger_frame for b in after] == list(range(3, 100))
    assert all(sorted(b.frames) == [0, 1, 2] and b.closed_by == "complete" for b in after)
    assert sum(len(b.frames) for b in d.bundles) + len(d.untracked) == 600
