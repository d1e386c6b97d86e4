"""The frame synchroniser's rejected frames: duplicates (every frame resent), future-dated frames by
the clock and without one, and early frames past the slack.

Frames are built by sync_driver.py: 100 fps from T0 = 1000 s, arrivals 2-2.5 ms after their pulse,
fed in arrival order with every deadline polled as the pipeline does.
"""

from __future__ import annotations

import sys
from pathlib import Path

from flytrack_host.intake.sync import FrameSynchronizer, UntrackedFrame

sys.path.insert(0, str(Path(__file__).parent))  # the builders these tests share (sync_driver.py)
from sync_driver import FPS, T0, P, frame, make, stream  # noqa: E402


def test_duplicate_and_future_dated_frames_are_rejected_and_counted():
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(40), tf_from_edge=True)
    dup = frame(1, 20, T0 + 20 * P + 0.003, 20)
    future = frame(0, 10**6, T0 + 25 * P + 0.0031, 25 + 100000)  # claims a trigger time 1000 s ahead
    d.feed(frames + [dup, future])
    d.advance(T0 + 40 * P + 0.1)
    reasons = sorted(u.reason for u in d.untracked)
    assert reasons == ["duplicate", "future"]
    assert d.sync.stats()[1].duplicate == 1 and d.sync.stats()[0].future == 1
    assert [b.bundle.trigger_frame for b in d.bundles] == list(range(40))
    assert not d.kinds("clock_jump")


def test_future_dated_frames_by_the_clock_and_without_one() -> None:
    """A frame numbered for a trigger time more than 0.5 s (future_tolerance_s) ahead is future-dated;
    0.4 s ahead is only early (claims a pulse not yet seen). Without a clock model (NaN times) the
    same tolerance counts in frames: 60 frames ahead of the newest accepted is future, 10 is accepted."""
    d = make()
    d.feed(stream({0: 0, 1: 0, 2: 0}, range(10), tf_from_edge=True))
    now = T0 + 10 * P
    for ahead, reason in ((60, "future"), (40, "early")):
        out = d.sync.add(frame(0, 100 + ahead, now, 9 + ahead), now)
        assert [u.reason for u in out if isinstance(u, UntrackedFrame)] == [reason], ahead
    # Early (early_fraction 1.5 periods + 5 ms): numbered for trigger frame 12 but arriving 25 ms
    # before its usual lag after that pulse would allow (camera 1 answers its pulses 2-2.5 ms late).
    t = T0 + 9.5 * P + 0.002
    out = d.sync.add(frame(1, 300, t, 12), t)
    assert [u.reason for u in out if isinstance(u, UntrackedFrame)] == ["early"]

    class NoModel:
        def frame_to_host_time(self, frame: int) -> float:
            return float("nan")

    s = FrameSynchronizer([0, 1, 2], FPS, clock=NoModel(), start_time=T0)
    for k in range(5):
        for c in range(3):
            s.add(frame(c, k, T0 + k * P, k), T0 + k * P)
    for ahead, reason in ((60, "future"), (10, None)):
        out = s.add(frame(1, 200 + ahead, T0 + 5 * P, 4 + ahead), T0 + 5 * P)
        assert [u.reason for u in out if isinstance(u, UntrackedFrame)] == ([reason] if reason else []), ahead


def test_an_early_frame_needs_more_than_the_slack() -> None:
    """early_s = 1.5 periods + 5 ms: numbered for a pulse 17 ms before its camera's usual lag allows
    is within the margin (host jitter); 25 ms is early."""
    for early_ms, reasons in ((17.0, []), (25.0, ["early"])):
        d = make()
        d.feed(stream({0: 0, 1: 0, 2: 0}, range(10), tf_from_edge=True))
        t = T0 + 12 * P + 0.002 - early_ms * 1e-3
        out = d.sync.add(frame(1, 300, t, 12), t)
        assert [u.reason for u in out if isinstance(u, UntrackedFrame)] == reasons, early_ms


def test_every_resent_frame_is_a_duplicate() -> None:
    d = make()
    frames = stream({0: 0, 1: 0, 2: 0}, range(60))
    frames += [frame(1, k, T0 + k * P + 0.004) for k in (20, 40)]  # camera 1 sends 20 and 40 again
    d.feed(frames)
    d.advance(T0 + 60 * P + 0.1)
    assert [(u.frame.camera_index, u.trigger_frame, u.reason) for u in d.untracked] == [(1, 20, "duplicate"),
                                                                                        (1, 40, "duplicate")]
    assert d.sync.stats()[1].duplicate == 2 and d.sync.stats()[1].tracked == 60
