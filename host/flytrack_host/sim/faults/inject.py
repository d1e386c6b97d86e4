"""Fault injectors for a running `flytrack demo` (see `suite.py`).

Each injector is handed the demo's live parts (`sim.run.DemoContext`): the host pipeline, the edge
processes, the simulated cameras, the trigger. It runs on its own thread and injects its fault
`at_s` seconds after the trigger started. It notes in host time when the fault began and ended, and
what the truth is where the fault changes it (the frames a restarted edge got). Everything it uses is
real: signals to real processes, datagrams on loopback, a second `flytrack-edge` process. Frames from
a misbehaving edge are IPv4/UDP packets built by hand on a raw socket, so they carry the real edge's
source port (this needs root; `needs_root` says so). Wall-clock steps go through the host's clock seam
(`hostclock.CLOCK.step_wall`), the same offset `FLYTRACK_FAULT_WALL_STEPS` sets for `flytrack run`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from typing import Any

import numpy as np

from flytrack_host.protocol import FeatureFrame, encode_features, make_points
from flytrack_host.util import children, hostclock

log = logging.getLogger("flytrack.faults")

ROGUE_MARK = 0xFA17_FA17_FA17_FA17  # device_timestamp_ns of injected frames: the measurement leaves them out


class Fault:
    """Base: run `inject` once, `at_s` after start, on a thread; note its host-time span."""

    needs_root = False
    at_s = 1.0

    def __init__(self, **kw: Any) -> None:
        self.__dict__.update(kw)
        self.t_start = float("nan")
        self.t_end = float("nan")
        self.info: dict[str, Any] = {}
        self.truth: dict[int, dict[int, int]] = {}  # camera -> {camera_frame: trigger frame}, replaced frames
        self.truth_after: dict[int, float] = {}  # camera -> host time from which `truth` applies
        self.error: str | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, ctx: Any) -> None:
        self.ctx = ctx
        self._thread = threading.Thread(target=self._run, name=f"fault-{type(self).__name__}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        if self._stop.wait(self.at_s):
            return
        self.t_start = hostclock.now()
        try:
            self.inject(self.ctx)
        except Exception as exc:  # reported in the table, never hidden
            self.error = f"{type(exc).__name__}: {exc}"
        self.t_end = hostclock.now() if self.t_end != self.t_end else self.t_end

    def inject(self, ctx: Any) -> None:
        raise NotImplementedError

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10.0)
        self.cleanup()

    def cleanup(self) -> None:
        pass


class NoFault(Fault):
    def inject(self, ctx: Any) -> None:
        pass


class WallStep(Fault):
    """The host's wall clock steps by `seconds` (as an NTP step or a user setting the date would)."""

    seconds = -1.0

    def inject(self, ctx: Any) -> None:
        hostclock.CLOCK.step_wall(self.seconds)


class SignalEdge(Fault):
    """SIGSTOP an edge process for `hold_s`, then SIGCONT (a frozen edge computer, or a camera gone)."""

    camera = 1
    hold_s = 0.3

    def inject(self, ctx: Any) -> None:
        p = ctx.edges.procs[self.camera]
        if not self._signal(p, signal.SIGSTOP):
            return
        try:
            self._stop.wait(self.hold_s)
        finally:
            self._signal(p, signal.SIGCONT)

    def _signal(self, p: subprocess.Popen, sig: signal.Signals) -> bool:
        """Send `sig` to the edge; False when the edge had already ended (a gone edge is what this
        fault simulates: logged and noted in `info`, not an error). Asked through `Popen.poll` first:
        once the demo's watchdog reaped the edge its pid is free, and may be another process's."""
        code = p.poll()
        if code is None:
            try:
                os.kill(p.pid, sig)
                return True
            except ProcessLookupError:  # it ended, and another thread reaped it, since the poll
                code = p.poll()
        name = signal.Signals(sig).name
        log.warning("fault %s: the edge of camera %d (pid %d) had already ended (exit status %s): no %s "
                    "sent; the camera is gone, as this fault simulates", type(self).__name__, self.camera,
                    p.pid, code, name)
        self.info["edge_ended"] = f"before {name} (exit status {code})"
        return False


