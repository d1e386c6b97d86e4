"""The frame synchroniser's bundles, behaviour by behaviour: a bundle's deadline, the cameras it waits
for, how it closed; frames resent while it is open; cameras that fall silent and are declared dead.

Frames are fed with explicit times (nothing timed, nothing slept), built by sync_builders.py: 64 fps
from T0 = 1024 s, so most times are exact binary fractions and a boundary is tested exactly.
"""

from __future__ import annotations

import sys
from pathlib import Path

from flytrack_host.intake.sync import FrameSynchronizer, SyncedBundle, SyncEvent

sys.path.insert(0, str(Path(__file__).parent))  # the builders these tests share (sync_builders.py)
from sync_builders import FPS, T0, L, P, frame, make, stream  # noqa: E402


def test_a_frame_resent_while_its_bundle_is_open_is_a_duplicate_each_time() -> None:
    """Camera 1's frames 10 and 20 are delivered again (held up in the network) after its next frame,
    while their bundles still wait for camera 2: each copy is reported as a duplicate, counted, and
    the first copy stays in the bundle."""
    r = make(deadline_fraction=1.5)
    frames = stream({0: 0, 1: 0, 2: 0}, range(30))
    for f in frames:
        if f.camera_index == 2 and f.camera_frame in (10, 20):
            f.recv_time += 0.004  # within the deadline
        if f.camera_index == 1 and f.camera_frame in (11, 21):
            f.recv_time -= P - 0.0002  # its next frame came right after, bunched
    frames += [frame(1, k, T0 + k * P + L + 0.0005) for k in (10, 20)]
    r.feed(frames, poll_every=P)
    assert [(u.frame.camera_index, u.trigger_frame, u.reason) for u in r.untracked] == [
        (1, 10, "duplicate"), (1, 20, "duplicate")]
    assert r.sync.stats()[1].duplicate == 2 and r.sync.stats()[1].tracked == 30
    by_tf = r.by_tf()
    assert all(by_tf[k].frames[1].recv_time == T0 + k * P + L for k in (10, 20))
    assert all(by_tf[k].closed_by == "complete" for k in range(30))


def test_an_edge_repeating_a_trigger_number_sends_a_suspect_frame_not_a_second_copy() -> None:
    """An edge-numbered camera whose next frame carries the same trigger number as its last one (its
    counter moved on, the number did not): that frame is suspect (a discontinuity), not tracked."""
    r = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(20), edge=True)
    for f in frames:
        if f.camera_index == 1 and f.camera_frame == 10:
            f.trigger_frame = 9
    r.feed(frames, poll_every=P)
    assert [(u.frame.camera_index, u.frame.camera_frame, u.reason) for u in r.untracked] == [
        (1, 10, "discontinuity")]
    st = r.sync.stats()[1]
    assert (st.suspect, st.duplicate, st.tracked) == (1, 0, 19)


def test_a_bundle_opened_ahead_of_every_other_camera_waits_for_them_up_to_the_dead_timeout() -> None:
    """Cameras 1 and 2 have delivered up to frame 9. Camera 0's frame 10 (one ahead: the usual case)
    gets the usual deadline, half a period; its frame 11 (two ahead of every other camera) waits for
    them up to dead_timeout_s, so a frame numbered wrongly cannot close (and make late) bundles the
    others have not delivered yet. Once another camera reaches it, the usual deadline applies."""
    r = make()
    r.feed(stream({0: 0, 1: 0, 2: 0}, range(10)), poll_every=P)
    assert len(r.bundles) == 10
    t10, t11 = T0 + 10 * P + L, T0 + 11 * P + L
    r.add(frame(0, 10, t10))
    assert r.sync.next_deadline() == t10 + P / 2
    r.add(frame(0, 11, t10 + 0.001))
    assert r.sync.next_deadline() == t10 + P / 2  # bundle 10's; 11's is later
    assert max(p.deadline for p in r.sync.pending.values()) == t10 + 0.001 + 0.5
    r.poll(t10 + P / 2)
    assert [(b.bundle.trigger_frame, b.closed_by, b.bundle.missing_cameras) for b in r.bundles[10:]] == [
        (10, "deadline", (1, 2))]
    assert r.poll(t10 + 0.4) == []  # 11 still waits
    r.add(frame(1, 10, t11 - 0.001))  # camera 1's 10: late
    r.add(frame(1, 11, t11))  # camera 1 reached 11: half a period from now
    assert r.sync.next_deadline() == t11 + P / 2
    assert r.poll(t11 + P / 2 - 2.0**-12) == []
    r.poll(t11 + P / 2)
    assert [(b.bundle.trigger_frame, b.closed_by, b.bundle.missing_cameras) for b in r.bundles[11:]] == [
        (11, "deadline", (2,))]
    assert [(u.frame.camera_index, u.trigger_frame, u.reason) for u in r.untracked] == [(1, 10, "late")]


