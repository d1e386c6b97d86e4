"""The simulated cameras' exposure loop: one child process that turns trigger edges into frames.

For every trigger edge (frame number n, read as text lines from the trigger's edge stream) it hands
frame n of every camera to that camera's edge extractor (its stdin pipe), then notes the moment the
last camera's frame was handed over. Exposure and image transfer are not modelled (a frame exists at
its pulse): frame n+1 is rendered after pulse n, and all of it but its last `STAGE_TAIL` bytes is
written into the edge's pipe then ("staged"); pulse n+1 writes only those bytes, which completes the
frame for the edge. So a pulse costs a few tiny writes, not a 300 KB copy per camera (measured 0.42 ms
P50 from the pulse to the last of 5 cameras handed over with whole-frame writes).

It runs in its own process (forked before the host starts any thread) so rendering never competes
with the host's tracking thread for the GIL.
"""

from __future__ import annotations

import contextlib
import fcntl
import math
import multiprocessing as mp
import os
import queue
import select
import stat
import struct
import termios
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from flytrack_host.geometry.camera import Camera
from flytrack_host.sim.dvs import evt2_header
from flytrack_host.sim.flight import GroundTruth
from flytrack_host.sim.render import CameraRenderer, RenderParams
from flytrack_host.util.children import tied
from flytrack_host.util.placement import run_as_hardware

STAGE_TAIL = 64  # bytes of a staged frame written at its pulse (under PIPE_BUF: one atomic write)
# Rendering the next frames (CPU-heavy, at the simulated hardware's priority) starts this fraction of
# a period after the pulse, not at once: a real camera's next exposure costs the host nothing, while
# here it took one of the machine's cores for ~2.5 ms (5 cameras) right while the host handled the
# frame just pulsed (its receive -> track -> actuate window). Never so late that rendering, at its
# measured pace, could miss the next pulse.
RENDER_AHEAD_DELAY = 0.3
RENDER_AHEAD_MARGIN = 3.0  # the delay leaves at least this many times the mean render time before the next pulse


def render_ahead_delay(period_s: float, mean_render_s: float) -> float:
    """How long after a pulse the next frames are rendered (s; <= 0: at once): RENDER_AHEAD_DELAY of the
    period, shortened so that RENDER_AHEAD_MARGIN x the mean render time still fits before the next pulse."""
    return min(RENDER_AHEAD_DELAY * period_s, period_s - RENDER_AHEAD_MARGIN * mean_render_s)
F_SETPIPE_SZ = 1031  # Linux fcntl: grow a pipe so one whole frame fits without blocking


def grow_pipe(fd: int, size: int = 1 << 20) -> int:
    """Ask for a pipe buffer of `size` bytes (the kernel caps it at /proc/sys/fs/pipe-max-size)."""
    try:
        return fcntl.fcntl(fd, F_SETPIPE_SZ, size)
    except OSError:
        return -1


