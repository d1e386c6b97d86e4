"""What every output device shares: connect / perform / close, and the worker thread that drives it.

The tracking thread only puts a job on the device's bounded queue (`OutputWorker.submit`, never
blocks; a full queue drops the job, counted and recorded as an error). On a frame that fired, it then
waits at most `HANDOFF_MAX_S` (a `Handoff`) until each device thread that was idle and connected has
put its command on the wire: Python runs one thread at a time (the GIL), and a woken device thread
otherwise waits for the tracking thread to block or be preempted (0.5-1.5 ms measured, P50). A device
that is busy, absent or reconnecting is not waited for, so it never delays tracking. The worker connects, performs
the jobs one by one and reports each outcome; a failure closes the connection, and the worker
reconnects on its own every `RECONNECT_S` (also while no job comes), so a device that was absent at
start or went away mid-run is back as soon as it answers. Failures are logged rate-limited per kind
(the host's `ratelog.RateLimitedLog`: the first at once, then a count every few seconds).
"""

from __future__ import annotations

import logging
import math
import os
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from flytrack_host.actuation.rules import Action
from flytrack_host.rig import ActuatorConfig
from flytrack_host.util import hostclock
from flytrack_host.util.ratelog import RateLimitedLog

log = logging.getLogger("flytrack.actuation")

RECONNECT_S = 0.5
HANDOFF_MAX_S = 0.002  # the tracking thread waits at most this long, on a frame that fired
LEAD_SAMPLES = 50
LEAD_MARGIN_S = 0.5e-3
WORKER_NICE = -5


class OutputError(RuntimeError):
    """A device failure with a clear cause (absent, refused, timed out)."""


class Handoff:
    """Counts the commands of one frame still to be put on the wire by their device threads; the
    tracking thread `wait`s (bounded) for them, its GIL released meanwhile. Two plain locks, no
    Condition: made and waited for on the tracking thread of every frame that fired."""

    def __init__(self) -> None:
        self._left = 0
        self._mutex = threading.Lock()
        self._gate = threading.Lock()  # held while commands are left

    def add(self) -> None:
        with self._mutex:
            if self._left == 0:
                self._gate.acquire()
            self._left += 1

    def done(self) -> None:
        with self._mutex:
            if self._left > 0:
                self._left -= 1
                if self._left == 0:
                    self._gate.release()

    def wait(self, timeout_s: float) -> bool:
        """True when every command left in time."""
        if not self._gate.acquire(timeout=max(0.0, timeout_s)):
            return False
        self._gate.release()
        return True


@dataclass
class Job:
    rule: str
    obj_id: int
    condition_frame: int
    scheduled_frame: int
    frame_time: float
    estimate_time: float
    pos: tuple[float, float, float]
    action: Action
    predicted: bool
    queued_at: float = field(default_factory=hostclock.now)
    handoff: Handoff | None = None  # the tracking thread waits for this job's command to leave
    after: Handoff | None = None  # the command of the same frame that leaves first (the device thread waits)
    after_wait_s: float = HANDOFF_MAX_S  # ... at most this long

    def handed_off(self) -> None:
        """The command is on the wire (or failed): release the tracking thread's wait. Idempotent."""
        h, self.handoff = self.handoff, None
        if h is not None:
            h.done()


@dataclass
class Outcome:
    job: Job
    output: str
    kind: str
    time_sent: float = math.nan
    time_ack: float = math.nan
    time_started: float = math.nan  # the worker took the job off its queue (hand-off stage)
    time_written: float = math.nan  # the command had left the host (NaN: the device has no such hook)
    scheduled_frame: int = -1
    frame_exact: bool = False
    error: str = ""


@dataclass
class Done:
    """What `Output.perform` returns: when the command left, when the device acknowledged it (NaN
    for a device that does not), and the frame it landed on when the device places it exactly."""

    time_sent: float
    time_ack: float
    scheduled_frame: int | None = None
    frame_exact: bool = False
    note: str = ""  # e.g. "late: pulsed at once"


class Output:
    """One device. Subclasses implement `_connect`, `_perform` and `_close`."""

    kind = "?"
    ack_means = "?"  # what `time_ack` is for this device (said in the demo JSON and the manual's rules-file reference)
    arm_frames = 0  # frames ahead the device must have the command (the trigger firmware: 1)

    initial_lead_s = 0.0  # until measured: time from queueing a command to its acknowledgement

    def __init__(self, cfg: ActuatorConfig, context: dict[str, Any] | None = None):
        self.cfg = cfg
        self.context = context or {}
        self.connected = False
        self._lead: deque[float] = deque(maxlen=LEAD_SAMPLES)  # measured queued -> acknowledged times
        self._lead_s = self.initial_lead_s
        self._job: Job | None = None  # the job being performed (its hand-off is released by `written`)
        self.time_written = math.nan

    @property
    def name(self) -> str:
        return self.cfg.name

    @property
    def lead_s(self) -> float:
        """How long before its frame an action must be queued: the device's stated latency plus the
        90th percentile of the measured time from queueing to acknowledgement (waiting for the worker
        thread, for a serial link busy with a clock query, the round trip) and a margin."""
        return self.cfg.latency_ms / 1e3 + self._lead_s

    def connect(self) -> None:
        self._connect()
        self.connected = True

    def perform(self, job: Job) -> Done:
        self._job = job
        self.time_written = math.nan
        try:
            done = self._perform(job)
        finally:
            self._job = None
        sample = self._lead_sample(job, done)
        if math.isfinite(sample):
            self._lead.append(max(0.0, sample))
            v = sorted(self._lead)
            self._lead_s = max(self.initial_lead_s, v[int(0.9 * (len(v) - 1))] + LEAD_MARGIN_S)
        return done

    def written(self) -> None:
        """Called by a device right after its command left the host (the write returned): stamps it
        and lets the tracking thread go on."""
        self.time_written = hostclock.now()
        job = getattr(self, "_job", None)
        if job is not None:
            job.handed_off()

    def _lead_sample(self, job: Job, done: Done) -> float:
        """The time this command needed, from queueing, to take effect (default: to its acknowledgement)."""
        return done.time_ack - job.queued_at

    def close(self) -> None:
        self.connected = False
        try:
            self._close()
        except Exception as exc:  # closing a broken link can fail too; it is being dropped anyway
            log.debug("closing %s: %r", self.name, exc)

    def _connect(self) -> None:
        raise NotImplementedError

    def _perform(self, job: Job) -> Done:
        raise NotImplementedError

    def _close(self) -> None:
        pass