def test_bundles_waiting_for_cameras_that_fell_silent_close_when_those_are_declared_dead() -> None:
    """Cameras 1 and 2 stop after frame 9; camera 0's bundles from 11 on wait for them (they are ahead
    of every other camera). When the two are declared dead (0.5 s of silence), every waiting bundle
    is closed at that poll: by deadline, with no camera missing (dead ones are not waited for), and
    counted as closed by deadline, not complete."""
    r = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(10)) + stream({0: 0}, range(10, 60))
    r.feed([f for f in frames if f.recv_time < T0 + 9 * P + 0.5], poll_every=P)
    waiting = sorted(r.sync.pending)
    assert waiting == list(range(11, 41)) and r.sync.bundles_complete == 10
    assert r.sync.bundles_deadline == 1  # bundle 10, one ahead: the usual deadline
    out = r.poll(T0 + 9 * P + L + 0.5 + 2.0**-10)
    assert [(e.kind, e.camera_index) for e in out if isinstance(e, SyncEvent)] == [("dead", 1), ("dead", 2)]
    closed = [b for b in out if isinstance(b, SyncedBundle)]
    assert [b.bundle.trigger_frame for b in closed] == waiting and not r.sync.pending
    assert all(b.closed_by == "deadline" and b.bundle.missing_cameras == () for b in closed)
    assert (r.sync.bundles_complete, r.sync.bundles_deadline) == (10, 1 + len(waiting))
    # From then on camera 0's bundles are complete on its own.
    r.feed([f for f in frames if f.recv_time >= T0 + 9 * P + 0.5], poll_every=P)
    assert all(b.closed_by == "complete" for b in r.bundles[-10:])


def test_a_camera_is_dead_only_once_silent_for_longer_than_the_dead_timeout() -> None:
    """Exactly dead_timeout_s (0.5 s) of silence is not yet dead; any longer is."""
    s = FrameSynchronizer([0, 1], FPS, start_time=T0)
    assert s.poll(T0 + 0.5) == [] and s.live_cameras() == [0, 1]
    assert [(e.kind, e.camera_index) for e in s.poll(T0 + 0.5 + 2.0**-20)] == [("dead", 0), ("dead", 1)]
    assert s.live_cameras() == []


def test_how_a_bundle_closed_when_several_close_at_once() -> None:
    """A poll closing several bundles: all by deadline; flush() closing several: all by flush; a bundle
    completed while older ones still wait closes them by deadline."""
    r = make()
    r.feed([f for f in stream({0: 0, 1: 0, 2: 0}, range(4)) if f.camera_index != 2])  # no polls
    r.poll(T0 + 4 * P)
    assert [(b.bundle.trigger_frame, b.closed_by) for b in r.bundles] == [(k, "deadline") for k in range(4)]
    r.feed([f for f in stream({0: 0, 1: 0, 2: 0}, range(4, 8)) if f.camera_index != 2])
    out = r.sync.flush()
    assert [(b.bundle.trigger_frame, b.closed_by) for b in out] == [(k, "flush") for k in range(4, 8)]
    r.feed([f for f in stream({0: 0, 1: 0, 2: 0}, range(8, 10)) if not (f.camera_index == 2 and f.camera_frame == 8)])
    assert [(b.bundle.trigger_frame, b.closed_by) for b in r.bundles[4:]] == [(8, "deadline"), (9, "complete")]
    assert r.bundles[4].bundle.missing_cameras == (2,)