class HostStop(Fault):
    """SIGSTOP the host process itself for `hold_s` (an overloaded or swapping host), from a child
    shell, then SIGCONT: the host must catch up and say what it skipped."""

    hold_s = 1.5

    def inject(self, ctx: Any) -> None:
        pid = os.getpid()
        children.run(["sh", "-c", f"kill -STOP {pid}; sleep {self.hold_s}; kill -CONT {pid}"], check=True)


class TriggerPause(Fault):
    """The trigger stops pulsing for `hold_s` and resumes (its count goes on): the cameras pause.
    With the host on a fixed-rate clock (--no-trigger) the clock must be re-anchored."""

    hold_s = 0.5

    def inject(self, ctx: Any) -> None:
        s = ctx.session
        with s._dev_lock:  # the session's clock thread must not take the pause for a device reset
            s._expect_running = False
            s.device.stop()
        self._stop.wait(self.hold_s)
        with s._dev_lock:
            s.device.start()
        time.sleep(0.3)
        s._expect_running = True


def _spoof_udp(sock: socket.socket, src: tuple[str, int], dst: tuple[str, int], payload: bytes) -> None:
    """One UDP datagram with a chosen source address and port, IPv4 header built by hand."""
    udp = struct.pack("!HHHH", src[1], dst[1], 8 + len(payload), 0)  # checksum 0: none (IPv4)
    ip = struct.pack("!BBHHHBBH4s4s", 0x45, 0, 20 + 8 + len(payload), 0, 0, 64, socket.IPPROTO_UDP, 0,
                     socket.inet_aton(src[0]), socket.inet_aton(dst[0]))
    sock.sendto(ip + udp + payload, (dst[0], 0))


class MisnumberingEdge(Fault):
    """Well-formed FEATURES from a camera's own edge address and port with frame numbers `shift` ahead
    (a misbehaving edge, or a replay tool keeping the port), one per `period`, for `hold_s`."""

    needs_root = True
    camera = 1
    shift = 48
    hold_s = 1.0

    def inject(self, ctx: Any) -> None:
        rx, sync = ctx.host.receiver, ctx.host.sync
        port = rx._senders[self.camera][0]
        raw = socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_RAW)
        sent = 0
        end = time.monotonic() + self.hold_s
        seq = 100_000
        try:
            while time.monotonic() < end and not self._stop.is_set():
                cf = (sync.cams[self.camera].last_cf or 0) + self.shift
                f = FeatureFrame(camera_index=self.camera, seq=seq + sent, camera_frame=cf,
                                 device_timestamp_ns=ROGUE_MARK, total_points=2, points=make_points(2))
                for d in encode_features(f):
                    _spoof_udp(raw, ("127.0.0.1", port), ("127.0.0.1", ctx.port), d)
                sent += 1
                time.sleep(1.0 / ctx.fps)
        finally:
            raw.close()
        self.info["sent"] = sent


class GarbageFlood(Fault):
    """`n` random datagrams, then `n_valid` well-formed FEATURES with random camera indices, from a
    separate process on the edges' address, paced at `rate` datagrams a second (`flood`)."""

    n = 20_000
    n_valid = 5_000
    rate = 25_000.0

    def inject(self, ctx: Any) -> None:
        children.run([sys.executable, "-m", "flytrack_host.sim.faults.inject", "127.0.0.1", str(ctx.port),
                        str(self.n), str(self.n_valid), str(self.rate)], check=True, timeout=120)
        self.info["sent"] = self.n + self.n_valid


