"""Driver of the strawlab triggerbox (the Arduino Nano box of flydra and Braid, firmware version 14),
sharing the FlyTrack clock model. firmware/strawlab_box does on the wire what that firmware does,
so that this driver is tested against it in simavr (docs/compatibility.md).

What the box does, and what the driver does about it:

- Reset. A Nano resets when its port is opened, and the firmware then spends ~5.5 s in a 9600-baud
  name handshake that drops every byte but 'N' before it answers at "115200". The driver waits
  `reset_wait_s` (RESET_WAIT_S = 7 s, as Braid does) and asks `V?` every second until it answers,
  at most `connect_timeout_s` (20 s, as Braid) after opening. A port that does not reset the box
  (a simulated box on a pty) is opened with reset_wait_s = 0: the probes then start at once.
- No framing. A command is two bytes, taken whenever two are waiting; one stray byte (line noise,
  a probe cut in two as the box leaves its handshake) shifts every later pair. Replies are found by
  their header, length (7) and checksum; whatever is waiting before a query is read and dropped
  first, and a reply to another query (late, or not asked for) is dropped, so none of them shifts
  later queries onto the wrong replies. The box itself is put back in step only on evidence: from
  the second clock query in a row left unanswered on, with no late reply to a recent token seen
  0.2 s more, every other query is sent with a leading '?' ('?' is no command, and a pair that
  starts with it does nothing, so one of the two realigns the box). V? probes stay plain for the
  first 8 s (the box may still be in its handshake). The commands the box does not answer (S, T=,
  N=) and those that would leave it waiting for bytes (O=, N?) go only after a reply carrying a
  token has shown it in step; a clock query is made first when none has.
- Commands: `V?` (reply 'V', value 14), `P` + token (reply 'P' with the token), `S0` stop and zero
  the pulse count and TCNT1, `S1` start, `S2` stop only, `T=` + u16 LE TOP + '1' (prescaler 8) or
  '2' (64), `O=` + u16 + u16 + u8 (analog outputs; reply 'O' with the u8), `N?` (name), `N=` +
  8 bytes + 2 hex characters (sets the name). Replies 'P', 'V', 'O': header, 7, {u8 value, u32
  pulse count, u16 TCNT1} little-endian, then the sum of those 7 bytes mod 256.
- The reply to `N?` is the 8 name bytes from EEPROM, then their CRC-8/Maxim in upper-case hex
  without a leading zero (one or two characters): no header, no length, no checksum.
- The UART runs at 16 MHz / (8 x 17) = 117647 baud when "115200" is asked for (UBRR 16, double
  speed): the link timing of the clock model uses that (a round trip can be shorter than 12 bytes
  at 115200 baud would take).
- Frame count. Timer1 fast PWM, TOP = ICR1; the trigger (OC1A) rises at BOTTOM and falls at the
  match with OCR1A = 1000, and the pulse count is incremented in that match interrupt, not at the
  wrap. A clock sample with TCNT1 <= 1000 therefore has the count of the pulses begun before the
  frame under way, one with TCNT1 past the match that count plus one. The first rising edge after
  a start from S0 is one period after the start (the output is set at BOTTOM, which the counter
  first reaches then), and that pulse is FlyTrack's frame 0: a sample's "pulses started" (the
  FlyTrack firmware's frame count) is the count when TCNT1 <= 1000 and the count - 1 after the
  match. For a short while after the match (the interrupt may wait for another, at most
  COUNT_LATE_CYCLES) either can be true: there the clock model's prediction decides, and before
  it has a fit the sample is not used (`stats["near_mark_skipped"]`).

It has no pulse channel: `pulse()` raises TriggerError.
"""

from __future__ import annotations

import math
import select
import struct
import threading
import time
from collections import deque

import serial

from flytrack_host.util import hostclock

from .clock_model import ClockModel, LinkTiming
from .common import ClockThread, RateChoice, SerialTrigger, TriggerError, choose_rate, open_serial
from .device import ClockReading