class EdgeLineParser:
    """Turns trigger edge lines into frame numbers (None for lines that start no frame).

    Two forms are read:
    - the simavr harness's edge log: `<cycle> <signal> <level>` per edge, `#` comments; every rising
      edge of `trigger` starts the next frame, the first being frame 0;
    - a plain frame number per line (what the frame feeder's own software-trigger bridge writes).
    """

    def __init__(self) -> None:
        self.next_frame = 0
        self.bad_lines = 0
        self.f_cpu: float | None = None
        # A paced harness states when cycle 0 was due on the host clock: with it, an edge's cycle
        # gives the true host time of the pulse (what the host's clock model should reproduce).
        self.anchor: float | None = None
        self.last_cycle: int | None = None
        # Rising edges of the firmware's pulse output (the high-speed camera line), as trigger frames.
        self.pulse_frames: list[int] = []
        self._trig0: int | None = None
        self._period: int | None = None

    def true_time(self) -> float:
        """Host time of the last trigger edge by its cycle (NaN when the run is not paced)."""
        if self.anchor is None or self.f_cpu is None or self.last_cycle is None:
            return math.nan
        return self.anchor + self.last_cycle / self.f_cpu

    def feed(self, line: str) -> int | None:
        s = line.strip()
        if not s:
            return None
        if s.startswith("#"):
            for tok in s.split():
                if tok.startswith("f_cpu="):
                    with contextlib.suppress(ValueError):
                        self.f_cpu = float(tok[6:])
                elif tok.startswith("t0_realtime="):
                    with contextlib.suppress(ValueError):
                        self.anchor = float(tok[len("t0_realtime="):])
            return None
        parts = s.split()
        if len(parts) == 1:
            if parts[0].isdigit():
                return int(parts[0])
            self.bad_lines += 1
            return None
        if len(parts) == 3 and parts[0].isdigit() and parts[2] in ("0", "1"):
            if parts[1] == "trigger" and parts[2] == "1":
                n = self.next_frame
                self.next_frame += 1
                c = int(parts[0])
                if self.last_cycle is not None:
                    self._period = c - self.last_cycle
                if self._trig0 is None:
                    self._trig0 = c
                self.last_cycle = c
                return n
            if parts[1] == "pulse0" and parts[2] == "1":
                c = int(parts[0])
                if self._trig0 is not None and self._period:  # by cycles: the line order within a cycle varies
                    self.pulse_frames.append((c - self._trig0 + 16) // self._period)
                else:
                    self.pulse_frames.append(self.next_frame - 1)
            return None
        self.bad_lines += 1
        return None


@dataclass
class FrameFeedStats:
    edges: int
    frames_rendered: int
    handoff_time: np.ndarray  # (n_frames,) host time (s) the last camera's frame was handed over, NaN if not
    edge_time: np.ndarray  # (n_frames,) host time the trigger edge was read
    edge_true_time: np.ndarray  # (n_frames,) host time the edge happened (paced simavr), else NaN
    render_s: float  # CPU seconds spent rendering
    write_s: float  # seconds spent handing frames to the cameras' links
    bad_lines: int = 0  # edge-stream lines that could not be read
    # (n_frames, n_cams) host time each camera's frame started into its edge's input pipe
    written_time: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    priority_raised: bool = False
    pulse_frames: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # pulse0 rising edges
    dvs_events_sent: list[int] = field(default_factory=list)  # per DVS camera, written to its edge
    dvs_syncs_sent: list[int] = field(default_factory=list)
    frames_staged: int = 0  # camera frames written ahead of their pulse but their last bytes
    frames_stale: int = 0  # staged frames a pulse of another number completed (a skipped number)


class FrameFeeder:
    """Owns the child process. Create it BEFORE starting threads in this process (it forks)."""

    def __init__(
        self,
        gt: GroundTruth,
        cameras: Sequence[Camera],
        edge_fds: Sequence[int],
        params: RenderParams,
        seed: int,
        frame_format: str = "raw",
        warmup_frames: int = 0,
        dvs: Sequence[tuple[tuple[int, int, list[tuple[bytes, int]]], int]] = (),
    ):
        """dvs: simulated event cameras ((width, height, sim.dvs.render_stream's chunks), their edge's
        stdin): at pulse n each gets the events since the last pulse and a sync event at the pulse."""
        if len(cameras) != len(edge_fds):
            raise ValueError("one edge pipe per camera is needed")
        self.n_frames = gt.n_frames
        ctx = mp.get_context("fork")
        self._handoff = ctx.RawArray("d", [math.nan] * gt.n_frames)
        self.n_cams = len(cameras)
        self._written = ctx.RawArray("d", [math.nan] * (gt.n_frames * self.n_cams))
        self._edge_t = ctx.RawArray("d", [math.nan] * gt.n_frames)
        self._edge_true = ctx.RawArray("d", [math.nan] * gt.n_frames)
        # edges, rendered, render_s, write_s, done, bad lines, priority raised, pre-roll frames, staged
        self._counters = ctx.RawArray("d", 10)
        self._pulses = ctx.RawArray("q", [-1] * 1024)  # frames of the pulse output's rising edges
        self.n_dvs = len(dvs)
        self._dvs_sent = ctx.RawArray("q", 2 * max(1, self.n_dvs))  # per DVS camera: events, sync events
        self._conn, child_conn = ctx.Pipe()
        self._proc = ctx.Process(
            target=tied(_feed),  # it ends with this process, also on SIGTERM or SIGKILL (util.children)
            args=(gt, list(cameras), list(edge_fds), child_conn, params, seed, frame_format, warmup_frames,
                  self._handoff, self._edge_t, self._counters, self._written, self._edge_true, self._pulses,
                  list(dvs), self._dvs_sent),
            name="flytrack-sim-frames",
            daemon=True,
        )
        self._proc.start()

    def set_source(self, source: str | int) -> None:
        """Where trigger edges come from: a path (file or FIFO, followed as it grows), or a file
        descriptor number inherited by the child (create it before the feeder)."""
        self._conn.send(source)

    def preroll(self, frames: int) -> None:
        """Hand every edge `frames` frames without animals now, before the trigger starts (the child
        must already be following its edge stream)."""
        self._conn.send(("preroll", int(frames)))

    @property
    def preroll_frames(self) -> int:
        return int(self._counters[7])

    @property
    def priority_raised(self) -> bool:
        return bool(self._counters[6])

    @property
    def frames_rendered(self) -> int:
        return int(self._counters[1])

    @property
    def edges_seen(self) -> int:
        return int(self._counters[0])

    def alive(self) -> bool:
        return self._proc.is_alive()

    def join(self, timeout: float | None = None) -> None:
        self._proc.join(timeout)

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    @property
    def done(self) -> bool:
        """Every frame was handed to the edges (their stdin is closed)."""
        return bool(self._counters[4])

    def finish(self) -> None:
        """Tell the child that no more edges will come (it stops reading the edge stream)."""
        with contextlib.suppress(OSError, BrokenPipeError):
            self._conn.send(None)

    def stop(self) -> None:
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(2.0)

    def stats(self) -> FrameFeedStats:
        return FrameFeedStats(
            edges=int(self._counters[0]),
            frames_rendered=int(self._counters[1]),
            handoff_time=np.frombuffer(self._handoff, dtype=np.float64).copy(),
            written_time=np.frombuffer(self._written, dtype=np.float64).reshape(-1, self.n_cams).copy(),
            edge_time=np.frombuffer(self._edge_t, dtype=np.float64).copy(),
            edge_true_time=np.frombuffer(self._edge_true, dtype=np.float64).copy(),
            render_s=float(self._counters[2]),
            write_s=float(self._counters[3]),
            bad_lines=int(self._counters[5]),
            priority_raised=bool(self._counters[6]),
            pulse_frames=np.array([p for p in self._pulses if p >= 0], dtype=np.int64),
            dvs_events_sent=[int(self._dvs_sent[2 * i]) for i in range(self.n_dvs)],
            dvs_syncs_sent=[int(self._dvs_sent[2 * i + 1]) for i in range(self.n_dvs)],
            frames_staged=int(self._counters[8]),
            frames_stale=int(self._counters[9]),
        )


class _CameraLink:
    """One camera's connection to its edge. A frame is written at once when the edge's pipe has room
    for it (the common case: a cheap copy); otherwise it waits in this camera's queue for a writer
    thread. A slow edge then delays only its own frames (as a camera's frame buffer would), not the
    other cameras nor the trigger; past `depth` queued frames the camera waits (back-pressure)."""

    def __init__(self, fd: int, frame_format: str, cam: Camera, fps: float, written_t, index: int, n_cams: int,
                 cond: threading.Condition, depth: int = 64):
        self.fd = fd
        self.cond = cond
        self.written_t, self.index, self.n_cams = written_t, index, n_cams
        self.y4m = frame_format == "y4m"
        self.closed = False
        self.written = 0
        self.queued = 0  # frames given to the writer thread and not yet written
        self.inline = 0
        # A frame in the pipe but its last STAGE_TAIL bytes (see stage()), and those bytes.
        self.staged: tuple[np.ndarray, memoryview] | None = None
        self.stale = 0  # staged frames released for another pulse than the one they were rendered for
        self.q: queue.Queue[tuple[int, np.ndarray] | None] = queue.Queue(depth)
        size = grow_pipe(fd)
        self.capacity = size if size > 0 else 65536
        if self.y4m:
            self._write(_y4m_header(cam.width, cam.height, fps))
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _write(self, data: bytes | memoryview) -> None:
        if self.closed:
            return
        try:
            _write_all(self.fd, memoryview(data).cast("B"))
        except OSError:
            self.closed = True  # the edge died; the host will see a dead camera

    def _deliver(self, n: int, img: np.ndarray) -> None:
        # Stamped as the write begins: a stamp after it could come late (the writer may not run again
        # before the edge and the host are done with the frame), and the write itself is a memory copy
        # of well under 0.1 ms, so the latency measured from here errs long, not short.
        t_start = time.time()  # noqa: TID251 - stamps compared across the simulated cameras' processes and the C harness's CLOCK_REALTIME
        if self.y4m:
            self._write(b"FRAME\n")
        self._write(memoryview(img))
        if n >= 0 and not self.closed:
            self.written_t[n * self.n_cams + self.index] = t_start

    def _run(self) -> None:
        while True:
            item = self.q.get()
            if item is None:
                return
            self._deliver(*item)
            with self.cond:
                self.written += 1
                self.queued -= 1
                self.cond.notify_all()

    def stage(self, img: np.ndarray) -> bool:
        """Write all of the next frame but its last STAGE_TAIL bytes now, ahead of its pulse; the edge
        reads them and waits for the rest (put() writes it). Only when the pipe has room for the whole
        frame and nothing is queued (else put() hands the whole frame over at the pulse, as before)."""
        need = img.nbytes + (6 if self.y4m else 0)
        if (self.closed or self.staged is not None or self.queued or img.nbytes <= STAGE_TAIL
                or self.capacity - _pipe_bytes(self.fd) < need):
            return False
        flat = memoryview(img).cast("B")
        if self.y4m:
            self._write(b"FRAME\n")
        self._write(flat[:-STAGE_TAIL])
        if self.closed:
            return False
        self.staged = (img, flat[-STAGE_TAIL:])
        return True

    def put(self, n: int, img: np.ndarray) -> None:
        """Hand over frame `n` (-1: a pre-roll frame)."""
        if self.staged is not None:
            # The frame is in the pipe but its tail: the pulse completes it. (Staged for the pulse that
            # came: always with the simavr edge log, numbered 0, 1, 2...; a source that skipped a number
            # gets the frame rendered for the expected one, counted as stale.)
            staged, tail = self.staged
            self.staged = None
            if staged is not img:
                self.stale += 1
            t = time.time()  # noqa: TID251 - cross-process stamp (see _deliver)
            self._write(tail)
            if n >= 0 and not self.closed:
                self.written_t[n * self.n_cams + self.index] = t
            self.inline += 1
            with self.cond:
                self.written += 1
            return
        need = img.nbytes + (6 if self.y4m else 0)
        if self.queued == 0 and self.capacity - _pipe_bytes(self.fd) >= need:
            self._deliver(n, img)  # nothing queued before it and it fits: no thread hand-off
            self.inline += 1
            with self.cond:
                self.written += 1
            return
        with self.cond:
            self.queued += 1
        self.q.put((n, img))

    def finish(self, timeout: float = 30.0) -> None:
        if self.staged is not None:  # the trigger stopped early: a whole frame rather than a torn one
            self.put(-1, self.staged[0])
        self.q.put(None)
        self.thread.join(timeout)


def _pipe_bytes(fd: int) -> int:
    """Bytes waiting in a pipe (FIONREAD works on the write end too); 0 when it cannot tell."""
    try:
        return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]
    except OSError:
        return 0


