"""The frame synchroniser's bundles: edge-numbered frames bundled by their number, a deadline closing
an incomplete bundle, flush, cameras that stop (and die, twice) and come back, the defaults, a
camera frame's defaults, and the counts that add up to every frame.

Frames are built by sync_driver.py: 100 fps from T0 = 1000 s, arrivals 2-2.5 ms after their pulse,
fed in arrival order with every deadline polled as the pipeline does.
"""

from __future__ import annotations

import sys
from pathlib import Path

from flytrack_host.intake.sync import FixedRateClock, FrameSynchronizer, SyncedBundle, SyncEvent

sys.path.insert(0, str(Path(__file__).parent))  # the builders these tests share (sync_driver.py)
from sync_driver import FPS, T0, P, frame, make, stream  # noqa: E402


def test_edge_trigger_frame_is_used():
    d = make()
    d.feed(stream({0: 3, 1: 9, 2: 1}, range(500, 520), tf_from_edge=True))
    assert [b.bundle.trigger_frame for b in d.bundles] == list(range(500, 520))


def test_deadline_closes_incomplete_bundle_and_late_data_is_untracked():
    d = make(deadline_fraction=0.5)
    frames = stream({0: 0, 1: 0, 2: 0}, range(20))
    late = [f for f in frames if f.camera_index == 2 and f.camera_frame == 10][0]
    frames.remove(late)
    late.recv_time += 0.05  # 5 frames late
    d.feed(frames + [late])
    d.advance(T0 + 1)
    b10 = [b for b in d.bundles if b.bundle.trigger_frame == 10][0]
    assert b10.closed_by == "deadline" and b10.bundle.missing_cameras == (2,)
    assert [(u.trigger_frame, u.reason) for u in d.untracked] == [(10, "late")]
    assert d.sync.stats()[2].late == 1
    assert len(d.bundles) == 20


def test_camera_stops_and_comes_back():
    d = make(dead_timeout_s=0.3)
    frames = stream({0: 0, 1: 0, 2: 50}, range(300))
    gone = [f for f in frames if f.camera_index == 2 and 100 <= f.camera_frame - 50 < 200]
    for f in gone:
        frames.remove(f)
    d.feed(frames)
    d.advance(T0 + 300 * P + 0.1)
    assert [e.camera_index for e in d.kinds("dead")] == [2]
    assert [e.camera_index for e in d.kinds("alive")] == [2]
    assert len(d.bundles) == 300
    by_tf = {b.bundle.trigger_frame: b for b in d.bundles}
    # While dead, bundles no longer wait for camera 2: closed complete, and 2 is not "missing".
    assert all(by_tf[k].closed_by == "complete" for k in range(140, 200))
    assert all(2 not in by_tf[k].bundle.detections for k in range(100, 200))
    # When it is back, its frames land in the right bundles again.
    assert all(2 in by_tf[k].bundle.detections for k in range(200, 300))
    assert not d.untracked


def test_camera_frame_defaults_describe_a_plain_complete_frame() -> None:
    """Sources that know no edge timing (software trigger, synthetic feeds) leave the defaults: no
    timestamps, no points beyond those given, not truncated, complete, no restart, not an event camera."""
    f = frame(0, 1, 2.0)
    assert (f.device_timestamp_ns, f.edge_recv_ns, f.edge_done_ns, f.total_points) == (0, 0, 0, 0)
    assert (f.truncated, f.incomplete, f.restarted, f.dvs) == (False, False, False, False)


