"""The trigger box in a live run: open it, set the rate, tie camera frames to trigger frames, keep the
trigger clock model fed, stop. This is what `flytrack run` does around `HostPipeline`, in the order
flydra and Braid use:

    session = TriggerSession(rig.trigger)
    fps = session.open()              # port, handshake, stop-and-reset, rate (exact rate returned)
    pipe = HostPipeline(rig, cameras, clock=session.clock, fps=fps, hold_until_synchronized=True)
    pipe.start(); session.attach(pipe)
    session.start(pipe)               # cameras quiet -> re-arm the frame-0 tie -> START -> clock thread
    ...
    session.stop()                    # trigger stopped; then pipe.stop()

Frame numbering: the firmware counts pulses started; the first pulse after START is trigger frame 0
and the device time is the time since it began. The synchroniser ties each camera's first frame
after its re-arm to trigger frame 0, so the two agree as long as the cameras were quiet when the
trigger started (checked: the session waits until no FEATURES arrived for `quiet_s`).

The clock thread queries the device every `clock_query_interval_s` (faster for the first samples
after a start), records every reply in the recording's trigger-clock table (start/stop host time,
pulse count, fraction of the current frame), feeds the `ClockModel` and publishes a snapshot of it
as `clock`, the FrameClock the synchroniser stamps bundles with; latency is then measured from the
trigger pulse's host time. Failures:
- the device stops answering: logged, counted, the status line says so and the last clock model is
  kept; the port is re-opened every few seconds and, once it answers, the trigger is re-armed;
- the pulse count goes back or the device says it is not running (it reset): logged, and the trigger
  is re-armed (stop-and-reset, rate, quiet cameras, frame-0 tie, START), the tracker restarts;
- the clock model restarts without that (a host clock step): logged; its snapshot restarts too.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, Protocol

import serial

from flytrack_host.rig import TriggerConfig
from flytrack_host.trigger.clock_model import ClockModel
from flytrack_host.trigger.common import QuerySchedule, TriggerError
from flytrack_host.trigger.device import ClockReading
from flytrack_host.util import hostclock

log = logging.getLogger("flytrack.trigger_session")

ARDUINO_RESET_WAIT_S = 2.0  # an Arduino resets when its port opens; its bootloader listens ~1-2 s
# A strawlab box then spends ~5.5 s in its name handshake: 7 s, then V? every second up to 20 s
# (the driver's RESET_WAIT_S and CONNECT_TIMEOUT_S, as Braid does).
WARMUP_SAMPLES = 15  # clock queries at WARMUP_INTERVAL_S right after a start, before the rig's interval
WARMUP_INTERVAL_S = 0.02
# The software stand-in, a thread of this process, replies when a loaded host gets to it: "no reply
# to Start from /dev/pts/3 within 0.5 s" ended a fault-suite run at load 11. It cannot be unplugged,
# so waiting longer costs nothing; a late reply to a clock query is still dropped by the clock model
# (round trip > 10 ms). (A simulated box on a pty keeps 0.5 s: its slow replies would enter the
# recorded clock table, which tests/host/test_trigger_run.py fits.)
SIMULATED_REPLY_TIMEOUT_S = 2.0
FIXED_GAIN_SPAN_S = 1.0  # until the samples span this much device time the fitted gain is mostly noise
RECONNECT_EVERY_S = 2.0
LOST_AFTER_FAILURES = 3  # clock queries unanswered in a row before the trigger counts as lost


class _Device(Protocol):  # what TriggerDevice and StrawlabTriggerbox both offer
    model: ClockModel

    def set_rate(self, fps: float) -> float: ...
    def start(self) -> None: ...
    def stop(self) -> None: ...
    def stop_reset(self) -> None: ...
    def query_clock(self) -> ClockReading: ...
    def close(self) -> None: ...


class _Pipeline(Protocol):  # the parts of HostPipeline the session uses
    last_frame_recv: float
    status_sources: list[Callable[[], str]]

    def resynchronize(self, timeout_s: float = ...) -> None: ...
    def record_clock_sample(self, start_time: float, framecount: int, fraction: float, stop_time: float) -> None: ...
    def log(self, message: str, source: str = ...) -> None: ...


class SessionClock:
    """The FrameClock given to the synchroniser: a snapshot (gain, offset, period) of the trigger
    clock, replaced whole after each clock sample so the tracking thread never reads a half-updated
    fit, and kept as it is while the device does not answer.

    Right after a start the samples span a few tens of ms, over which a fitted gain is dominated by
    round-trip jitter (a 0.5 ms error over 20 ms is 2.5 %), so until they span FIXED_GAIN_SPAN_S the
    gain is taken as 1 (exact to the crystal's tolerance, ~50 ppm) and the offset from the sample with
    the shortest round trip."""

    def __init__(self) -> None:
        self._snap: tuple[float, float, float] | None = None  # gain, offset, frame period
        self._recent: deque[tuple[float, float, float]] = deque(maxlen=64)  # rtt, host sample time, device t
        self.source = "none"  # "none", "offset-only" or "fit"

    def clear(self) -> None:
        self._snap = None
        self._recent.clear()
        self.source = "none"

    def update(self, model: ClockModel, reading: ClockReading, period_s: float) -> None:
        if reading.running:
            self._recent.append((reading.host_t1 - reading.host_t0,
                                 model.sample_host_time(reading.host_t0, reading.host_t1), reading.device_time_s))
        if not self._recent:
            return
        span = max(r[2] for r in self._recent) - min(r[2] for r in self._recent)
        if model.fitted and span >= FIXED_GAIN_SPAN_S:
            self._snap = (model.gain, model.offset, period_s)
            self.source = "fit"
        elif self.source != "fit":
            rtt, mid, dev = min(self._recent)
            if rtt <= model.max_rtt_s:
                self._snap = (1.0, mid - dev, period_s)
                self.source = "offset-only"

    @property
    def ready(self) -> bool:
        return self._snap is not None

    def frame_to_host_time(self, frame: int) -> float:
        s = self._snap
        if s is None:
            return math.nan
        gain, offset, period = s
        return gain * (frame * period) + offset

    def host_time_to_frame(self, t: float) -> float:
        s = self._snap
        if s is None:
            return math.nan
        gain, offset, period = s
        return (t - offset) / gain / period


@dataclass
class TriggerSessionStats:
    clock_samples: int = 0
    clock_errors: int = 0
    lost: int = 0  # times the device stopped answering
    reconnects: int = 0
    device_restarts: int = 0  # pulse count went back / device not running when it should be
    clock_model_restarts: int = 0
    rearms: int = 0
    quiet_timeouts: int = 0


def is_pty(port: str) -> bool:
    return port.startswith("/dev/pts/")


def open_device(cfg: TriggerConfig, port: str | None = None, reset_wait_s: float | None = None,
                model: ClockModel | None = None) -> tuple[_Device, Any]:
    """Open the rig's trigger -> (device, software stand-in or None). Raises TriggerError with a
    one-line cause (missing or busy port, no permission, not a trigger of that kind)."""
    port = port or cfg.port
    if cfg.kind == "software":
        from flytrack_host.trigger.device import TriggerDevice
        from flytrack_host.trigger.software import SoftwareTrigger

        soft = SoftwareTrigger(name="flytrack-soft")  # name field: 16 bytes
        try:
            # Its pty delivers at once (no wire): the clock model takes the round trip's midpoint.
            return TriggerDevice(soft.port, cfg.baud, reset_wait_s=0.0, model=model, wire_timed=False,
                                 timeout_s=SIMULATED_REPLY_TIMEOUT_S), soft
        except BaseException:
            soft.close()
            raise
    wait = reset_wait_s if reset_wait_s is not None else (0.0 if is_pty(port) else ARDUINO_RESET_WAIT_S)
    if cfg.kind == "strawlab":
        from flytrack_host.trigger.strawlab import RESET_WAIT_S, StrawlabTriggerbox

        if reset_wait_s is None and not is_pty(port):
            wait = RESET_WAIT_S
        # A pty (a simulated box) is not reset by opening it, but it may have just booted: the driver's
        # V? probes, every second for up to 20 s, wait through the handshake either way.
        return StrawlabTriggerbox(port, cfg.baud, reset_wait_s=wait, model=model), None
    from flytrack_host.trigger.device import TriggerDevice

    return TriggerDevice(port, cfg.baud, reset_wait_s=wait, model=model), None


class TriggerSession:
    """Trigger box orchestration for a live run (see the module docstring for the order of calls)."""

    def __init__(
        self,
        cfg: TriggerConfig,
        port: str | None = None,
        reset_wait_s: float | None = None,
        quiet_s: float = 0.2,
        max_quiet_wait_s: float = 5.0,
        clock_query_interval_s: float | None = None,
    ) -> None:
        self.cfg = cfg
        self.port = port or cfg.port
        self.reset_wait_s = reset_wait_s
        self.quiet_s = quiet_s
        self.max_quiet_wait_s = max_quiet_wait_s
        self.interval_s = clock_query_interval_s or cfg.clock_query_interval_s
        self.model = ClockModel()
        self.clock = SessionClock()
        self.device: _Device | None = None
        self.software: Any = None  # the SoftwareTrigger when kind = "software" (tests drive its frames)
        self.fps = cfg.fps
        self.period_s = 1.0 / cfg.fps
        self.stats = TriggerSessionStats()
        self.started_at = math.nan  # host time START was sent
        self.lost_since: float | None = None
        self._failures_in_row = 0
        self._pipe: _Pipeline | None = None
        self._early_log: list[str] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._expect_running = False
        self._last_count: int | None = None
        self._seen_model_restarts = 0
        self._dev_lock = threading.Lock()  # the clock thread re-arms; stop() must not race it
        self._rearming = False
        self._warmup_left = WARMUP_SAMPLES  # clock queries still due at WARMUP_INTERVAL_S (reset by each start)

    @property
    def label(self) -> str:
        return "software trigger" if self.cfg.kind == "software" else f"{self.cfg.kind} trigger on {self.port}"

    def log(self, message: str) -> None:
        if self._pipe is not None:
            self._pipe.log(message, "trigger")
        else:
            log.info("trigger: %s", message)
            self._early_log.append(message)

    # --- opening ----------------------------------------------------------------------------------
    def open(self) -> float:
        """Open the device, stop it with its count reset, set the rate; returns the exact rate made.
        Raises TriggerError (and leaves nothing open) when any of it fails."""
        self.device, self.software = open_device(self.cfg, self.port, self.reset_wait_s, self.model)
        try:
            self._stop_and_rate()
        except BaseException:
            self.close()
            raise
        return self.fps

    def _stop_and_rate(self) -> None:
        assert self.device is not None
        self.device.stop_reset()
        self._expect_running = False
        self.fps = self.device.set_rate(self.cfg.fps)
        self.period_s = 1.0 / self.fps
        rate = getattr(self.device, "rate", None)
        how = f" (prescaler /{rate.divisor}, TOP {rate.top}, f_cpu {rate.f_cpu})" if rate is not None else ""
        self.log(f"{self.label}: asked for {self.cfg.fps:g} fps, running at exactly {self.fps:.6f} fps{how}; "
                 f"frame period {self.period_s * 1e3:.6f} ms")

    def attach(self, pipe: _Pipeline) -> None:
        """Route the session's log into the pipeline (recorded) and add the trigger to its status line."""
        self._pipe = pipe
        for m in self._early_log:
            pipe.log(m, "trigger")
        self._early_log.clear()
        pipe.status_sources.append(self.status)

    # --- starting ---------------------------------------------------------------------------------
    def wait_quiet(self, pipe: _Pipeline) -> bool:
        """Wait until no camera frame arrived for `quiet_s` (at most `max_quiet_wait_s`)."""
        t_begin = hostclock.now()
        while True:
            now = hostclock.now()
            if now - max(pipe.last_frame_recv, t_begin) >= self.quiet_s:
                return True
            if now - t_begin > self.max_quiet_wait_s:
                self.stats.quiet_timeouts += 1
                self.log(f"cameras still sending {self.max_quiet_wait_s:g} s after the trigger stopped "
                         "(free-running?): starting anyway, the frame-0 tie may be wrong")
                return False
            time.sleep(0.01)

    def start(self, pipe: _Pipeline) -> None:
        """Quiet cameras -> frame-0 tie armed -> START -> first clock samples -> clock thread."""
        self._start_trigger(pipe)
        self._thread = threading.Thread(target=self._clock_loop, name="flytrack-trigger-clock", daemon=True)
        self._thread.start()

    def _start_trigger(self, pipe: _Pipeline) -> None:
        assert self.device is not None
        self.wait_quiet(pipe)
        pipe.resynchronize()
        self.clock.clear()
        self._last_count = None
        self.device.start()
        self.started_at = hostclock.now()
        self._expect_running = True
        self.log(f"trigger started at {self.fps:.6f} fps; the first pulse is trigger frame 0")
        # Every start warms up, a re-arm too: its clock model and snapshot start empty, and on a loaded
        # host the first round trips can all exceed max_rtt, so bundles wait for a usable sample.
        self._warmup_left = WARMUP_SAMPLES
        # A few samples at once: bundles get trigger times from the first frames on.
        for _ in range(3):
            self._sample()

    # --- clock thread -----------------------------------------------------------------------------
    def _sample(self) -> ClockReading | None:
        """One clock query: recorded, checked for a device restart, fed to the snapshot."""
        assert self.device is not None
        try:
            r = self.device.query_clock()
        except (TriggerError, OSError, serial.SerialException) as exc:
            self.stats.clock_errors += 1
            self._failures_in_row += 1
            # One unanswered query is not a lost trigger: on a loaded host a reply can miss its
            # timeout. The port itself failing, or several misses in a row, is.
            port_gone = isinstance(exc, (OSError, serial.SerialException))
            if self.lost_since is None and (port_gone or self._failures_in_row >= LOST_AFTER_FAILURES):
                self.lost_since = hostclock.now()
                self.stats.lost += 1
                self.log(f"trigger not answering ({exc}); the run goes on with the last clock model")
            return None
        self._failures_in_row = 0
        if self.lost_since is not None:
            self.log(f"trigger answering again after {hostclock.now() - self.lost_since:.1f} s")
            self.lost_since = None
        self.stats.clock_samples += 1
        if self._pipe is not None:
            self._pipe.record_clock_sample(r.host_t0, r.frame_count, r.ticks / (r.top + 1), r.host_t1)
        restarted = self._expect_running and (
            not r.running or (self._last_count is not None and r.frame_count < self._last_count)
        )
        self._last_count = r.frame_count
        if restarted:
            self.stats.device_restarts += 1
            self.log(f"trigger restarted (pulse count {r.frame_count}, running={r.running}): device reset? "
                     "re-arming the trigger and the frame-0 tie")
            self._rearm()
            return r
        if self.model.restarts > self._seen_model_restarts:
            self._seen_model_restarts = self.model.restarts
            self.stats.clock_model_restarts += 1
            self.log("trigger clock jumped against the host clock (host clock step?): clock model restarted")
            self.clock.clear()
        self.clock.update(self.model, r, self.period_s)
        return r

    def _rearm(self) -> None:
        if self._pipe is None or self._stop.is_set() or self._rearming:
            return
        self._rearming = True  # its own first samples must not re-arm again
        try:
            self._stop_and_rate()
            self._start_trigger(self._pipe)
            self.stats.rearms += 1
        except (TriggerError, OSError, serial.SerialException, RuntimeError) as exc:
            self.stats.clock_errors += 1
            self.log(f"re-arming the trigger failed: {exc}")
        finally:
            self._rearming = False

    def _reconnect(self) -> None:
        """The device vanished: try to open it again; once it answers, re-arm."""
        if self.cfg.kind == "software":
            return  # in-process: it cannot vanish and come back
        try:
            dev, _ = open_device(self.cfg, self.port, self.reset_wait_s, self.model)
        except (TriggerError, OSError, serial.SerialException):
            return
        old, self.device = self.device, dev
        if old is not None:
            try:
                old.close()
            except (OSError, serial.SerialException):
                pass
        self.stats.reconnects += 1
        self.log(f"trigger {self.port} re-opened")
        self.lost_since = None
        self._rearm()

    def _clock_loop(self) -> None:
        last_reconnect = time.monotonic()
        # Each query moved within the frame (QuerySchedule): the warm-up's 20 ms and many a rig's
        # interval are whole numbers of frames, which would put every query at one place in the frame.
        schedule = QuerySchedule(self.period_s)
        while not self._stop.is_set():
            with self._dev_lock:
                if self._stop.is_set():
                    break
                self._sample()
                if self.lost_since is not None and time.monotonic() - last_reconnect > RECONNECT_EVERY_S:
                    last_reconnect = time.monotonic()
                    self._reconnect()
            self._warmup_left -= 1
            schedule.spread_s = self.period_s
            self._stop.wait(schedule.next_wait(WARMUP_INTERVAL_S if self._warmup_left > 0 else self.interval_s))

    # --- stopping ---------------------------------------------------------------------------------
    def stop(self) -> None:
        """Stop the clock thread and the trigger (cameras stop), then close the port."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        with self._dev_lock:
            if self.device is not None and self.lost_since is None:
                try:
                    self.device.stop()
                    self._expect_running = False
                    self.log("trigger stopped")
                except (TriggerError, OSError, serial.SerialException) as exc:
                    self.log(f"could not stop the trigger: {exc}")
        self.close()

    def close(self) -> None:
        if self.device is not None:
            try:
                self.device.close()
            except (OSError, serial.SerialException):
                pass
        if self.software is not None:
            self.software.close()

    # --- reporting --------------------------------------------------------------------------------
    def status(self) -> str:
        if self.lost_since is not None:
            return (f"trigger LOST {hostclock.now() - self.lost_since:.1f} s: using the last clock model "
                    f"({self.stats.clock_errors} errors)")
        m = self.model
        resid = f"{m.residual_s * 1e6:.0f} us" if m.fitted else "-"
        extra = f" restarts {self.stats.device_restarts}" if self.stats.device_restarts else ""
        return f"trigger {self.fps:.3f} fps clock resid {resid} ({self.stats.clock_samples} samples){extra}"

    def summary(self) -> dict[str, Any]:
        return {
            "kind": self.cfg.kind, "port": self.port if self.cfg.kind != "software" else None,
            "fps_asked": self.cfg.fps, "fps": self.fps, "clock_source": self.clock.source,
            "clock_model": self.model.summary() if self.model.fitted else {}, **asdict(self.stats),
        }


__all__ = ["SessionClock", "TriggerSession", "TriggerSessionStats", "open_device", "TriggerError"]
