"""StrawlabTriggerbox against a pty peer in Python that answers as the strawlab firmware (version 14)
does. The simulated firmware in simavr (firmware/strawlab_box, tests/firmware/test_strawlab_box.py)
is the reference; this peer is for what that one cannot be made to do on demand: a corrupted
checksum, a pulse count set to a given value, a byte lost on the way."""

from __future__ import annotations

import os
import select
import struct
import threading
import time
import tty

import pytest

from flytrack_host.trigger.common import TriggerError
from flytrack_host.trigger.strawlab import (
    COUNT_LATE_CYCLES,
    OCR1A,
    StrawlabTriggerbox,
    checksum,
    crc8_maxim,
    frames_started,
    name_reply,
    uart_baud,
)


class _Box:
    """The strawlab firmware's behaviour on the wire, timed by the host clock: commands two bytes at a
    time with no framing, S0 stop and zero, S2 stop, the pulse count stepping OCR1A ticks into each
    frame, N? answered with the name and its hex CRC, O= confirmed with an 'O' reply."""

    def __init__(self, corrupt: bool = False, name: bytes = b"box-1\0\0\0", boot_s: float = 0.0) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.port = os.ttyname(self.slave)
        self.corrupt = corrupt
        self.name = name
        self.commands: list[bytes] = []
        self.top, self.div, self.div_next = 10000, 64, 64  # boot: 25 fps, running
        self.pos = 0.0  # timer ticks since the last S0 (wraps included), as of t_ref
        self.t_ref = time.monotonic()
        self.running = True
        self.boot_until = time.monotonic() + boot_s  # the name handshake: every byte but 'N' dropped
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    # the timer
    def _now_pos(self) -> float:
        if not self.running:
            return self.pos
        return self.pos + (time.monotonic() - self.t_ref) * 16e6 / self.div

    def count_and_ticks(self) -> tuple[int, int]:
        p = int(self._now_pos())
        period = self.top + 1
        return (p + period - (OCR1A + 1)) // period, p % period

    def set_stopped_at(self, count: int, ticks: int) -> None:
        """Stopped with the pulse count at `count` and TCNT1 at `ticks`."""
        self.running = False
        self.pos = (count - (1 if ticks > OCR1A else 0)) * (self.top + 1) + ticks

    def _reply(self, header: bytes, value: int) -> None:
        count, ticks = self.count_and_ticks()
        payload = struct.pack("<BIH", value, count & 0xFFFFFFFF, ticks)
        cs = (checksum(payload) + (1 if self.corrupt else 0)) & 0xFF
        os.write(self.master, header + bytes([len(payload)]) + payload + bytes([cs]))

    def _run(self) -> None:
        buf = b""
        while not self._closing.is_set():
            # Poll, so that close() can stop this thread before the descriptor is closed: a closed
            # number is soon reused by the next test's pty, which this thread would then answer.
            if not select.select([self.master], [], [], 0.02)[0]:
                continue
            try:
                data = os.read(self.master, 64)
            except OSError:
                return
            if time.monotonic() < self.boot_until:
                continue  # the handshake drops it (no 'N' is ever sent by the driver)
            buf += data
            while len(buf) >= 2:
                cmd, value = buf[0:1], buf[1]
                if cmd in (b"T", b"O") and value == ord("="):
                    need = 5 if cmd == b"T" else 7
                    if len(buf) < need:
                        break  # the firmware waits for the rest
                    self.commands.append(buf[:need])
                    if cmd == b"T":
                        self.top = struct.unpack("<H", buf[2:4])[0]
                        self.div_next = 8 if buf[4:5] == b"1" else 64
                    else:
                        self._reply(b"O", buf[6])
                    buf = buf[need:]
                    continue
                buf = buf[2:]
                if cmd == b"P":
                    self._reply(b"P", value)
                elif cmd == b"V":
                    self._reply(b"V", 14)
                elif cmd == b"N" and value == ord("?"):
                    os.write(self.master, name_reply(self.name))
                elif cmd == b"S":
                    self.commands.append(b"S" + bytes([value]))
                    if value in b"02":
                        self.pos, self.running = self._now_pos(), False
                        if value == ord("0"):
                            self.pos = 0.0
                    elif value == ord("1") and not self.running:
                        self.div = self.div_next
                        self.t_ref, self.running = time.monotonic(), True

    def close(self) -> None:
        self._closing.set()
        self._thread.join()
        os.close(self.master)
        os.close(self.slave)