F_CPU = 16_000_000
FIRMWARE_VERSION = 14  # what the firmware this driver was written against answers to V?
OCR1A = 1000  # the firmware's trigger pulse width in ticks, and where its pulse count steps
NAME_LEN = 8
RESET_WAIT_S = 7.0  # after opening a port that resets the Nano: its name handshake lasts ~5.5 s
CONNECT_TIMEOUT_S = 20.0  # from opening the port to the first answer to V?
PROBE_EVERY_S = 1.0  # V? again this often until the box answers
PLAIN_PROBES_S = 8.0  # and without a realigning '?' for this long (the handshake of a box reset just before)
LATE_LOOK_S = 0.2  # before realigning, how long to look for late replies that would show the box in step
CONTROL_TIMEOUT_S = 2.0  # V?, O=, N?: the box waits for the bytes after O= in steps of 10 ms
# How late the OCR1A match interrupt may increment the count after the match: the chip enters it
# after the instruction under way and after a running interrupt (the Arduino core's Timer0 and
# UART ones, ~100 cycles each) or a section with interrupts off.
COUNT_LATE_CYCLES = 400
_PRESCALER_CHAR = {2: b"1", 3: b"2"}  # SPEC prescaler code -> the triggerbox's T= suffix
_COMMAND_BYTES = frozenset(b"NOPSTV=?")  # never used as a token or sequence byte
REPLY_LEN = 7

# Clock query on the wire: 'P' + token (2 bytes); reply 'P', length, 7 payload bytes, checksum (10).
# The firmware's own time from the request's last byte to its sample (its main loop seeing two
# bytes waiting) is a few microseconds: taken as 0.
CLOCK_REQUEST_BYTES = 2
CLOCK_REPLY_BYTES = 10


