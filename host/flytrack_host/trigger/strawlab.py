"""Driver of the strawlab triggerbox (Arduino Nano firmware used with flydra/Braid), sharing the
FlyTrack clock model.

Its serial protocol (MISSION.md, "Figures from the field"): 115200 baud; commands `V?` (version),
`P<u8>` (clock query carrying a token), `S0` stop, `S1` start, `S2` stop and reset the pulse count
(our reading of the third state), `T=` + u16 LE ICR1 + '1' (prescaler 8) or '2' (prescaler 64),
`O=` + u16 + u16 + u8 (analog outputs), `N?` (name). Replies: a header char, a length byte, the
payload, then a checksum = sum of the payload mod 256. The clock reply 'P' carries {u8 token,
u32 pulse number, u16 TCNT1}. The board runs Timer1 fast PWM with TOP = ICR1 at 16 MHz.

It has no pulse channel: `pulse()` raises TriggerError.

Early-frame samples: a query answered in the first moments of a frame (small TCNT1) may find the timer
wrapped but the pulse count not yet incremented, which puts the sample exactly one frame early. Once the
clock model has a fit, such a sample (TCNT1 below EARLY_FRACTION of the period) is compared with the
model's prediction and moved one frame on when that is where it belongs (`early_corrected`); before
the first fit it is not used (`early_skipped`). clock_model.correct_clock_counts does the same for
recorded samples (flydra/Braid trigger_clock_info).
"""

from __future__ import annotations

import struct
import threading
import time

import serial

from flytrack_host.util import hostclock

from .clock_model import EARLY_FRACTION, ClockModel, LinkTiming
from .common import ClockThread, RateChoice, SerialTrigger, TriggerError, choose_rate, open_serial
from .device import ClockReading

F_CPU = 16_000_000
_PRESCALER_CHAR = {2: b"1", 3: b"2"}  # SPEC prescaler code -> the triggerbox's T= suffix


# Clock query on the wire: 'P' + token (2 bytes); reply 'P', length, 7 payload bytes, checksum (10).
# The triggerbox's processing time is not known here (no board to measure): taken as 0.
CLOCK_REQUEST_BYTES = 2
CLOCK_REPLY_BYTES = 10


def clock_link_timing(baudrate: float) -> LinkTiming:
    return LinkTiming.serial(baudrate, CLOCK_REQUEST_BYTES, CLOCK_REPLY_BYTES, 0.0)


def checksum(payload: bytes) -> int:
    return sum(payload) & 0xFF


