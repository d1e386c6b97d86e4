"""Issue 16's fixes, piece by piece and deterministic: misnumbered frames, edge restarts, the
fixed-rate clock after a pause, the host clock seam, rate-limited logs, range checks, latency overflow,
one sender per camera. The same faults against the real processes: tests/faults."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np

from flytrack_host.intake.receiver import Receiver
from flytrack_host.intake.sync import (
    CameraFrame,
    FixedRateClock,
    FrameSynchronizer,
    SyncedBundle,
    SyncEvent,
    UntrackedFrame,
)
from flytrack_host.pipeline import data2d_rows
from flytrack_host.recording.latency import LatencyStats
from flytrack_host.recording.schema import FLAG_REJECTED, FLAG_TRACKED
from flytrack_host.sim.faults import inject as fi
from flytrack_host.util import hostclock
from flytrack_host.util.ratelog import RateLimitedLog

FPS = 100.0
P = 1.0 / FPS
T0 = 1000.0
PTS = np.zeros(1, dtype=[("x_dist", "<f4")])


class Run:
    def __init__(self, cams=(0, 1, 2), clock=None):
        self.sync = FrameSynchronizer(cams, FPS, clock=clock or FixedRateClock(FPS), start_time=T0)
        self.bundles: list[SyncedBundle] = []
        self.untracked: list[UntrackedFrame] = []
        self.events: list[SyncEvent] = []
        self.now = T0

    def _take(self, outs):
        for o in outs:
            {SyncedBundle: self.bundles, UntrackedFrame: self.untracked, SyncEvent: self.events}[type(o)].append(o)

    def add(self, fr: CameraFrame):
        while True:  # poll every deadline before the frame arrives, as the pipeline does
            d = self.sync.next_deadline()
            if d is None or d > fr.recv_time:
                break
            self.now = max(self.now, d)
            self._take(self.sync.poll(self.now))
        self.now = max(self.now, fr.recv_time)
        self._take(self.sync.add(fr, fr.recv_time))

    def tracked(self):
        """(camera, camera frame) -> trigger frame of every tracked frame."""
        return {(c, f.camera_frame): b.bundle.trigger_frame for b in self.bundles for c, f in b.frames.items()}

    def tracked_list(self):
        return [(c, f.camera_frame, b.bundle.trigger_frame) for b in self.bundles for c, f in b.frames.items()]


def frame(cam, cf, t, restarted=False):
    return CameraFrame(camera_index=cam, camera_frame=cf, trigger_frame=-1, points=PTS, recv_time=t,
                       restarted=restarted)


def test_wrong_numbers_mixed_into_a_good_stream_are_rejected_frame_by_frame():
    r = Run()
    for k in range(300):
        t = T0 + k * P + 0.002
        for c in (0, 1, 2):
            r.add(frame(c, 100 * c + k, t + 0.0001 * c))
        if 100 <= k < 200:  # camera 1's numbers + 48, from its own address (a replaying edge)
            r.add(frame(1, 100 + k + 48, t + 0.003))
    good = r.tracked()
    assert all(tf == cf - 100 * c for (c, cf), tf in good.items())  # every tracked frame right
    assert len(good) >= 3 * 298
    early = [u for u in r.untracked if u.reason == "early"]
    assert len(early) == 100 and r.sync.stats()[1].early == 100
    assert not r.sync.stats()[1].clock_jumps


def test_a_gap_in_the_good_stream_does_not_let_wrong_numbers_confirm_a_jump():
    r = Run()
    for k in range(200):
        t = T0 + k * P + 0.002
        for c in (0, 2):
            r.add(frame(c, k, t))
        if 100 <= k < 105:  # camera 1's edge stalls 5 frames; three wrong frames come in between
            if k < 103:
                r.add(frame(1, k + 48, t))
            continue
        r.add(frame(1, k, t))
    assert all(tf == cf for (_, cf), tf in r.tracked().items())
    assert r.sync.stats()[1].clock_jumps == 0


def test_an_edge_restart_is_mapped_by_arrival_and_its_gap_counted():
    r = Run()
    for k in range(100):
        for c in (0, 1, 2):
            r.add(frame(c, k, T0 + k * P + 0.002))
    for k in range(100, 200):  # camera 1's edge is down for 40 frames, then restarts at 0
        t = T0 + k * P + 0.002
        for c in (0, 2):
            r.add(frame(c, k, t))
        if k >= 140:
            r.add(frame(1, k - 140, t + 0.0005, restarted=(k == 140)))
    got = r.tracked_list()
    assert all(tf == k + 140 for c, k, tf in got if c == 1 and tf >= 100)
    # Its first 10 frames are held until it is placed (10 paced frames): recorded, not tracked.
    assert sum(1 for c, _, tf in got if c == 1 and tf >= 140) >= 48
    s = r.sync.stats()[1]
    assert s.restarts == 1 and s.missed == 40  # trigger frames 100..139
    assert any(e.kind == "restart" for e in r.events)
    # Its first frames are not filed under trigger frames 0 and 1 again.
    assert sum(1 for c, _, tf in got if c == 1 and tf < 2) == 2


def test_the_fixed_rate_clock_is_reanchored_after_every_camera_paused():
    r = Run()
    for k in range(300):
        t = T0 + k * P + 0.002 + (0.5 if k >= 100 else 0.0)  # the cameras pause 0.5 s after frame 99
        for c in (0, 1, 2):
            r.add(frame(c, k, t))
    assert [e for e in r.events if e.kind == "reanchor"]
    late = [b.last_arrival - b.bundle.timestamp for b in r.bundles if b.bundle.trigger_frame >= 150]
    assert max(late) < 0.01  # before: every later frame ~0.5 s late
    assert all(tf == cf for (_, cf), tf in r.tracked().items())


def test_a_stall_and_burst_do_not_reanchor_the_fixed_rate_clock():
    r = Run()
    for k in range(300):
        t = T0 + k * P + 0.002
        if 100 <= k < 150:
            t = T0 + 150 * P + 0.002 + (k - 100) * 0.0001  # a 0.5 s stall, then the backlog in a burst
        for c in (0, 1, 2):
            r.add(frame(c, k, t))
    assert not [e for e in r.events if e.kind == "reanchor"]


def test_the_wall_clock_only_labels_and_steps_are_noticed():
    c = hostclock.HostClock()
    t0, w0 = c.now(), c.wall()
    assert c.check_wall() is None
    c.step_wall(-30.0)
    assert abs((c.wall() - w0) - (-30.0)) < 1.0
    assert 0 <= c.now() - t0 < 1.0  # host time did not move with it
    assert abs(c.check_wall() + 30.0) < 0.05 and c.steps_seen == 1
    assert c.check_wall() is None


def test_wall_steps_from_the_environment_reach_a_real_process():
    # Host time moves as the monotonic clock did, bracketed by monotonic reads on either side (a loaded
    # machine sleeps 0.3 s for 0.35 s or more: `round(elapsed, 1) == 0.3` failed so), untouched by the
    # -1 h step of the wall clock.
    code = ("import time; from flytrack_host.util import hostclock as h; m=time.monotonic; "
            "a=m(); t=h.now(); b=m(); w=h.wall(); time.sleep(0.3); c=m(); t2=h.now(); d=m(); "
            "print(round(h.wall()-w-(t2-t)), int(c-b <= t2-t <= d-a), int(t2-t >= 0.3))")
    env = dict(os.environ, FLYTRACK_FAULT_WALL_STEPS="0.1:-3600")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.split() == ["-3600", "1", "1"], out
    bad = subprocess.run([sys.executable, "-c", "import flytrack_host.util.hostclock"], capture_output=True, text=True,
                         env=dict(os.environ, FLYTRACK_FAULT_WALL_STEPS="soon"))
    assert bad.returncode != 0 and "AT_SECONDS:STEP_SECONDS" in bad.stderr


def test_rate_limited_log_counts_every_kind_and_never_stops_logging():
    lines: list[str] = []
    log = RateLimitedLog(lines.append, interval_s=5.0, max_kinds=10)
    for i in range(5000):  # random camera indices: one kind, not 5000
        log("unknown_camera", f"camera index {i}: rejected", now=i * 0.001)
    assert lines == ["camera index 0: rejected"]  # once; the rest counted
    log.flush(now=5.0)
    assert lines[-1] == "camera index 4999: rejected (4999 more like this since the last report, 5000 in all)"
    for k in range(50):  # more kinds than the bound: still logged, in "other"
        log(f"kind{k}", f"problem {k}", now=10.0)
    assert log.counts["other"] == 41 and lines[-1] == "problem 9"
    log("late real problem", "a real problem", now=16.0)  # a later, different problem is logged
    assert lines[-1].startswith("a real problem") and "42 in all" in lines[-1]


def test_values_out_of_range_are_recorded_flagged_and_named():
    fr = CameraFrame(camera_index=1, camera_frame=2**64 + 5, trigger_frame=-1, points=PTS, recv_time=1.0,
                     total_points=70000)
    bad: list[str] = []
    rows = data2d_rows(fr, 2**70, 1.0, FLAG_TRACKED, bad)
    assert len(rows) == 1 and rows["trigger_frame"][0] == -1 and rows["camera_frame"][0] == 0
    assert rows["flags"][0] & FLAG_REJECTED and not rows["flags"][0] & FLAG_TRACKED
    assert any("camera_frame" in b for b in bad) and any("total_points" in b for b in bad)


def test_latency_beyond_the_histogram_is_reported_exactly():
    s = LatencyStats()
    for i in range(100):
        s.row(i, 0.0, 0.0, 0.0, 0.002 if i < 40 else 3600.026, 3, 0)
    out = s.summary()
    assert out["total_p50_ms"] == 3600026.0 or abs(out["total_p50_ms"] - 3600026.0) < 1e-3
    assert out["total_overflow"] == 60
    assert "60 frames at 1 s or more" in s.format()


def test_one_sender_per_camera_and_a_new_port_after_silence_is_a_restart(helpers):
    import time

    logs: list[str] = []
    rx = Receiver(helpers.make_rig(1), bind="127.0.0.1:0", log=logs.append, sender_switch_s=0.2)
    a, b = helpers.EdgeSim(0, rx.address), helpers.EdgeSim(0, rx.address)
    try:
        got = []
        for k in range(5):
            a.send(k)
            b.send(k + 1000)  # a second edge with the same index while the first sends
            time.sleep(0.01)
            got += rx.receive(0.05)
        assert [f.camera_frame for f in got] == list(range(5))
        assert rx.stats.cameras[0].second_sender == 5
        assert sum("second sender" in m for m in logs) == 1  # once, then counted
        time.sleep(0.3)  # the first edge went quiet: one stray datagram from elsewhere takes nothing over
        b.send(77)
        assert rx.receive(0.2) == [] and rx.stats.cameras[0].restarts == 0
        a.send(5)  # the owner is back
        assert [f.camera_frame for f in rx.receive(0.5)] == [5]
        time.sleep(0.3)  # now it is gone for good; a new edge sends three frames: a restart
        b.seq = 0
        for k in range(3):
            b.send(k)
        got = []
        for _ in range(3):
            got += rx.receive(0.2)
        assert [f.camera_frame for f in got] == [0, 1, 2]  # held until confirmed, none lost
        assert got[0].restarted and not got[1].restarted and rx.stats.cameras[0].restarts == 1
        assert rx.stats.cameras[0].reordered == 0 and rx.stats.cameras[0].lost == 0
        # every datagram counted once: 5 + 1 from the owner, 3 from the new edge; 5 + 1 rejected/held
        assert rx.stats.cameras[0].packets == 9 and rx.stats.datagrams == 5 + 5 + 1 + 1 + 3
    finally:
        a.close()
        b.close()
        rx.close()


def test_a_restarted_edge_whose_first_frames_come_late_and_bunched_is_placed_right():
    # The new edge starts slowly: its first 8 frames arrive together 70 ms late. Placed by the first
    # arrival they would be ~7 frames ahead; the synchroniser holds them until its frames come paced.
    r = Run()
    for k in range(100):
        for c in (0, 1, 2):
            r.add(frame(c, k, T0 + k * P + 0.002))
    for k in range(100, 250):
        t = T0 + k * P + 0.002
        for c in (0, 2):
            r.add(frame(c, k, t))
        if k >= 140:
            t1 = max(t, T0 + 147 * P + 0.002 + (k - 140) * 0.0001) if k < 148 else t
            r.add(frame(1, k - 140, t1, restarted=(k == 140)))
    wrong = [(cf, tf) for c, cf, tf in r.tracked_list() if c == 1 and tf >= 100 and tf != cf + 140]
    assert not wrong and r.sync.stats()[1].ahead == 0  # placed right at once, no re-map needed
    after = [(cf, tf) for c, cf, tf in r.tracked_list() if c == 1 and tf >= 140 and cf >= 40]
    assert len(after) >= 60 and all(tf == cf + 140 for cf, tf in after)  # right from 0.4 s on
    assert abs(r.sync.stats()[1].missed - 40) <= 1


def test_a_restarted_edge_is_taken_over_by_arrival_times_however_late_the_host_handles_them(helpers):
    """The host handles the old edge's last datagram and the restarted edge's first three in one
    batch (it was not scheduled for 0.7 s): their arrival stamps are 0.7 s apart, so it is a restart,
    none lost. Before, silence was judged by when the host got to them (no time at all): the new edge
    was rejected as a second sender (41 frames lost at load 15)."""
    from flytrack_host.protocol import FeatureFrame, encode_features, make_points

    logs: list[str] = []
    rx = Receiver(helpers.make_rig(1), bind="127.0.0.1:0", log=logs.append)
    try:
        def dgram(seq: int, cf: int) -> bytes:
            f = FeatureFrame(camera_index=0, seq=seq, camera_frame=cf, total_points=1, points=make_points(1))
            return encode_features(f)[0]

        out: list = []
        for k in range(5):
            rx.handle(dgram(k, 100 + k), ("127.0.0.1", 40001), T0 + k * P, out)
        for k in range(3):  # the new edge, 0.7 s after the old one's last datagram, handled at once
            rx.handle(dgram(k, k), ("127.0.0.1", 40002), T0 + 4 * P + 0.7 + k * P, out)
        assert [f.camera_frame for f in out] == [100, 101, 102, 103, 104, 0, 1, 2]
        assert out[5].restarted and rx.stats.cameras[0].restarts == 1 and rx.stats.cameras[0].second_sender == 0
        # A second sender while the owner sends (by arrival) is still rejected.
        rx.handle(dgram(9, 9), ("127.0.0.1", 40003), T0 + 4 * P + 0.7 + 3 * P, out)
        assert rx.stats.cameras[0].second_sender == 1 and len(out) == 8
    finally:
        rx.close()


# --- SignalEdge (the edge-stop / edge-gone faults) against real processes -------------------------------
def _proc_state(pid: int) -> str:
    """The state letter of /proc/PID/stat ('T': stopped by a signal)."""
    with open(f"/proc/{pid}/stat") as f:
        stat = f.read()
    return stat[stat.rindex(")") + 2]


def _wait_state(pid: int, states: str, timeout_s: float = 10.0) -> str:
    deadline = time.monotonic() + timeout_s
    while (st := _proc_state(pid)) not in states and time.monotonic() < deadline:
        time.sleep(0.01)
    return st


def _edges_ctx(proc: subprocess.Popen) -> SimpleNamespace:
    # The fault reads only ctx.edges.procs (the demo's edge Popen objects); the process is real.
    return SimpleNamespace(edges=SimpleNamespace(procs=[proc]))


def test_signal_edge_holds_a_live_edge_stopped_then_continues_it():
    p = subprocess.Popen(["sleep", "60"])
    try:
        fault = fi.SignalEdge(camera=0, at_s=0.0, hold_s=60.0)
        fault.start(_edges_ctx(p))
        assert _wait_state(p.pid, "T") == "T"
        time.sleep(0.2)
        assert _proc_state(p.pid) == "T"  # held for hold_s, until the fault is stopped
        fault.stop()  # ends the hold: SIGCONT
        assert _wait_state(p.pid, "SR") in "SR"
        assert p.poll() is None and fault.error is None and "edge_ended" not in fault.info
        assert fault.t_end >= fault.t_start
    finally:
        p.kill()
        p.wait()


def test_signal_edge_against_an_edge_that_already_ended_logs_it_and_does_not_fail(caplog):
    p = subprocess.Popen(["true"])
    p.wait()  # ended and reaped (the demo's watchdog polls its edges): its pid is free
    fault = fi.SignalEdge(camera=0, at_s=0.0, hold_s=0.1)
    with caplog.at_level(logging.WARNING, logger="flytrack.faults"):
        fault.start(_edges_ctx(p))
        fault.stop()
    assert fault.error is None
    assert fault.info["edge_ended"] == "before SIGSTOP (exit status 0)"
    assert f"camera 0 (pid {p.pid}) had already ended" in caplog.text and "no SIGSTOP sent" in caplog.text


def test_signal_edge_whose_edge_ends_while_held_logs_it_and_does_not_fail(caplog):
    p = subprocess.Popen(["sleep", "60"])
    try:
        fault = fi.SignalEdge(camera=0, at_s=0.0, hold_s=60.0)
        with caplog.at_level(logging.WARNING, logger="flytrack.faults"):
            fault.start(_edges_ctx(p))
            assert _wait_state(p.pid, "T") == "T"
            p.kill()  # SIGKILL ends a stopped process too
            p.wait()
            fault.stop()
        assert fault.error is None
        assert fault.info["edge_ended"] == "before SIGCONT (exit status -9)"
        assert "no SIGCONT sent" in caplog.text
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
