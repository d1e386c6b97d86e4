"""The frame synchroniser's drift check, behaviour by behaviour: a camera that misses a pulse is
re-mapped (whatever its own lag), a latency step that is not whole periods or a slow creep is no
drift, an edge-numbered camera's drift is reported once, and trigger frames no camera delivered
leave nothing behind.

Frames are fed with explicit times (nothing timed, nothing slept), built by sync_builders.py: 64 fps
from T0 = 1024 s, so most times are exact binary fractions and a boundary is tested exactly.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))  # the builders these tests share (sync_builders.py)
from sync_builders import T0, L, P, Run, cam_frames, frame, make, stream  # noqa: E402


def _drift_run(lag2, n: int = 300, edge: bool = False, skip_at: int | None = None, sync: bool = False,
               **kw) -> Run:
    """Cameras 0 and 1 answer L after each pulse, camera 2 lag2(k) after pulse k; with skip_at, camera
    2 misses that pulse without its counter showing it (its frames from then on carry one less)."""
    r = make(**kw)
    if sync:
        r.sync.synchronize()
    frames = stream({0: 0, 1: 0}, range(n), edge=edge)
    for k in range(n):
        cf = k - (1 if skip_at is not None and k >= skip_at else 0)
        if skip_at is not None and k == skip_at:
            continue
        frames.append(frame(2, cf, T0 + k * P + lag2(k), cf if edge else -1))
    r.feed(frames, poll_every=P)
    return r


def test_a_camera_4_ms_later_than_the_others_that_misses_a_pulse_is_re_mapped() -> None:
    """Camera 2 always comes 4 ms after the others (its own baseline); it misses pulse 100: re-mapped
    once, by one frame, and from then on its frames sit in the bundles of the pulses they answered,
    its numbering carried over (no discontinuity, even with max_gap_s 0.25 s)."""
    r = _drift_run(lambda k: L + 0.004, skip_at=100, max_gap_s=0.25)
    assert [(e.kind, e.camera_index) for e in r.events] == [("drift", 2)]
    assert r.events[0].message.startswith("camera 2 drifted by 1 frames") and r.events[0].message.endswith("re-mapped")
    got = cam_frames(r, 2)
    assert all(got[k] == k - 1 for k in range(150, 300))
    assert {u.reason for u in r.untracked} == {"late"} and r.sync.stats()[2].suspect == 0


def test_a_camera_5_periods_behind_the_others_that_misses_a_pulse_is_still_re_mapped() -> None:
    """Camera 2 comes 86 ms (5.5 periods) after the others: its arrivals are still compared (the check
    waits drift_settle_s, 0.5 s, for a camera's frames), so a pulse it misses is found and re-mapped."""
    r = _drift_run(lambda k: L + 5.5 * P, skip_at=100, sync=True, deadline_fraction=7.0)
    assert [(e.kind, e.camera_index) for e in r.events] == [("drift", 2)]
    got = cam_frames(r, 2)
    assert all(got[k] == k - 1 for k in range(200, 290))


def test_a_latency_step_that_is_not_whole_periods_is_no_drift() -> None:
    """Camera 2's arrivals move 1.35 periods later at trigger frame 100 (its link got slower): not a
    whole number of periods, so not a missed pulse: no drift, its frames keep their mapping."""
    r = _drift_run(lambda k: L + (1.35 * P if k >= 100 else 0.0), deadline_fraction=2.0)
    assert not r.events
    got = cam_frames(r, 2)
    assert len(got) == 300 and all(got[k] == k for k in range(300))


def test_a_camera_whose_latency_creeps_up_slowly_is_followed_not_re_mapped() -> None:
    """Camera 2 comes 3 ms after the others, then ever later, by 12 ms over 8 s (a link filling up):
    its baseline follows, no drift is reported, and its frames keep their mapping."""
    n = 600
    r = _drift_run(lambda k: L + 0.003 + 0.012 * min(1.0, max(0, k - 64) / 512), n=n, deadline_fraction=1.5)
    assert not r.events
    got = cam_frames(r, 2)
    assert len(got) == n and all(got[k] == k for k in range(n))


def test_an_edge_numbered_camera_12_ms_behind_that_falls_a_period_behind_is_reported_once() -> None:
    """Camera 2 numbers its frames by its edge and comes 12 ms after the others; from trigger frame 100
    its frames come a period later still: a drift, reported once (the edge's numbers are kept), its
    baseline moved by that period, so nothing more is reported."""
    r = _drift_run(lambda k: L + 0.012 + (P if k >= 100 else 0.0), n=400, edge=True, deadline_fraction=3.0)
    assert [(e.kind, e.camera_index) for e in r.events] == [("drift", 2)]
    assert not r.events[0].message.endswith("re-mapped")
    assert all(cam_frames(r, 2)[k] == k for k in range(400))


def test_trigger_frames_no_camera_delivered_leave_nothing_behind_and_drift_is_still_checked() -> None:
    """Every camera loses the same trigger frames (60 in a row, then 20 single ones): the drift check
    skips them, keeps no record of them (its memory stays within drift_settle_s of frames), and still
    finds camera 2's missed pulse afterwards."""
    r = make()
    lost = set(range(100, 160)) | set(range(200, 400, 10))
    frames = [f for f in stream({0: 0, 1: 0}, range(600)) if f.camera_frame not in lost]
    frames += [frame(2, k - (1 if k >= 450 else 0), T0 + k * P + L) for k in range(600) if k not in lost and k != 450]
    most = 0
    for f in sorted(frames, key=lambda f: f.recv_time):
        r.feed([f], poll_every=P)
        most = max(most, len(r.sync._arrivals))
    assert [(e.kind, e.camera_index) for e in r.events] == [("drift", 2)]
    assert all(cam_frames(r, 2)[k] == k - 1 for k in range(520, 600))
    # Arrival records: at most those of the frames not settled yet; none once all came and compared.
    assert most <= r.sync.drift_settle + 2 and len(r.sync._arrivals) == 0
