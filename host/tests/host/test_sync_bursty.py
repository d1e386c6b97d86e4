"""The synchroniser under bursty arrival (issue 5): stalls followed by bursts, jitter, a camera late by
more than the deadline, all cameras stalled together, dropped and reordered packets, a trigger clock
model that steps. Whatever the arrival pattern, a camera whose camera_frame sequence is continuous
keeps its camera_frame -> trigger_frame mapping: every frame handed on (bundled or recorded untracked)
carries the trigger frame it really answered.

Arrival model: camera c's answer to trigger pulse k leaves at T0 + k P + base_c (+ jitter); a stall
[t_s, t_s + L P) holds every packet that would arrive in it until its end, then they arrive at once.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from flytrack_host.intake.sync import (
    CameraFrame,
    FixedRateClock,
    FrameSynchronizer,
    SyncedBundle,
    SyncEvent,
    UntrackedFrame,
)

FPS = 100.0
P = 1.0 / FPS
T0 = 1000.0
PTS = np.zeros(1, dtype=[("x_dist", "<f4")])
CF0 = {0: 17, 1: 1017, 2: 2017}  # camera counters at trigger frame 0: unrelated to the trigger's


class SteppedClock:
    """A trigger clock model whose snapshot is replaced while the run goes on (as SessionClock's is
    after each query): frame times move by `steps` (host time from which it applies, shift in s)."""

    def __init__(self, steps: list[tuple[float, float]] = ()):
        self.steps = sorted(steps)
        self.now = -math.inf

    def frame_to_host_time(self, frame: int) -> float:
        shift = sum(s for t, s in self.steps if self.now >= t)
        return T0 + frame * P + shift


class Run:
    """Feeds frames in arrival order, polling deadlines as the pipeline's receive loop does, and
    checks every output against the truth (camera, camera_frame) -> trigger frame."""

    def __init__(self, sync: FrameSynchronizer, clock: SteppedClock | None = None):
        self.sync = sync
        self.clock = clock
        self.truth: dict[tuple[int, int], int] = {}
        self.bundles: list[SyncedBundle] = []
        self.untracked: list[UntrackedFrame] = []
        self.events: list[SyncEvent] = []
        self.now = T0 - 1.0

    def _set_now(self, t: float) -> None:
        self.now = max(self.now, t)
        if self.clock is not None:
            self.clock.now = self.now

    def _take(self, outs) -> None:
        for o in outs:
            if isinstance(o, SyncedBundle):
                self.bundles.append(o)
            elif isinstance(o, UntrackedFrame):
                self.untracked.append(o)
            else:
                self.events.append(o)

    def advance(self, t: float) -> None:
        while True:
            d = self.sync.next_deadline()
            nxt = t if d is None else min(d, t)
            self._set_now(nxt)
            self._take(self.sync.poll(self.now))
            if nxt >= t:
                return

    def feed(self, arrivals: list[tuple[float, CameraFrame, int]]) -> None:
        """arrivals: (arrival time, frame, true trigger frame); fed in arrival order (stable)."""
        for t, fr, true_tf in sorted(arrivals, key=lambda a: a[0]):
            self.truth[(fr.camera_index, fr.camera_frame)] = true_tf
            fr.recv_time = t
            self.advance(t)
            self._take(self.sync.add(fr, t))

    def finish(self) -> None:
        self.advance(self.now + 1.0)
        self._take(self.sync.flush())

    # --- checks ---------------------------------------------------------------------------------
    def wrong(self) -> list[tuple]:
        bad = []
        for b in self.bundles:
            for cam, fr in b.frames.items():
                want = self.truth[(cam, fr.camera_frame)]
                if want != b.bundle.trigger_frame:
                    bad.append(("tracked", cam, fr.camera_frame, b.bundle.trigger_frame, want))
        for u in self.untracked:
            if u.trigger_frame >= 0:
                want = self.truth[(u.frame.camera_index, u.frame.camera_frame)]
                if want != u.trigger_frame:
                    bad.append((u.reason, u.frame.camera_index, u.frame.camera_frame, u.trigger_frame, want))
        return bad

    def tracked(self) -> int:
        return sum(len(b.frames) for b in self.bundles)

    def kinds(self, kind: str) -> list[SyncEvent]:
        return [e for e in self.events if e.kind == kind]

    def assert_never_mismapped(self, n_frames: int, min_tracked: float = 0.5) -> None:
        bad = self.wrong()
        assert not bad, (len(bad), bad[:8], [e.message for e in self.events][:8])
        assert not self.kinds("drift"), [e.message for e in self.kinds("drift")]
        assert not self.kinds("clock_jump"), [e.message for e in self.kinds("clock_jump")]
        # Everything handed on, and enough of it tracked that the test means something.
        assert self.tracked() + len(self.untracked) == n_frames
        assert self.tracked() >= min_tracked * n_frames, (self.tracked(), n_frames, self._reasons())

    def _reasons(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for u in self.untracked:
            out[u.reason] = out.get(u.reason, 0) + 1
        return out


def make(clock=None, cams=(0, 1, 2), quiet_tie=True, **kw) -> Run:
    clk = clock if clock is not None else FixedRateClock(FPS, start_time=T0)
    sync = FrameSynchronizer(cams, FPS, clock=clk, start_time=T0 - 0.1, **kw)
    if quiet_tie:
        sync.synchronize()  # the trigger session's order: cameras quiet, tie armed, START
    return Run(sync, clk if isinstance(clk, SteppedClock) else None)


def arrivals(
    n: int,
    cams=(0, 1, 2),
    base: dict[int, float] | None = None,
    jitter: float = 0.0005,
    stalls: list[tuple[tuple[int, ...], float, float]] = (),
    drop: set[tuple[int, int]] = frozenset(),
    seed: int = 0,
    edge_tf: bool = False,
) -> list[tuple[float, CameraFrame, int]]:
    """Arrivals of n trigger frames. stalls: (cameras, start time after T0 in s, length in periods):
    what would arrive in [start, start + length) arrives at its end, in sending order."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        for c in cams:
            if (c, k) in drop:
                continue
            t = T0 + k * P + (base or {}).get(c, 0.002) + rng.uniform(0, jitter)
            for who, s0, length in stalls:
                if c in who and T0 + s0 <= t < T0 + s0 + length * P:
                    # released in sending order: a tiny spread keeps the order stable and realistic
                    t = T0 + s0 + length * P + 1e-6 * (k % 1000)
            fr = CameraFrame(camera_index=c, camera_frame=CF0[c] + k, trigger_frame=k if edge_tf else -1,
                             points=PTS, recv_time=t)
            out.append((t, fr, k))
    return out