@dataclass
class WorkerStats:
    sent: int = 0
    ok: int = 0
    errors: int = 0
    dropped: int = 0  # queue full
    connects: int = 0
    connect_failures: int = 0
    last_error: str = ""
    priority_raised: bool = False


class OutputWorker:
    """A thread per device with a bounded queue; `on_done(outcome)` is called for every job."""

    def __init__(self, output: Output, on_done: Callable[[Outcome], None], warn: RateLimitedLog):
        self.output = output
        self.on_done = on_done
        self.warn = warn
        self.q: queue.Queue[Job | None] = queue.Queue(maxsize=output.cfg.queue)
        self.stats = WorkerStats()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"actuation-{output.name}", daemon=True)
        self._next_connect = 0.0
        self.idle = False  # waiting on an empty queue: a job now is taken at once

    @property
    def ready(self) -> bool:
        """Idle and connected: a command now goes straight to the device (the tracking thread may wait
        for it to leave)."""
        return self.idle and self.output.connected and self.q.empty()

    def start(self) -> None:
        self._thread.start()

    def submit(self, job: Job) -> bool:
        try:
            self.q.put_nowait(job)
            return True
        except queue.Full:
            job.handed_off()
            self.stats.dropped += 1
            self.stats.last_error = "queue full"
            self.warn(f"{self.output.name}:full", f"output {self.output.name}: queue full "
                      f"({self.output.cfg.queue} commands waiting), command dropped; the device is too slow")
            self.on_done(Outcome(job, self.output.name, self.output.kind, error="dropped: queue full"))
            return False

    def _try_connect(self) -> bool:
        if self.output.connected:
            return True
        if time.monotonic() < self._next_connect:
            return False
        try:
            self.output.connect()
        except Exception as exc:
            self.stats.connect_failures += 1
            self.stats.last_error = f"cannot connect: {exc}"
            self._next_connect = time.monotonic() + RECONNECT_S
            self.warn(f"{self.output.name}:connect", f"output {self.output.name} ({self.output.kind}): "
                      f"cannot connect: {exc}; retrying every {RECONNECT_S:g} s")
            return False
        self.stats.connects += 1
        if self.stats.connects > 1 or self.stats.connect_failures:
            self.warn(f"{self.output.name}:up", f"output {self.output.name} ({self.output.kind}): connected")
        return True

    def _run(self) -> None:
        # A device thread sleeps almost always and must run at once when a command comes: nice -5 for
        # this thread (Linux: per thread; when allowed), so a busy machine delays it less.
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), WORKER_NICE)
            self.stats.priority_raised = True
        except (PermissionError, OSError):
            pass
        while True:
            try:
                self.idle = True
                job = self.q.get(timeout=RECONNECT_S)
            except queue.Empty:
                if self._stop.is_set():
                    break
                self._try_connect()  # reconnect while idle too
                continue
            finally:
                self.idle = False
            if job is None:
                break
            if job.after is not None:
                # Another device's command of the same frame goes first: wait (bounded) until it left,
                # the interpreter released meanwhile, rather than taking it from that device's thread.
                job.after.wait(job.after_wait_s)
            try:
                self._do(job)
            finally:
                job.handed_off()  # a device without a write hook, or one that failed
        self.output.close()

    def _do(self, job: Job) -> None:
        out = Outcome(job, self.output.name, self.output.kind, time_started=hostclock.now())
        if not self._try_connect():
            self._next_connect = 0.0  # a job is waiting: try once more now
            if not self._try_connect():
                out.error = f"not connected: {self.stats.last_error}"
                self.stats.errors += 1
                self.on_done(out)
                return
        self.stats.sent += 1
        try:
            done = self.output.perform(job)
        except Exception as exc:
            out.time_sent = hostclock.now()
            out.error = f"{type(exc).__name__}: {exc}"
            self.stats.errors += 1
            self.stats.last_error = out.error
            self.warn(f"{self.output.name}:perform", f"output {self.output.name} ({self.output.kind}) failed: "
                      f"{out.error}; reconnecting")
            self.output.close()
            self._next_connect = 0.0
            self.on_done(out)
            return
        self.stats.ok += 1
        out.time_sent, out.time_ack = done.time_sent, done.time_ack
        out.time_written = self.output.time_written
        out.scheduled_frame = job.scheduled_frame if done.scheduled_frame is None else done.scheduled_frame
        out.frame_exact = done.frame_exact
        out.error = done.note
        self.on_done(out)

    def stop(self, timeout_s: float = 2.0) -> None:
        """Finish the queued jobs (up to `timeout_s`), then close the device."""
        self._stop.set()
        try:
            self.q.put_nowait(None)
        except queue.Full:
            pass
        self._thread.join(timeout_s)