def flood(host: str, port: int, n: int, n_valid: int, rate: float) -> None:
    rng = np.random.default_rng(5)
    dst = (host, port)
    t0 = time.monotonic()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for i in range(n):
            s.sendto(rng.integers(0, 256, int(rng.integers(1, 600)), dtype=np.uint8).tobytes(), dst)
            if i % 500 == 0:
                time.sleep(max(0.0, t0 + i / rate - time.monotonic()))
        for i in range(n_valid):
            f = FeatureFrame(camera_index=int(rng.integers(0, 65536)), seq=i, camera_frame=i,
                             device_timestamp_ns=ROGUE_MARK, total_points=1, points=make_points(1))
            for d in encode_features(f):
                s.sendto(d, dst)


class _FedEdge:
    """A real `flytrack-edge` process for a camera, fed flat grey frames by this thread, one for each
    frame the simulated cameras rendered (so it keeps their pace, also when a busy machine makes them
    lag behind the trigger)."""

    def __init__(self, ctx: Any, camera: int, log_name: str) -> None:
        from flytrack_host.sim.run import edge_command

        cam = ctx.cameras[camera]
        self.frame = np.full((cam.height, cam.width), 40, dtype=np.uint8).tobytes()
        log = open(ctx.out / log_name, "wb")  # noqa: SIM115 (kept open for the process's life)
        # Started from the fault's thread, which ends before this edge: util.children forks it from a
        # thread that lasts, and it ends with the demo.
        self.proc = children.popen(edge_command(ctx.edge_bin, camera, cam, ctx.port), stdin=subprocess.PIPE,
                                   stdout=log, stderr=subprocess.STDOUT, close_fds=True)
        self.written: dict[int, int] = {}  # camera frame -> trigger frame (pulse) it answers

    def feed_until(self, ctx: Any, end_mono: float, stop: threading.Event) -> None:
        seen = ctx.feeder.frames_rendered
        assert self.proc.stdin is not None
        while time.monotonic() < end_mono and not stop.is_set():
            # Every frame rendered before the cameras were done is written, also when this thread
            # runs behind them (a loaded host): stopping at `done` lost the last 17 of a run.
            done = ctx.feeder.done
            now_seen = ctx.feeder.frames_rendered
            while seen < now_seen:
                seen += 1
                try:
                    self.proc.stdin.write(self.frame)
                    self.proc.stdin.flush()
                except OSError:
                    return
                self.written[len(self.written)] = seen - 1
            if done:
                return
            time.sleep(0.0005)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            if self.proc.stdin is not None:
                self.proc.stdin.close()
        try:
            self.proc.wait(3.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(2.0)


class SecondEdge(Fault):
    """A second real `flytrack-edge` started with a camera index already in use, for `hold_s`."""

    camera = 1
    hold_s = 1.0

    def inject(self, ctx: Any) -> None:
        self.edge = _FedEdge(ctx, self.camera, "edge_second.log")
        self.edge.feed_until(ctx, time.monotonic() + self.hold_s, self._stop)
        self.edge.close()
        self.info["sent"] = len(self.edge.written)


class EdgeRestart(Fault):
    """SIGKILL a camera's edge; `down_s` later a new `flytrack-edge` for the same camera starts and
    runs to the end (its counter restarts at 0; its source port is new)."""

    camera = 1
    down_s = 0.6

    def inject(self, ctx: Any) -> None:
        p = ctx.edges.procs[self.camera]
        p.kill()
        p.wait(5.0)
        t_kill_seen = ctx.feeder.frames_rendered
        self._stop.wait(self.down_s)
        self.edge = _FedEdge(ctx, self.camera, "edge_restarted.log")
        self.truth_after[self.camera] = hostclock.now()
        self.t_end = hostclock.now()
        self.info["pulses_while_down"] = ctx.feeder.frames_rendered - t_kill_seen
        self.edge.feed_until(ctx, time.monotonic() + 3600, self._stop)

    def cleanup(self) -> None:
        edge = getattr(self, "edge", None)
        if edge is not None:
            edge.close()
            time.sleep(0.3)  # its last datagrams reach the host before it stops
            self.truth[self.camera] = dict(edge.written)


# The flood's own process: python -m flytrack_host.sim.faults.inject HOST PORT N N_VALID RATE
if __name__ == "__main__":
    flood(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5]))