def uart_baud(nominal: float, f_cpu: int = F_CPU) -> float:
    """The rate an Arduino AVR UART really runs at when `nominal` baud is asked for: the Arduino
    core picks the double-speed divisor UBRR = (f_cpu / 4 / baud - 1) / 2 in integer arithmetic
    (single speed for 57600 at 16 MHz, or when that divisor would not fit in 12 bits)."""
    n = int(nominal)
    if n <= 0:
        raise ValueError("baud rate must be positive")
    ubrr = (f_cpu // 4 // n - 1) // 2
    if (f_cpu == 16_000_000 and n == 57600) or ubrr > 4095:
        return f_cpu / (16 * ((f_cpu // 8 // n - 1) // 2 + 1))
    return f_cpu / (8 * (ubrr + 1))


def clock_link_timing(baudrate: float) -> LinkTiming:
    """Wire timing of a clock query at the rate the box's UART really runs at for `baudrate`."""
    return LinkTiming.serial(uart_baud(baudrate), CLOCK_REQUEST_BYTES, CLOCK_REPLY_BYTES, 0.0)


def checksum(payload: bytes) -> int:
    return sum(payload) & 0xFF


def crc8_maxim(data: bytes) -> int:
    """CRC-8/Maxim (Dallas 1-Wire): reflected polynomial 0x31, initial value 0, no final xor."""
    crc = 0
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0x8C if crc & 1 else crc >> 1
    return crc


def name_reply(name: bytes) -> bytes:
    """What the box sends for `N?`: the 8 name bytes, then their CRC in upper-case hex, no leading zero."""
    return name + f"{crc8_maxim(name):X}".encode()


def frames_started(count: int, ticks: int, top: int, divisor: int) -> tuple[int, int]:
    """(pulses started, how sure) of a clock sample {pulse count, TCNT1}: see the module docstring.
    how: 0 the count had not stepped for the frame under way (TCNT1 <= OCR1A), 1 it had, -1 either
    can be true (just after the match): the first element is then the value if it had."""
    if ticks <= OCR1A or top <= OCR1A:
        return count, 0
    if ticks <= OCR1A + math.ceil(COUNT_LATE_CYCLES / divisor):
        return count - 1, -1
    return count - 1, 1


class StrawlabTriggerbox(SerialTrigger):
    """The strawlab triggerbox on a serial port, with the TriggerDevice surface."""

    def __init__(self, port: str, baudrate: int = 115200, reset_wait_s: float = RESET_WAIT_S,
                 timeout_s: float = 0.5, model: ClockModel | None = None, wire_timed: bool = True,
                 connect_timeout_s: float = CONNECT_TIMEOUT_S) -> None:
        """reset_wait_s: the wait before the first V? (the name handshake after the reset that opening
        the port causes); 0 for a port that does not reset the box. wire_timed: as TriggerDevice's."""
        self.port = port
        self.timeout_s = timeout_s
        self.model = model or ClockModel()
        self.model.link = clock_link_timing(baudrate) if wire_timed else None
        self.rate: RateChoice | None = None
        self.stats = {"stray_replies": 0, "junk_bytes": 0, "bad_checksums": 0, "unanswered": 0,
                      "realigned": 0, "near_mark_resolved": 0, "near_mark_skipped": 0}
        self._token = 0
        self._misses = 0  # queries in a row that got no reply (the box may be one byte out of step)
        self._recent: deque[int] = deque(maxlen=8)  # tokens of the last queries (a late reply is one of them)
        self._in_step = False  # a reply since the last miss or realigned query shows the box in step
        self._plain_probes_until = math.inf  # _connect: V? without a realigning '?' until then
        self._rx = bytearray()
        self._running = False
        self._levels = [0, 0]  # analog outputs 0 and 1, as last set (O= sets both at once)
        self._clock_thread: ClockThread | None = None
        self._lock = threading.Lock()
        t_open = time.monotonic()
        self._ser = open_serial(port, baudrate, timeout=0.005)
        try:
            if reset_wait_s > 0:
                time.sleep(reset_wait_s)
            self.version, self._connect_s = self._connect(t_open + max(connect_timeout_s, reset_wait_s))
        except BaseException:
            self._ser.close()
            raise

    # ------------------------------------------------------------------ wire

    def _write(self, data: bytes) -> None:
        try:
            self._ser.write(data)
        except (serial.SerialException, OSError) as exc:
            raise TriggerError(f"cannot write to {self.port}: {exc}") from None

    def _read_some(self, until: float) -> bool:
        """Reads what arrives before `until` (monotonic) into the buffer; False when nothing did."""
        try:
            while True:
                n = self._ser.in_waiting
                if n:
                    self._rx += self._ser.read(n)
                    return True
                left = until - time.monotonic()
                if left <= 0:
                    return False
                if select.select([self._ser.fileno()], [], [], min(left, 0.05))[0] and not self._ser.in_waiting:
                    # Readable with nothing to read: the other end of a pty is gone (or between writes).
                    data = self._ser.read(1)
                    if data:
                        self._rx += data
                        return True
                    time.sleep(0.001)
        except (serial.SerialException, OSError, TypeError, ValueError) as exc:
            raise TriggerError(f"cannot read from {self.port}: {exc}") from None

    def _packet(self) -> tuple[int, bytes] | None:
        """The first whole reply in the buffer (header, payload), bytes before it dropped; None when
        the buffer holds none yet (a partial reply stays)."""
        buf = self._rx
        while buf:
            if buf[0] not in b"PVO":
                del buf[0]
                self.stats["junk_bytes"] += 1
                continue
            if len(buf) < 2:
                return None
            if buf[1] != REPLY_LEN:
                del buf[0]
                self.stats["junk_bytes"] += 1
                continue
            if len(buf) < REPLY_LEN + 3:
                return None
            payload = bytes(buf[2:2 + REPLY_LEN])
            if checksum(payload) != buf[2 + REPLY_LEN]:
                self.stats["bad_checksums"] += 1
                del buf[0]  # not a reply after all, or a corrupted one: look further on
                continue
            header = buf[0]
            del buf[:REPLY_LEN + 3]
            return header, payload
        return None

    def _drain(self) -> None:
        """Whatever is waiting (late replies, replies nobody asked for, junk) is read and dropped."""
        try:
            n = self._ser.in_waiting
            if n:
                self._rx += self._ser.read(n)
        except (serial.SerialException, OSError, TypeError) as exc:
            raise TriggerError(f"cannot read from {self.port}: {exc}") from None
        while (p := self._packet()) is not None:
            self._note_stray(p)
        self.stats["junk_bytes"] += len(self._rx)
        self._rx.clear()

    def _note_stray(self, packet: tuple[int, bytes]) -> None:
        self.stats["stray_replies"] += 1
        if packet[0] == ord("P") and packet[1][0] in self._recent:
            self._misses = 0  # an earlier query was answered, late: the box was in step

    def _next_byte(self, reserved: frozenset[int] = _COMMAND_BYTES) -> int:
        while True:
            self._token = self._token % 255 + 1
            if self._token not in reserved:
                return self._token

    def _request(self, cmd: bytes, header: bytes, value: int | None, timeout_s: float
                 ) -> tuple[bytes, float, float]:
        """Sends `cmd` and returns (payload, host time sent, host time the reply was in) of the first
        `header` reply whose value byte is `value` (any when None); TriggerError after `timeout_s`."""
        with self._lock:
            self._drain()
            # After one miss the reply was more likely late than the box out of step: the same again;
            # from the second on, every other query is sent realigned, after a last look for late replies
            # (one to a recent query shows the box in step: then not). V? probes while the box may still
            # be in its handshake are never realigned.
            realign = (self._misses >= 2 and self._misses % 2 == 0
                       and time.monotonic() >= self._plain_probes_until)
            if realign:
                self._read_some(time.monotonic() + LATE_LOOK_S)
                self._drain()
                realign = self._misses >= 2
            if realign:
                self.stats["realigned"] += 1
                self._in_step = False
            if cmd[:1] == b"P":
                self._recent.append(cmd[1])
            t0 = hostclock.now()
            self._write(b"?" + cmd if realign else cmd)
            deadline = time.monotonic() + timeout_s
            while True:
                p = self._packet()
                if p is None:
                    if not self._read_some(deadline):
                        self._misses += 1
                        self._in_step = False
                        self.stats["unanswered"] += 1
                        raise TriggerError(f"no {header!r} reply to {cmd[:2]!r} from {self.port} within {timeout_s} s")
                    continue
                if p[0] == header[0] and (value is None or p[1][0] == value):
                    t1 = hostclock.now()
                    self._misses = 0
                    # A V reply may be a late one to an earlier probe: only a token proves the box in step.
                    self._in_step = value is not None
                    return p[1], t0, t1
                self._note_stray(p)

    def _in_step_now(self) -> None:
        """Makes sure the box takes the next two bytes as one command: unless the last query was answered,
        clock queries (realigned as in _request) until one is. For the commands the box does not answer
        (S, T=, N=): sent out of step they would be taken apart and lost without a word."""
        for _ in range(4):
            if self._in_step:
                return
            token = self._next_byte()
            try:
                self._request(b"P" + bytes([token]), b"P", token, CONTROL_TIMEOUT_S)
            except TriggerError as exc:
                if "cannot" in str(exc):
                    raise
        if not self._in_step:
            raise TriggerError(f"the strawlab box on {self.port} does not answer clock queries")

    def _send(self, cmd: bytes) -> None:
        self._in_step_now()
        with self._lock:
            self._write(cmd)

    def _connect(self, deadline: float) -> tuple[int, float]:
        """V? every PROBE_EVERY_S until the box answers (at most until `deadline`, monotonic) ->
        (firmware version, seconds from the first probe to the answer)."""
        t_first = time.monotonic()
        # Plain V? (never shifting the box) for as long as a box just reset may still be in its handshake.
        self._plain_probes_until = t_first + PLAIN_PROBES_S
        bad = 0
        while True:
            try:
                payload, _, _ = self._request(b"V?", b"V", None,
                                              min(PROBE_EVERY_S, max(0.05, deadline - time.monotonic())))
                self._plain_probes_until = 0.0
                return payload[0], time.monotonic() - t_first
            except TriggerError as exc:
                if "cannot" in str(exc):
                    raise
            bad = self.stats["bad_checksums"]
            if time.monotonic() >= deadline:
                break
        seen = f"; {bad} replies had a bad checksum" if bad else ""
        junk = self.stats["junk_bytes"]
        seen += f"; it sent {junk} bytes that were no reply" if junk and not bad else ""
        raise TriggerError(
            f"the device on {self.port} does not answer as a strawlab triggerbox (no reply to V? within "
            f"{deadline - t_first:.1f} s{seen}); a strawlab box answers ~5.5 s after a reset")

    # ------------------------------------------------------------------ commands

    def info(self) -> dict[str, object]:
        return {"kind": "strawlab triggerbox", "version": self.version, "name": self.name(), "f_cpu": F_CPU,
                "uart_baud": round(uart_baud(self._ser.baudrate), 1)}

    def _strip_replies(self) -> bool:
        """Drops a whole reply (late, unasked) at the start of the buffer, where the name is expected (it
        has no header); True when one was dropped."""
        buf = self._rx
        if (len(buf) >= REPLY_LEN + 3 and buf[0] in b"PVO" and buf[1] == REPLY_LEN
                and checksum(bytes(buf[2:2 + REPLY_LEN])) == buf[2 + REPLY_LEN]):
            del buf[:REPLY_LEN + 3]
            self.stats["stray_replies"] += 1
            return True
        return False

    def name(self) -> str:
        """The name in the box's EEPROM (N?); "" for a box never named (its EEPROM erased, 0xFF)."""
        raw = self._read_name()
        if raw == b"\xff" * NAME_LEN:
            return ""
        return raw.rstrip(b"\0").decode("ascii", "replace")

    def _read_name(self) -> bytes:
        self._in_step_now()
        with self._lock:
            self._drain()
            self._write(b"N?")
            deadline = time.monotonic() + CONTROL_TIMEOUT_S
            while True:
                if self._strip_replies():
                    continue
                buf = self._rx
                maybe_reply = len(buf) >= 2 and buf[0] in b"PVO" and buf[1] == REPLY_LEN and len(buf) < REPLY_LEN + 3
                if len(buf) >= NAME_LEN + 1 and not maybe_reply:
                    break
                if not self._read_some(deadline):
                    got = bytes(self._rx)
                    self._rx.clear()
                    raise TriggerError(f"no name from {self.port}: {len(got)} of at least {NAME_LEN + 1} "
                                       f"bytes of the reply to N? within {CONTROL_TIMEOUT_S} s ({got!r})")
            raw = bytes(self._rx[:NAME_LEN])
            crc = f"{crc8_maxim(raw):X}".encode()
            # Exactly as many hex characters as this CRC has: no terminator follows.
            while len(self._rx) < NAME_LEN + len(crc) and self._read_some(deadline):
                pass
            got = bytes(self._rx[NAME_LEN:NAME_LEN + len(crc)])
            del self._rx[:NAME_LEN + len(crc)]
        if got != crc:
            raise TriggerError(f"the name {raw!r} from {self.port} comes with CRC {got!r}, expected {crc!r}")
        return raw

    def set_name(self, name: str) -> None:
        """Stores `name` (at most 8 ASCII characters) in the box's EEPROM (N=), then reads it back."""
        raw = name.encode("ascii")
        if len(raw) > NAME_LEN:
            raise TriggerError(f"a strawlab box name has at most {NAME_LEN} characters, got {name!r}")
        raw = raw.ljust(NAME_LEN, b"\0")
        self._send(b"N=" + raw + f"{crc8_maxim(raw):02X}".encode())  # the firmware reads two characters
        if self._read_name() != raw:
            raise TriggerError(f"the box on {self.port} did not keep the name {name!r}")

    def set_rate(self, fps: float) -> float:
        # OC1A falls at OCR1A = 1000: TOP must be past it for a pulse, and a count, every frame.
        choice = choose_rate(fps, F_CPU, codes=(2, 3), min_top=OCR1A + 1)
        self._send(b"T=" + struct.pack("<H", choice.top) + _PRESCALER_CHAR[choice.prescaler_code])
        self.rate = choice
        self.model.frame_period_s = choice.period_s
        return choice.fps

    def version_sample(self) -> tuple[int, int]:
        """(pulse count, TCNT1) from the reply to V?."""
        payload, _, _ = self._request(b"V?", b"V", None, CONTROL_TIMEOUT_S)
        _, count, ticks = struct.unpack("<BIH", payload)
        return count, ticks

    def start(self) -> None:
        self._send(b"S1")
        self._running = True

    def stop(self) -> None:
        """Stops the trigger; the pulse count is kept (S2)."""
        self._send(b"S2")
        self._running = False

    def stop_reset(self) -> None:
        """Stops the trigger and zeroes its pulse count and timer (S0), checked with V?."""
        self._running = False
        count = ticks = -1
        for _ in range(3):
            self._send(b"S0")
            try:
                count, ticks = self.version_sample()
            except TriggerError:
                continue  # unanswered: the next S0 goes after a clock query has shown the box in step
            if count == 0 and ticks == 0:
                self.model.reset()
                return
        raise TriggerError(f"the strawlab box on {self.port} did not stop with its count zeroed after S0 "
                           f"(count {count}, TCNT1 {ticks})")

    def query_clock(self) -> ClockReading:
        if self.rate is None:
            raise TriggerError("frame rate unknown: call set_rate() first")
        token = self._next_byte()
        payload, t0, t1 = self._request(b"P" + bytes([token]), b"P", token, self.timeout_s)
        _, count, ticks = struct.unpack("<BIH", payload)
        top, period = self.rate.top, self.rate.top + 1
        started, how = frames_started(count, ticks, top, self.rate.divisor)
        use = self._running
        if how < 0:  # just after the match: the count may not have stepped yet
            if self.model.fitted:
                pred = self.model.host_to_device(self.model.sample_host_time(t0, t1))
                stepped = ((started - 1) * period + ticks) * self.rate.tick_s
                if abs(pred - (stepped + self.rate.period_s)) < abs(pred - stepped):
                    started += 1
                self.stats["near_mark_resolved"] += 1
            else:
                use = False
                self.stats["near_mark_skipped"] += 1
        dev_t = ((started - 1) * period + ticks) * self.rate.tick_s
        r = ClockReading(t0, t1, started, ticks, top, self._running, dev_t)
        if use:
            self.model.add_sample(t0, t1, dev_t)
        return r

    def pulse(self, channel: int = 0, frame: int | None = None, width_s: float = 0.001) -> int:
        raise TriggerError("the strawlab triggerbox has no pulse output")

    def set_output(self, channel: int, level: int | bool) -> tuple[int, int]:
        """Analog outputs 0/1 set fully low or high (O=); returns (pulse count, TCNT1) of the box's
        confirmation, which is read (it is a reply like the clock's, and left waiting it would be
        taken for one)."""
        if channel not in (0, 1):
            raise TriggerError("the strawlab triggerbox has analog outputs 0 and 1")
        self._in_step_now()  # O= taken apart would leave the box waiting for bytes that are our next queries
        self._levels[channel] = 4095 if level else 0  # 12-bit DAC, full scale
        seq = self._next_byte()
        payload, _, _ = self._request(b"O=" + struct.pack("<HHB", self._levels[0], self._levels[1], seq),
                                      b"O", seq, CONTROL_TIMEOUT_S)
        _, count, ticks = struct.unpack("<BIH", payload)
        return count, ticks

    def events(self) -> list:
        return []
