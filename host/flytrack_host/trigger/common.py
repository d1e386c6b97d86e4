"""Pieces shared by the trigger drivers: errors, serial opening, rate choice, the clock thread."""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Self

import serial

PRESCALERS: dict[int, int] = {1: 1, 2: 8, 3: 64, 4: 256, 5: 1024}  # SPEC prescaler code -> divisor


class TriggerError(RuntimeError):
    """A trigger device problem with a clear cause: missing or busy port, wrong protocol, refusal."""


@dataclass(frozen=True)
class RateChoice:
    prescaler_code: int
    top: int
    f_cpu: int

    @property
    def divisor(self) -> int:
        return PRESCALERS[self.prescaler_code]

    @property
    def fps(self) -> float:
        return self.f_cpu / ((self.top + 1) * self.divisor)

    @property
    def tick_s(self) -> float:
        return self.divisor / self.f_cpu

    @property
    def period_s(self) -> float:
        return (self.top + 1) * self.tick_s


def choose_rate(
    fps: float,
    f_cpu: int,
    codes: tuple[int, ...] = (1, 2, 3, 4, 5),
    min_top: int = 15,
    min_period_cycles: int = 1600,
) -> RateChoice:
    """Prescaler and TOP whose frame rate is closest to `fps` (ties: the finer prescaler)."""
    if not fps > 0:
        raise TriggerError(f"frame rate must be positive, got {fps}")
    best: RateChoice | None = None
    for code in codes:
        div = PRESCALERS[code]
        ideal = f_cpu / (div * fps) - 1
        for top in {int(ideal), int(ideal) + 1}:
            if not min_top <= top <= 0xFFFF or (top + 1) * div < min_period_cycles:
                continue
            c = RateChoice(code, top, f_cpu)
            if best is None or abs(c.fps - fps) < abs(best.fps - fps) - 1e-12:
                best = c
    if best is None:
        lo = f_cpu / (PRESCALERS[max(codes)] * 65536)
        hi = f_cpu / max(min_period_cycles, min_top + 1)
        raise TriggerError(f"{fps} fps is outside what the device can make ({lo:.3g} .. {hi:.6g} fps)")
    return best


def _no_such_port(port: str) -> TriggerError:
    return TriggerError(f"serial port {port} does not exist (is the board plugged in?)")


def check_port_exists(port: str) -> None:
    """Raises the drivers' TriggerError for a serial port that is not there (before handing the port
    to a tool such as avrdude, whose own message is far less clear)."""
    if not os.path.exists(port):
        raise _no_such_port(port)


def open_serial(port: str, baudrate: int, timeout: float = 0.05) -> serial.Serial:
    """Opens a serial port exclusively, turning pyserial's errors into clear TriggerErrors."""
    try:
        return serial.Serial(port, baudrate, timeout=timeout, exclusive=True)
    except serial.SerialException as exc:
        text = str(exc)
        if "No such file" in text or "could not open port" in text and "Errno 2" in text:
            raise _no_such_port(port) from None
        if "exclusively lock" in text or "Resource temporarily unavailable" in text or "busy" in text.lower():
            raise TriggerError(f"serial port {port} is busy: another program has it open") from None
        if "Permission denied" in text:
            raise TriggerError(f"no permission to open {port} (add yourself to the dialout group)") from None
        raise TriggerError(f"cannot open serial port {port}: {text}") from None


GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


class QuerySchedule:
    """When clock queries are due: every `interval_s`, each moved within the frame by a share of the
    frame period `spread_s` that walks through the frame (k x golden ratio mod 1), so that an
    interval that is a whole number of frames does not put every query at the same place in the
    frame (the strawlab box's count steps 1000 ticks into it; a query that always lands before
    that step, or always at it, tells the clock model less). Falls back in step when late."""

    def __init__(self, spread_s: float = 0.0) -> None:
        self.spread_s = max(0.0, float(spread_s or 0.0))
        self._grid = time.monotonic()
        self._k = 0

    def next_wait(self, interval_s: float) -> float:
        """Seconds from now to the next query, `interval_s` after the last one's grid point."""
        now = time.monotonic()
        self._k += 1
        self._grid += interval_s
        if self._grid < now - interval_s:  # far behind (a slow query, a reconnect): start again from now
            self._grid = now
        due = self._grid + self.spread_s * ((self._k * GOLDEN) % 1.0)
        return max(0.0, due - now)


class ClockThread:
    """Calls `query` every `period_s` seconds in a daemon thread until stopped; with `spread_s` (the
    frame period) each call is moved within the frame (QuerySchedule)."""

    def __init__(self, query: Callable[[], object], period_s: float, spread_s: float = 0.0) -> None:
        self._query = query
        self._period = period_s
        self._schedule = QuerySchedule(spread_s)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="trigger-clock", daemon=True)
        self.errors = 0
        self.last_error: Exception | None = None

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._query()
            except (TriggerError, OSError, serial.SerialException) as exc:
                self.errors += 1
                self.last_error = exc
            self._stop.wait(self._schedule.next_wait(self._period))

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=2)


class SerialTrigger:
    """What every serial trigger driver shares: the background clock-query thread and its lifetime.
    Subclasses set `_ser` (the serial port) and `_clock_thread = None`, and define `query_clock()`."""

    _ser: serial.Serial
    _clock_thread: ClockThread | None

    def query_clock(self) -> object:
        raise NotImplementedError

    def start_clock_thread(self, period_s: float = 0.1) -> None:
        if self._clock_thread is None:
            model = getattr(self, "model", None)
            self._clock_thread = ClockThread(self.query_clock, period_s,
                                             spread_s=getattr(model, "frame_period_s", None) or 0.0)
            self._clock_thread.start()

    def stop_clock_thread(self) -> None:
        if self._clock_thread is not None:
            self._clock_thread.stop()
            self._clock_thread = None

    def close(self) -> None:
        self.stop_clock_thread()
        try:
            self._ser.close()
        except (serial.SerialException, OSError):
            pass

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