# --- the cases of issue 5 -------------------------------------------------------------------------


@pytest.mark.parametrize("length", [1, 2, 3, 5, 8, 10.5, 11, 12, 15, 20])
def test_one_camera_stalls_then_bursts(length):
    r = make()
    n = 200
    r.feed(arrivals(n, stalls=[((1,), 0.5003, length)]))
    r.finish()
    r.assert_never_mismapped(3 * n)


@pytest.mark.parametrize("length", [1.5, 5, 10.5, 12, 20])
def test_all_cameras_stall_together(length):
    # A GIL or scheduler stall: nothing arrives, then every camera's frames at once.
    r = make()
    n = 200
    r.feed(arrivals(n, stalls=[((0, 1, 2), 0.6302, length)]))
    r.finish()
    r.assert_never_mismapped(3 * n)


def test_all_cameras_stall_together_and_cameras_released_one_after_another():
    # The fake edges of the trigger test: each edge thread resumes at its own moment after the stall.
    r = make()
    n = 300
    stalls = [((0,), 0.6302, 11.0), ((1,), 0.6302, 11.4), ((2,), 0.6302, 11.9),
              ((0, 1, 2), 1.5, 6.2), ((2,), 2.2, 17.0)]
    r.feed(arrivals(n, stalls=stalls))
    r.finish()
    r.assert_never_mismapped(3 * n)


