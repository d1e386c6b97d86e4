"""StrawlabTriggerbox against a pty peer that speaks the triggerbox protocol (MISSION.md)."""

from __future__ import annotations

import os
import select
import struct
import threading
import time
import tty

import pytest

from flytrack_host.trigger.common import TriggerError
from flytrack_host.trigger.strawlab import StrawlabTriggerbox, checksum


class _Box:
    """Answers like the triggerbox firmware, frame count from the host clock."""

    def __init__(self, corrupt: bool = False, early_lag: float = 0.0) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.port = os.ttyname(self.slave)
        self.corrupt = corrupt
        # Real boards: a query in the first `early_lag` of a frame finds the timer wrapped but the pulse
        # count not yet incremented.
        self.early_lag = early_lag
        self.lagged = 0
        self.commands: list[bytes] = []
        self.icr, self.div, self.running, self.t0 = 19999, 8, False, 0.0
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _reply(self, header: bytes, payload: bytes) -> None:
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
                buf += os.read(self.master, 64)
            except OSError:
                return
            while len(buf) >= 2:
                c = buf[:2]
                if c == b"V?":
                    self._reply(b"V", b"\x02")
                    buf = buf[2:]
                elif c == b"N?":
                    self._reply(b"N", b"box-1\0\0\0")
                    buf = buf[2:]
                elif c[:1] == b"P":
                    cyc = (time.monotonic() - self.t0) * 16e6 if self.running else 0
                    per = (self.icr + 1) * self.div
                    count, ticks = int(cyc // per), int(cyc % per) // self.div
                    if self.running and count > 0 and ticks < self.early_lag * (self.icr + 1):
                        count -= 1
                        self.lagged += 1
                    self._reply(b"P", struct.pack("<BIH", c[1], count, ticks))
                    buf = buf[2:]
                elif c[:1] == b"S":
                    self.running = c == b"S1"
                    self.t0 = time.monotonic()
                    self.commands.append(c)
                    buf = buf[2:]
                elif c == b"T=":
                    if len(buf) < 5:
                        break
                    self.icr = struct.unpack("<H", buf[2:4])[0]
                    self.div = 8 if buf[4:5] == b"1" else 64
                    self.commands.append(buf[:5])
                    buf = buf[5:]
                elif c == b"O=":
                    if len(buf) < 7:
                        break
                    self.commands.append(buf[:7])
                    buf = buf[7:]
                else:
                    buf = buf[1:]

    def close(self) -> None:
        self._closing.set()
        self._thread.join()
        os.close(self.master)
        os.close(self.slave)


def test_strawlab_driver_and_shared_clock_model() -> None:
    box = _Box()
    try:
        with StrawlabTriggerbox(box.port, reset_wait_s=0) as tb:
            assert tb.version == 2 and tb.info()["name"] == "box-1"
            assert tb.set_rate(100.0) == pytest.approx(100.0)
            tb.start()
            for _ in range(30):
                tb.query_clock()
                time.sleep(0.005)
            assert tb.model.fitted and abs(tb.model.gain - 1) < 0.05
            tb.set_output(1, 1)
            with pytest.raises(TriggerError, match="no pulse"):
                tb.pulse()
            tb.stop()
        time.sleep(0.2)  # let the peer read the last commands
        assert box.commands[0] == b"T=" + struct.pack("<H", 19999) + b"1"
        assert b"S1" in box.commands and b"O=" + struct.pack("<HHB", 0, 0xFFFF, 3) in box.commands
    finally:
        box.close()


def test_early_frame_samples_are_corrected() -> None:
    """Samples in the first 10 % of a frame come one count short; the driver puts them back."""
    box = _Box(early_lag=0.10)
    try:
        with StrawlabTriggerbox(box.port, reset_wait_s=0) as tb:
            tb.set_rate(100.0)
            tb.start()
            readings = []
            t_end = time.monotonic() + 20.0
            while (box.lagged < 8 or len(readings) < 120) and time.monotonic() < t_end:
                readings.append(tb.query_clock())
                time.sleep(0.0017)  # not a divisor of the 10 ms period: the phase walks through the frame
            assert box.lagged >= 8, "the peer never answered early in a frame"
            assert tb.early_corrected + tb.early_skipped >= box.lagged - 1
            assert tb.model.fitted
            # Every used sample lies on the model's line (a lagged one would be 10 ms off).
            off = [abs(tb.model.device_to_host(r.device_time_s) - 0.5 * (r.host_t0 + r.host_t1))
                   for r in readings[10:] if r.host_t1 - r.host_t0 < 0.003]
            print(f"\nlagged {box.lagged}, corrected {tb.early_corrected}, skipped {tb.early_skipped}, "
                  f"worst offset {max(off) * 1e3:.2f} ms over {len(off)} samples")
            assert max(off) < 0.004
            tb.stop()
    finally:
        box.close()


def test_bad_checksum_is_an_error() -> None:
    box = _Box(corrupt=True)
    try:
        with pytest.raises(TriggerError, match="strawlab"):
            StrawlabTriggerbox(box.port, reset_wait_s=0, timeout_s=0.2)
    finally:
        box.close()


def test_unplugged_box_is_a_trigger_error_not_a_traceback() -> None:
    box = _Box()
    try:
        tb = StrawlabTriggerbox(box.port, reset_wait_s=0)
        tb._ser.close()  # the board is unplugged: every write fails at the port
        with pytest.raises(TriggerError, match="cannot write"):
            tb.set_output(0, 1)
        with pytest.raises(TriggerError, match="cannot write"):
            tb.stop()
        tb.close()
    finally:
        box.close()