class StrawlabTriggerbox(SerialTrigger):
    """The strawlab triggerbox on a serial port, with the TriggerDevice surface."""

    def __init__(self, port: str, baudrate: int = 115200, reset_wait_s: float = 2.0, timeout_s: float = 0.5,
                 model: ClockModel | None = None, wire_timed: bool = True) -> None:
        """wire_timed: as TriggerDevice's (False for a peer that answers at once on a pty)."""
        self.port = port
        self.timeout_s = timeout_s
        self.model = model or ClockModel()
        self.model.link = clock_link_timing(baudrate) if wire_timed else None
        self.rate: RateChoice | None = None
        self._ser = open_serial(port, baudrate, timeout=timeout_s)
        self._lock = threading.Lock()
        self._token = 0
        self._levels = [0, 0]  # analog outputs 0 and 1, as last set (O= sets both at once)
        self.early_corrected = 0  # clock samples one frame early (count not yet incremented), corrected
        self.early_skipped = 0  # early-frame samples not used because the model had no fit yet
        self._clock_thread: ClockThread | None = None
        if reset_wait_s > 0:
            time.sleep(reset_wait_s)
        self._ser.reset_input_buffer()
        try:
            self.version = self._query(b"V?", b"V")[0]
        except TriggerError as exc:
            self._ser.close()
            raise TriggerError(f"the device on {port} does not answer as a strawlab triggerbox: {exc}") from None

    def _read_reply(self, header: bytes) -> bytes:
        deadline = time.monotonic() + self.timeout_s
        while time.monotonic() < deadline:
            b = self._ser.read(1)
            if not b or b != header:
                continue  # resynchronise on the expected header
            n = self._ser.read(1)
            if not n:
                break
            body = self._ser.read(n[0] + 1)
            if len(body) != n[0] + 1:
                break
            payload, cs = body[:-1], body[-1]
            if checksum(payload) != cs:
                raise TriggerError(f"triggerbox reply {header!r} has a bad checksum")
            return payload
        raise TriggerError(f"no {header!r} reply from {self.port} within {self.timeout_s} s")

    def _query(self, cmd: bytes, header: bytes) -> bytes:
        with self._lock:
            try:
                self._ser.write(cmd)
            except (serial.SerialException, OSError) as exc:
                raise TriggerError(f"cannot write to {self.port}: {exc}") from None
            return self._read_reply(header)

    def _send(self, cmd: bytes) -> None:
        with self._lock:
            try:
                self._ser.write(cmd)
            except (serial.SerialException, OSError) as exc:
                raise TriggerError(f"cannot write to {self.port}: {exc}") from None

    def info(self) -> dict[str, object]:
        name = self._query(b"N?", b"N").rstrip(b"\0").decode("ascii", "replace")
        return {"kind": "strawlab triggerbox", "version": self.version, "name": name, "f_cpu": F_CPU}

    def set_rate(self, fps: float) -> float:
        choice = choose_rate(fps, F_CPU, codes=(2, 3))
        self._send(b"T=" + struct.pack("<H", choice.top) + _PRESCALER_CHAR[choice.prescaler_code])
        self.rate = choice
        self.model.frame_period_s = choice.period_s
        return choice.fps

    def start(self) -> None:
        self._send(b"S1")

    def stop(self) -> None:
        self._send(b"S0")

    def stop_reset(self) -> None:
        self._send(b"S2")
        self.model.reset()

    def query_clock(self) -> ClockReading:
        if self.rate is None:
            raise TriggerError("frame rate unknown: call set_rate() first")
        self._token = (self._token + 1) & 0xFF
        t0 = hostclock.now()
        payload = self._query(b"P" + bytes([self._token]), b"P")
        t1 = hostclock.now()
        if len(payload) != 7:
            raise TriggerError(f"triggerbox clock reply has {len(payload)} bytes, expected 7")
        token, pulses, tcnt = struct.unpack("<BIH", payload)
        if token != self._token:
            raise TriggerError(f"triggerbox answered query {token}, expected {self._token}")
        dev_t = ((pulses - 1) * (self.rate.top + 1) + tcnt) * self.rate.tick_s
        use = True
        if tcnt < EARLY_FRACTION * (self.rate.top + 1):
            if self.model.fitted:
                period = (self.rate.top + 1) * self.rate.tick_s
                pred = self.model.host_to_device(self.model.sample_host_time(t0, t1))
                if abs(pred - (dev_t + period)) < abs(pred - dev_t):
                    dev_t += period
                    pulses += 1
                    self.early_corrected += 1
            else:
                use = False
                self.early_skipped += 1
        r = ClockReading(t0, t1, pulses, tcnt, self.rate.top, True, dev_t)
        if use:
            self.model.add_sample(t0, t1, dev_t)
        return r

    def pulse(self, channel: int = 0, frame: int | None = None, width_s: float = 0.001) -> int:
        raise TriggerError("the strawlab triggerbox has no pulse output")

    def set_output(self, channel: int, level: int | bool) -> None:
        """Analog outputs 0/1 set fully low or high (O= command)."""
        if channel not in (0, 1):
            raise TriggerError("the strawlab triggerbox has analog outputs 0 and 1")
        self._levels[channel] = 0xFFFF if level else 0
        self._send(b"O=" + struct.pack("<HHB", self._levels[0], self._levels[1], 3))

    def events(self) -> list:
        return []