def test_repeated_random_stalls_on_every_camera():
    rng = np.random.default_rng(5)
    n = 1500
    for trial in range(6):
        stalls = []
        for _ in range(40):
            who = tuple(int(c) for c in rng.choice(3, size=int(rng.integers(1, 4)), replace=False))
            stalls.append((who, float(rng.uniform(0.2, n * P - 0.3)), float(rng.uniform(1, 20))))
        r = make()
        r.feed(arrivals(n, stalls=stalls, jitter=0.003, seed=trial))
        r.finish()
        r.assert_never_mismapped(3 * n, min_tracked=0.3)


def test_jittered_arrival():
    # Up to 1.5 periods of independent delay per packet: packets of one camera overtake each other.
    r = make()
    n = 1000
    r.feed(arrivals(n, jitter=1.5 * P, seed=3))
    r.finish()
    r.assert_never_mismapped(3 * n, min_tracked=0.2)


@pytest.mark.parametrize("late", [0.6, 1.3, 3.2])
def test_camera_consistently_later_than_the_deadline(late):
    # Camera 2's packets always come `late` periods after the others': its frames are late (recorded,
    # not tracked), and still numbered right; it is not a drift.
    r = make(deadline_fraction=0.5)
    n = 400
    r.feed(arrivals(n, base={0: 0.002, 1: 0.002, 2: 0.002 + late * P}))
    r.finish()
    r.assert_never_mismapped(3 * n, min_tracked=0.6)
    assert r.sync.stats()[2].late >= n - 5


def test_camera_late_by_more_than_the_deadline_and_stalling():
    r = make(deadline_fraction=0.5)
    n = 600
    stalls = [((2,), 1.0, 12), ((0, 1, 2), 2.0, 15), ((0, 1), 3.0, 9)]
    r.feed(arrivals(n, base={0: 0.002, 1: 0.002, 2: 0.0105}, stalls=stalls))
    r.finish()
    r.assert_never_mismapped(3 * n, min_tracked=0.5)


def test_trigger_clock_model_steps_by_about_a_period():
    # The clock model's snapshot is replaced (offset-only -> fitted, a better round trip, simavr
    # catching up): every frame time moves by about a period at once. Camera frames did not change.
    for shift in (+1.1 * P, -1.1 * P, 2.6 * P, -0.8 * P):
        clock = SteppedClock([(T0 + 0.6305, shift), (T0 + 1.5, -shift / 2)])
        r = make(clock=clock)
        n = 300
        r.feed(arrivals(n))
        r.finish()
        r.assert_never_mismapped(3 * n)


def test_clock_step_during_a_stall():
    clock = SteppedClock([(T0 + 0.64, 1.2 * P)])
    r = make(clock=clock)
    n = 300
    r.feed(arrivals(n, stalls=[((0, 1, 2), 0.6302, 12)]))
    r.finish()
    r.assert_never_mismapped(3 * n)


def test_dropped_packets_leave_counter_gaps_and_change_nothing():
    rng = np.random.default_rng(7)
    n = 500
    drop = {(int(c), int(k)) for c, k in zip(rng.integers(0, 3, 150), rng.integers(1, n, 150), strict=True)}
    drop |= {(1, k) for k in range(200, 230)}  # a run of 30 lost frames
    r = make()
    arr = arrivals(n, drop=drop, stalls=[((0,), 1.0, 8)])
    r.feed(arr)
    r.finish()
    r.assert_never_mismapped(len(arr))