def _write_all(fd: int, buf: memoryview) -> None:
    while buf:
        n = os.write(fd, buf)
        buf = buf[n:]


def _y4m_header(w: int, h: int, fps: float) -> bytes:
    num, den = (int(round(fps * 1000)), 1000)
    return f"YUV4MPEG2 W{w} H{h} F{num}:{den} Ip A1:1 Cmono\n".encode()


def _feed(
    gt: GroundTruth,
    cameras: list[Camera],
    edge_fds: list[int],
    conn,
    params: RenderParams,
    seed: int,
    frame_format: str,
    warmup: int,
    handoff,
    edge_t,
    counters,
    written_t,
    edge_true,
    pulses=None,
    dvs=(),
    dvs_sent=None,
) -> None:
    counters[6] = run_as_hardware()
    dvs_links = [_DvsLink(r, fd) for r, fd in dvs]
    renderers = [CameraRenderer(c, params, seed=seed * 1000 + i) for i, c in enumerate(cameras)]
    written_cond = threading.Condition()
    links = [_CameraLink(fd, frame_format, c, gt.fps, written_t, i, len(cameras), written_cond)
             for i, (fd, c) in enumerate(zip(edge_fds, cameras, strict=True))]
    render_s = put_s = 0.0
    ahead_s, ahead_count = 0.0, 0  # the renders made ahead, for the render-ahead delay
    period = 1.0 / gt.fps
    buf = b""
    parser = EdgeLineParser()
    n_pulses = 0
    no_pos = np.zeros((0, 3))

    def render(n: int) -> list[np.ndarray]:
        # Before the animals are released the edges learn their background.
        pos, axis = (gt.pos[n], gt.axis[n]) if n >= warmup else (no_pos, no_pos)
        return [r.render(gt.t[n], pos, axis, gt.body_length_m, gt.body_width_m, fresh=True) for r in renderers]

    ahead_n = 0
    imgs = render(0)
    try:
        if not conn.poll(60.0):
            return
        source = conn.recv()
        if source is None:
            return
        stream = os.fdopen(source, "rb", buffering=0) if isinstance(source, int) else open(source, "rb", buffering=0)
        with stream:
            fd = stream.fileno()
            is_fifo = isinstance(source, int) or stat.S_ISFIFO(os.fstat(fd).st_mode)
            done = False
            while not done:
                ready, _, _ = select.select([fd, conn], [], [], 0.5)
                if conn in ready:  # a command from the parent
                    msg = conn.recv()
                    if msg is None:
                        break
                    if isinstance(msg, tuple) and msg[0] == "preroll":
                        # Cameras running before the trigger starts (as when a lab arms a run): the
                        # edges take their background and the host sees them go quiet afterwards.
                        for _ in range(int(msg[1])):
                            blank = [r.render(0.0, no_pos, no_pos, gt.body_length_m, gt.body_width_m, fresh=True)
                                     for r in renderers]
                            for link, img in zip(links, blank, strict=True):
                                link.put(-1, img)
                            counters[7] += 1
                    continue
                if fd not in ready:
                    continue
                chunk = os.read(fd, 65536)
                if not chunk:
                    if is_fifo:
                        break  # writer closed
                    time.sleep(0.0005)  # a regular file: follow it as it grows
                    continue
                buf += chunk
                *lines, buf = buf.split(b"\n")
                for raw in lines:
                    n = parser.feed(raw.decode("ascii", "replace"))
                    counters[5] = parser.bad_lines
                    if pulses is not None and parser.pulse_frames:
                        for pf in parser.pulse_frames:
                            if n_pulses < len(pulses):
                                pulses[n_pulses] = pf
                                n_pulses += 1
                        parser.pulse_frames.clear()
                    if n is None:
                        continue
                    t_edge = time.time()  # noqa: TID251 - cross-process stamp (see t_start)
                    t_pulse = time.perf_counter()
                    counters[0] += 1
                    if n >= gt.n_frames:
                        done = True
                        break
                    edge_t[n] = t_edge
                    edge_true[n] = parser.true_time()
                    # The frames of pulse n were rendered ahead (the flight is known in advance), so a
                    # pulse costs only handing them to the cameras' links: every camera's frame n is
                    # available at (nearly) one time, right after the pulse, as with real cameras.
                    if ahead_n != n:
                        t0 = time.perf_counter()
                        imgs = render(n)
                        render_s += time.perf_counter() - t0
                    t1 = time.perf_counter()
                    for link, img in zip(links, imgs, strict=True):
                        link.put(n, img)
                    put_s += time.perf_counter() - t1
                    counters[9] = sum(lk.stale for lk in links)
                    handoff[n] = time.time()  # noqa: TID251 - cross-process stamp (see t_start)
                    counters[1] += 1
                    if dvs_links:
                        t0 = time.perf_counter()
                        for i, dl in enumerate(dvs_links):
                            dl.pulse(n)
                            if dvs_sent is not None:
                                dvs_sent[2 * i], dvs_sent[2 * i + 1] = dl.events, dl.syncs
                        render_s += time.perf_counter() - t0
                    # Let the links write before rendering ahead (this process's GIL would delay
                    # them), but never wait long for a slow edge.
                    target = int(counters[7] + counters[1])  # pre-roll frames went through the links too
                    deadline = time.perf_counter() + 0.5 / gt.fps
                    with written_cond:
                        written_cond.wait_for(
                            lambda t=target: all(lk.written >= t or lk.closed for lk in links), 0.5 / gt.fps
                        )
                    # ... and until the edges have read them, so that rendering ahead does not compete
                    # with the edges for the CPU at the moment they work on the frame.
                    while time.perf_counter() < deadline and any(_pipe_bytes(lk.fd) > 0 for lk in links):
                        time.sleep(1e-4)
                    # Render the next frame while waiting for its pulse, once the host had its moment
                    # (RENDER_AHEAD_DELAY).
                    ahead_n = n + 1
                    if ahead_n < gt.n_frames:
                        mean = ahead_s / ahead_count if ahead_count else period  # unknown yet: at once
                        wait = t_pulse + render_ahead_delay(period, mean) - time.perf_counter()
                        if wait > 0:
                            time.sleep(wait)
                        t0 = time.perf_counter()
                        imgs = render(ahead_n)
                        dt = time.perf_counter() - t0
                        render_s += dt
                        ahead_s += dt
                        ahead_count += 1
                        for link, img in zip(links, imgs, strict=True):
                            if link.stage(img):
                                counters[8] += 1
                    counters[2] = render_s
                    counters[3] = put_s
            for link in links:  # every frame handed out reaches its edge, then the edges see EOF
                link.finish()
            for dl in dvs_links:
                dl.close()
            for efd in edge_fds:
                with contextlib.suppress(OSError):
                    os.close(efd)
            counters[4] = 1
            # The trigger runs on until the host stops it: keep reading its edges (a writer with no
            # reader would get SIGPIPE) until it closes or the parent says so.
            while True:
                ready, _, _ = select.select([fd, conn], [], [], 0.5)
                if conn in ready and conn.recv() is None:
                    break
                if fd in ready and not os.read(fd, 65536) and is_fifo:
                    break
    finally:
        for efd in edge_fds:
            with contextlib.suppress(OSError):
                os.close(efd)
        for dl in dvs_links:
            dl.close()
        counters[4] = 1


class _DvsLink:
    """One simulated DVS camera's stream into its edge's stdin: at pulse n, the EVT 2.0 words rendered
    ahead for it (sim.dvs.render_stream), written whole."""

    def __init__(self, stream: tuple[int, int, list[tuple[bytes, int]]], fd: int) -> None:
        width, height, self.chunks = stream
        self.fd = fd
        self.events = self.syncs = 0
        self.closed = False
        grow_pipe(fd)
        self._write(evt2_header(width, height))

    def _write(self, data: bytes) -> None:
        if self.closed:
            return
        try:
            _write_all(self.fd, memoryview(data))
        except OSError:  # the edge went away: stop feeding it (the demo reports its exit)
            self.close()

    def pulse(self, n: int) -> None:
        if not 0 <= n < len(self.chunks):
            return
        data, n_ev = self.chunks[n]
        self._write(data)
        if not self.closed:
            self.events += n_ev
            self.syncs += 1

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            with contextlib.suppress(OSError):
                os.close(self.fd)