def test_stats_count_every_frame_once_and_bundles_by_how_they_closed() -> None:
    """Per camera: frames received; tracked (in a bundle), late, duplicate, future; deaths and revivals.
    The counts add up: every frame is tracked or reported untracked with one reason."""
    import dataclasses

    from flytrack_host.intake.sync import CameraSyncStats

    d = make(dead_timeout_s=0.3)
    frames = stream({0: 0, 1: 0, 2: 0}, range(120))
    frames = [f for f in frames if not (f.camera_index == 0 and 40 <= f.camera_frame < 90)]  # 0.5 s gone
    late = next(f for f in frames if f.camera_index == 2 and f.camera_frame == 20)
    late.recv_time += 0.05  # after frame 20's deadline
    dup = frame(1, 30, T0 + 30 * P + 0.004)  # camera 1 sends frame 30 twice
    future = frame(2, 10**6, T0 + 60 * P + 0.003, 60 + 100000)  # an edge number 1000 s ahead
    stranger = frame(7, 5, T0 + 5 * P + 0.003)  # a camera the rig does not have
    d.feed(frames + [dup, future, stranger])
    d.advance(T0 + 120 * P + 0.1)  # all bundles closed, nobody silent for 0.3 s yet
    assert [(u.frame.camera_index, u.trigger_frame, u.reason) for u in d.untracked if u.reason != "late"] == [
        (7, -1, "unknown_camera"), (1, 30, "duplicate"), (2, 100060, "future")]
    assert [(u.frame.camera_index, u.trigger_frame) for u in d.untracked if u.reason == "late"] == [(2, 20)]
    st = {c: dataclasses.asdict(x) for c, x in d.sync.stats().items()}
    zero = {f.name: 0 for f in dataclasses.fields(CameraSyncStats)}  # every other count stays 0
    assert st[0] == {**zero, "frames": 70, "tracked": 70, "deaths": 1, "revivals": 1}
    assert st[1] == {**zero, "frames": 121, "tracked": 120, "duplicate": 1}
    assert st[2] == {**zero, "frames": 121, "tracked": 119, "late": 1, "future": 1}
    assert [(e.kind, e.global_jump) for e in d.events] == [("dead", False), ("alive", False)]
    assert d.events[0].message.startswith("camera 0 silent for 0.3") and d.events[0].message.endswith(" s: marked dead")
    assert d.events[1].message == "camera 0 is sending again"
    complete = sum(b.closed_by == "complete" and not b.bundle.missing_cameras for b in d.bundles)
    assert len(d.bundles) == 120 and d.sync.bundles_complete == complete > 0
    assert d.sync.bundles_deadline == 120 - complete > 0 and d.sync.reanchors == 0


def test_defaults_deadline_dead_timeout_and_start_time() -> None:
    """The defaults: a bundle waits half a period after its first frame; a camera is dead after 0.5 s
    of silence, counted from start_time (0) before it ever sent; the clock is a fixed-rate one."""
    s = FrameSynchronizer([0, 1, 2], FPS)
    assert not [o for o in s.poll(0.49) if isinstance(o, SyncEvent)]
    assert [o.camera_index for o in s.poll(0.51) if isinstance(o, SyncEvent) and o.kind == "dead"] == [0, 1, 2]
    s = FrameSynchronizer([0, 1, 2], FPS)
    s.add(frame(0, 0, 0.100), 0.100)
    s.add(frame(1, 0, 0.101), 0.101)
    assert s.next_deadline() == 0.100 + 0.5 * P
    assert s.poll(0.100 + 0.45 * P) == []
    out = s.poll(0.100 + 0.55 * P)
    assert [(b.bundle.trigger_frame, b.closed_by) for b in out if isinstance(b, SyncedBundle)] == [(0, "deadline")]
    assert isinstance(s.clock, FixedRateClock) and abs(s.frame_time(0) - 0.100) < 1e-12
    # A clock given is used as it is.
    own = FixedRateClock(FPS, start_time=5.0)
    assert FrameSynchronizer([0], FPS, clock=own).clock is own


def test_a_camera_that_dies_twice_is_counted_twice() -> None:
    d = make(dead_timeout_s=0.2)
    frames = [f for f in stream({0: 0, 1: 0, 2: 0}, range(200))
              if not (f.camera_index == 2 and (40 <= f.camera_frame < 70 or 120 <= f.camera_frame < 150))]
    d.feed(frames)
    d.advance(T0 + 200 * P + 0.05)
    st = d.sync.stats()[2]
    assert (st.deaths, st.revivals) == (2, 2)
    assert [(e.kind, e.camera_index) for e in d.events] == [("dead", 2), ("alive", 2)] * 2


def test_flush_closes_what_is_pending_as_flush() -> None:
    d = make()
    d.feed([f for f in stream({0: 0, 1: 0, 2: 0}, range(5)) if f.camera_index != 2])
    out = d.sync.flush()  # frames 0-3 closed at their deadlines as the frames came; 4 was pending
    assert [(b.bundle.trigger_frame, b.closed_by) for b in out] == [(4, "flush")]
    assert d.sync.flush() == [] and d.sync.next_deadline() is None