def test_reordered_packets():
    n = 400
    arr = arrivals(n)
    rng = np.random.default_rng(11)
    by = {(a[1].camera_index, a[2]): i for i, a in enumerate(arr)}
    # Neighbours swapped in the network.
    for k in rng.integers(5, n - 5, 40):
        c = int(rng.integers(0, 3))
        i, j = by[(c, int(k))], by[(c, int(k) + 1)]
        (ti, fi, ki), (tj, fj, kj) = arr[i], arr[j]
        arr[i], arr[j] = (tj, fi, ki), (ti, fj, kj)
    # Three consecutive frames of camera 1 held back 0.4 s in the network and delivered together.
    for k in (150, 151, 152):
        i = by[(1, k)]
        _, f, kk = arr[i]
        arr[i] = (T0 + 152 * P + 0.4 + 1e-6 * k, f, kk)
    r = make()
    r.feed(arr)
    r.finish()
    r.assert_never_mismapped(3 * n)


def test_first_frames_stalled_are_still_tied_to_frame_zero():
    # Right after START one camera (or all) stalls: its first frames arrive in a burst after the others'.
    for stalls in ([((1,), 0.0, 15)], [((0, 1, 2), 0.0, 7)], [((2,), 0.0, 3), ((0,), 0.0, 19)]):
        r = make()
        n = 200
        r.feed(arrivals(n, stalls=stalls))
        r.finish()
        r.assert_never_mismapped(3 * n)


def test_edge_trigger_frame_always_wins():
    # With the edge's trigger_frame filled in, no arrival pattern and no clock step may change it.
    clock = SteppedClock([(T0 + 0.63, 1.3 * P)])
    r = make(clock=clock)
    n = 600
    stalls = [((1,), 0.5, 20), ((0, 1, 2), 1.5, 12), ((2,), 2.5, 15), ((0,), 3.3, 4)]
    arr = arrivals(n, base={0: 0.002, 1: 0.002, 2: 0.025}, stalls=stalls, jitter=0.004, edge_tf=True)
    r.feed(arr)
    r.finish()
    bad = r.wrong()
    assert not bad, bad[:8]
    assert r.tracked() + len(r.untracked) == 3 * n
    assert not r.kinds("clock_jump")


# --- real evidence still re-maps ------------------------------------------------------------------


def _drop_pulse(arr, cam: int, at: int):
    """Camera `cam` misses trigger pulse `at` without its counter showing it: from then on its frame
    counted `CF0 + k` answers pulse k + 1 (its frame rate is not the trigger's)."""
    out = []
    for t, fr, k in arr:
        if fr.camera_index == cam and k >= at:
            if k == at:
                continue
            fr.camera_frame -= 1
        out.append((t, fr, k))
    return out


def test_camera_that_misses_a_pulse_is_remapped_even_with_stalls_around():
    n = 400
    arr = arrivals(n, stalls=[((0, 1, 2), 0.5, 12), ((2,), 1.2, 6), ((0,), 2.5, 10)])
    arr = _drop_pulse(arr, 2, 150)
    r = make(drift_frames=10, drift_min_s=0.0)  # the mechanism at its quickest; defaults below
    r.feed(arr)
    r.finish()
    drift = r.kinds("drift")
    assert [e.camera_index for e in drift] == [2], [e.message for e in r.events]
    # Frames mapped wrong only between the missed pulse and the confirmation.
    bad = r.wrong()
    assert bad and all(b[1] == 2 and 150 <= r.truth[(2, b[2])] <= 150 + 25 for b in bad), bad
    assert len(bad) <= 25


def test_camera_counter_restart_under_bursts_is_remapped():
    n = 400
    arr = arrivals(n, stalls=[((0, 1, 2), 0.8, 10), ((1,), 2.0, 14)])
    for _, fr, k in arr:
        if fr.camera_index == 1 and k >= 120:
            fr.camera_frame -= CF0[1] + 120 - 3  # the camera restarted counting at 3
    r = make()
    r.feed(arr)
    r.finish()
    assert [e.camera_index for e in r.kinds("clock_jump")] == [1]
    assert not r.kinds("drift")
    bad = r.wrong()
    # The frames that confirm the restart are recorded untracked; nothing after it is wrong.
    assert all(r.truth[(b[1], b[2])] < 130 for b in bad), bad