def test_wire_facts() -> None:
    """117647 baud for "115200" at 16 MHz; CRC-8/Maxim's check value; a CRC below 16 is one hex
    character; the count has stepped only once TCNT1 has passed OCR1A (and its interrupt has run)."""
    assert uart_baud(115200) == pytest.approx(16e6 / 136)
    assert uart_baud(9600) == pytest.approx(16e6 / 8 / 208)
    assert uart_baud(57600) == pytest.approx(16e6 / 16 / 17)
    assert crc8_maxim(b"123456789") == 0xA1
    assert name_reply(b"cam00005") == b"cam000056"  # CRC 0x06
    assert name_reply(b"\xff" * 8) == b"\xff" * 8 + b"C9"
    late = -(-COUNT_LATE_CYCLES // 8)
    assert frames_started(7, 0, 3999, 8) == (7, 0)
    assert frames_started(7, OCR1A, 3999, 8) == (7, 0)  # the match flag rises as TCNT1 leaves 1000
    assert frames_started(8, OCR1A + 1, 3999, 8) == (7, -1)
    assert frames_started(8, OCR1A + late, 3999, 8) == (7, -1)
    assert frames_started(8, OCR1A + late + 1, 3999, 8) == (7, 1)


def test_strawlab_driver_and_shared_clock_model() -> None:
    box = _Box()
    try:
        with StrawlabTriggerbox(box.port, reset_wait_s=0) as tb:
            assert tb.version == 14 and tb.info()["name"] == "box-1"
            assert tb.info()["uart_baud"] == pytest.approx(117647.1)
            tb.stop_reset()
            assert tb.set_rate(100.0) == pytest.approx(100.0)
            tb.start()
            for _ in range(30):
                tb.query_clock()
                time.sleep(0.005)
            assert tb.model.fitted and abs(tb.model.gain - 1) < 0.05
            count, _ = tb.set_output(1, 1)
            assert count >= 1
            with pytest.raises(TriggerError, match="no pulse"):
                tb.pulse()
            tb.stop()
            r = tb.query_clock()
            assert r.running is False
        time.sleep(0.2)  # let the peer read the last commands
        assert box.commands[:2] == [b"S0", b"T=" + struct.pack("<H", 19999) + b"1"]
        assert b"S1" in box.commands and b"O=" + struct.pack("<HH", 0, 4095) in [c[:6] for c in box.commands]
        assert box.commands[-1] == b"S2"
    finally:
        box.close()


def test_samples_on_both_sides_of_the_count_step_lie_on_one_line() -> None:
    """At 400 fps (prescaler 8, TOP 4999) the count steps 20 % into each frame: samples before and after
    the step give the same line, with no sample a frame off, from the first fit on."""
    box = _Box()
    try:
        with StrawlabTriggerbox(box.port, reset_wait_s=0) as tb:
            tb.stop_reset()
            tb.set_rate(400.0)
            tb.start()
            readings = []
            t_end = time.monotonic() + 20.0
            while time.monotonic() < t_end and (len(readings) < 120 or sum(r.ticks <= OCR1A for r in readings) < 15):
                readings.append(tb.query_clock())
                time.sleep(0.0007)  # not a divisor of the 2.5 ms period: the phase walks through the frame
            assert tb.model.fitted
            off = [abs(tb.model.device_to_host(r.device_time_s) - 0.5 * (r.host_t0 + r.host_t1))
                   for r in readings if r.host_t1 - r.host_t0 < 0.001]
            early = sum(r.ticks <= OCR1A for r in readings)
            print(f"\n{len(readings)} samples, {early} before the count's step; worst offset from the line "
                  f"{max(off) * 1e3:.2f} ms over {len(off)} samples with round trips under 1 ms")
            assert early >= 15
            assert max(off) < 0.00125  # half a frame: a sample one frame off would be 2.5 ms off
    finally:
        box.close()


def test_set_output_reads_its_confirmation_even_when_the_count_is_80() -> None:
    """The 'O' reply carries the pulse count: at 80 (the letter P) a reply left waiting would be taken
    for the start of a clock reply. set_output reads it; later queries get their own replies."""
    box = _Box()
    try:
        with StrawlabTriggerbox(box.port, reset_wait_s=0) as tb:
            tb.set_rate(100.0)
            while not any(c[:2] == b"T=" for c in box.commands):  # the peer has the new TOP
                time.sleep(0.001)
            box.set_stopped_at(80, 5000)
            confirmed = tb.set_output(0, 1)
            readings = [tb.query_clock() for _ in range(20)]
            assert len(readings) == 20
            assert confirmed == (80, 5000) and tb.stats["stray_replies"] == 0
    finally:
        box.close()


def test_one_byte_too_many_costs_two_queries_at_most() -> None:
    """The box takes commands two bytes at a time: one byte too many shifts every later pair. The
    driver sends every other query after the second miss with a leading '?', which realigns it."""
    box = _Box()
    try:
        with StrawlabTriggerbox(box.port, reset_wait_s=0, timeout_s=0.1) as tb:
            tb.set_rate(100.0)
            tb.query_clock()
            tb._ser.write(b"x")
            results = []
            for _ in range(12):
                try:
                    tb.query_clock()
                    results.append(True)
                except TriggerError:
                    results.append(False)
            assert results[2:] == [True] * 10 and tb.stats["realigned"] >= 1, results
    finally:
        box.close()


def test_probes_wait_through_the_handshake() -> None:
    """A box that drops every byte for its first 2.5 s (its name handshake) is asked V? every second
    until it answers."""
    box = _Box(boot_s=2.5)
    try:
        t0 = time.monotonic()
        with StrawlabTriggerbox(box.port, reset_wait_s=0) as tb:
            assert tb.version == 14
            assert 2.0 < time.monotonic() - t0 < 6.0 and tb.stats["unanswered"] >= 2
    finally:
        box.close()


def test_bad_checksum_is_an_error() -> None:
    box = _Box(corrupt=True)
    try:
        with pytest.raises(TriggerError, match="strawlab.*bad checksum"):
            StrawlabTriggerbox(box.port, reset_wait_s=0, connect_timeout_s=1.0)
    finally:
        box.close()


def test_unplugged_box_is_a_trigger_error_not_a_traceback() -> None:
    box = _Box()
    try:
        tb = StrawlabTriggerbox(box.port, reset_wait_s=0)
        tb._ser.close()  # the board is unplugged: every write fails at the port
        with pytest.raises(TriggerError, match="cannot"):
            tb.set_output(0, 1)
        with pytest.raises(TriggerError, match="cannot"):
            tb.stop()
        tb.close()
    finally:
        box.close()


def test_a_run_waits_7_s_after_opening_a_strawlab_board(monkeypatch) -> None:
    """TriggerSession on a serial port (opening it resets the Nano): the driver is told to wait 7 s
    (its name handshake), then probes; on a pty (a simulated box, not reset by opening) it probes at
    once."""
    from flytrack_host.rig import TriggerConfig
    from flytrack_host.trigger import session, strawlab

    waits: dict[str, float] = {}

    class Box:
        def __init__(self, port: str, baud: int, reset_wait_s: float, model: object) -> None:
            waits[port] = reset_wait_s

    monkeypatch.setattr(strawlab, "StrawlabTriggerbox", Box)
    session.open_device(TriggerConfig(kind="strawlab", port="/dev/ttyUSB0"))
    session.open_device(TriggerConfig(kind="strawlab", port="/dev/pts/7"))
    assert waits == {"/dev/ttyUSB0": 7.0, "/dev/pts/7": 0.0}