def test_camera_running_at_a_slightly_different_rate_is_followed():
    # Camera 1 runs 0.4 % slow (free-running near the trigger's rate): every ~250 pulses its counter
    # falls one behind. Each slip is reported and re-mapped; its frames are wrong only around slips.
    n = 1500
    arr = []
    rng = np.random.default_rng(4)
    for c in (0, 1, 2):
        k_cam = 0
        for k in range(n):
            if c == 1 and k > 0 and k % 250 == 0:
                continue  # the pulse it missed
            t = T0 + k * P + 0.002 + rng.uniform(0, 0.0005)
            arr.append((t, CameraFrame(c, CF0[c] + k_cam, -1, PTS, t), k))
            k_cam += 1
    r = make(drift_frames=10, drift_min_s=0.0)
    r.feed(arr)
    r.finish()
    drift = r.kinds("drift")
    assert [e.camera_index for e in drift] == [1] * 5, [e.message for e in drift]
    bad = r.wrong()
    assert all(b[1] == 1 and (r.truth[(1, b[2])] % 250) <= 25 for b in bad), bad
    assert len(bad) <= 5 * 25


def test_edge_numbered_camera_that_drifts_is_reported_not_renumbered():
    # The edge stamps trigger frames, and camera 2's stamps are off by one from pulse 100 on: the
    # arrivals say so (reported), but the edge's number is what is used.
    n = 300
    arr = arrivals(n, edge_tf=True)
    for _, fr, k in arr:
        if fr.camera_index == 2 and k >= 100:
            fr.trigger_frame = k - 1
    r = make(drift_frames=10)
    r.feed([(t, fr, fr.trigger_frame) for t, fr, _ in arr])  # truth: the edge's number
    r.finish()
    assert [e.camera_index for e in r.kinds("drift")] == [2]
    assert "re-mapped" not in r.kinds("drift")[0].message
    assert not r.wrong()


def test_two_camera_rig_never_remaps_on_arrival():
    # With two cameras, which one moved cannot be told from arrivals: stalls never re-map.
    r = make(cams=(0, 1))
    n = 300
    r.feed(arrivals(n, cams=(0, 1), stalls=[((1,), 0.5, 15), ((0, 1), 1.2, 12), ((0,), 2.0, 11)]))
    r.finish()
    r.assert_never_mismapped(2 * n)


def test_a_transient_arrival_shift_of_most_of_a_period_is_not_a_drift():
    """At high frame rates a busy host can shift one camera's arrivals by most of a period for a
    fraction of a second (seen in the 11-camera, 200 fps simulated rig: 0.72 period for 0.19 s,
    re-mapped and back). A missed pulse shifts them for good: only that may re-map."""
    n = 300
    arr = arrivals(n)
    shifted = []
    for t, fr, k in arr:
        if fr.camera_index == 0 and 100 <= k < 120:  # 0.2 s early by 0.72 period
            t -= 0.72 * P
            fr.recv_time = t
        shifted.append((t, fr, k))
    r = make()
    r.feed(shifted)
    r.finish()
    r.assert_never_mismapped(3 * n)


def test_a_missed_pulse_is_remapped_with_the_default_evidence():
    n = 400
    arr = _drop_pulse(arrivals(n), 2, 150)
    r = make()
    r.feed(arr)
    r.finish()
    assert [e.camera_index for e in r.kinds("drift")] == [2], [e.message for e in r.events]
    bad = r.wrong()
    # Mis-mapped only from the missed pulse until the evidence spans drift_min_s (0.5 s = 50 frames)
    # and the frames settle.
    assert bad and all(b[1] == 2 and 150 <= r.truth[(2, b[2])] <= 150 + 60 for b in bad), bad
