"""SoftwareTrigger: a pure-Python stand-in for the trigger firmware, for machines without the AVR
tools (avr-gcc, simavr) or without a board.

It opens a pseudo-terminal and speaks the same FlyTrack serial protocol (protocol/SPEC.md section 3)
as the firmware, so TriggerDevice drives it unchanged. Frame timing comes from the host's monotonic
clock (there is no hardware timer, hence no real trigger edges: jitter is the OS's). Pulses are
recorded in `pulses`, outputs in `outputs`; `inject_event()` stands in for the event input pin.
"""

from __future__ import annotations

import os
import threading
import time
import tty

from flytrack_host.protocol import trigger_link as tl
from flytrack_host.protocol.errors import ProtocolError

from .common import PRESCALERS

_ERR_FOR = {
    "BAD_CRC": tl.ErrorCode.BAD_CRC,
    "BAD_MAGIC": tl.ErrorCode.BAD_MAGIC,
    "BAD_VERSION": tl.ErrorCode.BAD_VERSION,
    "UNKNOWN_TYPE": tl.ErrorCode.UNKNOWN_TYPE,
    "LENGTH_MISMATCH": tl.ErrorCode.LENGTH_MISMATCH,
    "BAD_FIELD": tl.ErrorCode.BAD_ARG,
}


class SoftwareTrigger:
    """Serves the trigger protocol on a pty; `port` is the path to open."""

    def __init__(self, name: str = "software-trigger", f_cpu: int = 16_000_000) -> None:
        if len(name.encode("utf-8")) > 16:
            raise ValueError(f"trigger name {name!r} is longer than 16 bytes, the size of the INFO name field")
        self.f_cpu = f_cpu
        self.name = name
        # Guards running/_base_frames/_t_start together: a clock query racing a STOP must see
        # either the old run or the stopped state, never a mix (which would count frames twice).
        self._state_lock = threading.Lock()
        self.code, self.top = 2, 19999
        self.running = False
        self._base_frames = 0  # frames counted before the current run
        self._t_start = 0.0
        self.pulses: list[tuple[int, int]] = []  # (frame, width_ticks)
        self.outputs: dict[int, int] = {}
        self._event_seq = 0
        self._master, slave = os.openpty()
        tty.setraw(slave)
        self.port = os.ttyname(slave)
        self._slave = slave  # kept open so the pty survives between client opens
        self._stop = threading.Event()
        self._wlock = threading.Lock()
        self._thread = threading.Thread(target=self._serve, name="software-trigger", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ timing

    @property
    def _period_cycles(self) -> int:
        return (self.top + 1) * PRESCALERS[self.code]

    def _now_cycles(self) -> float:
        return (time.monotonic() - self._t_start) * self.f_cpu

    def clock(self) -> tuple[int, int]:
        """(frame_count, ticks) now, as the firmware reports them."""
        with self._state_lock:
            return self._clock_locked()

    def _clock_locked(self) -> tuple[int, int]:
        if not self.running:
            return self._base_frames, 0
        c = self._now_cycles()
        # The first frame begins one period after START, as on the chip.
        started = int(c // self._period_cycles)
        ticks = int((c % self._period_cycles) // PRESCALERS[self.code])
        return self._base_frames + started, min(ticks, self.top)

    # ------------------------------------------------------------------ serving

    def _send(self, msg: tl.SerialMessage, seq: int) -> None:
        with self._wlock:
            os.write(self._master, tl.encode_message(msg, seq))

    def inject_event(self, edge: int = 1, channel: int = 0) -> None:
        frames, ticks = self.clock()
        self._send(tl.Event(channel, edge, frames, ticks), self._event_seq)
        self._event_seq = (self._event_seq + 1) % 256

    def _serve(self) -> None:
        splitter = tl.FrameSplitter()
        while not self._stop.is_set():
            try:
                data = os.read(self._master, 256)
            except OSError:
                return
            too_long_before = splitter.dropped_too_long
            for frame in splitter.feed(data):
                self._on_frame(frame)
            if splitter.dropped_too_long > too_long_before:
                self._send(tl.Error(tl.ErrorCode.TOO_LONG, 0), 0)

    def _on_frame(self, frame: bytes) -> None:
        try:
            seq, msg = tl.decode_message(frame)
        except ProtocolError as exc:
            if exc.name in ("BAD_COBS", "TRUNCATED"):
                return  # cannot be attributed: dropped, as the firmware does
            try:
                body = tl.cobs_decode(frame)
                msg_id, seq = body[2], body[3]
            except (ProtocolError, IndexError):
                return
            self._send(tl.Error(_ERR_FOR.get(exc.name, tl.ErrorCode.BAD_ARG), msg_id), seq)
            return
        self._handle(seq, msg)

    def _ack(self, seq: int, msg: tl.SerialMessage) -> None:
        self._send(tl.Ack(int(msg.MSG_ID)), seq)

    def _err(self, seq: int, msg: tl.SerialMessage, code: tl.ErrorCode) -> None:
        self._send(tl.Error(code, int(msg.MSG_ID)), seq)

    def _handle(self, seq: int, msg: tl.SerialMessage) -> None:  # noqa: C901 - one branch per request
        if isinstance(msg, tl.GetInfo):
            self._send(tl.Info(tl.SERIAL_VERSION, 1, 0, 0, tl.Mcu.ATMEGA328P, 4, self.f_cpu, self.name), seq)
        elif isinstance(msg, tl.SetRate):
            if self.running:
                self._err(seq, msg, tl.ErrorCode.BUSY)
            elif msg.top < 15 or (msg.top + 1) * PRESCALERS[msg.prescaler_code] < 1600:
                self._err(seq, msg, tl.ErrorCode.BAD_ARG)
            else:
                self.code, self.top = msg.prescaler_code, msg.top
                self._send(tl.Rate(self.f_cpu, self.code, self.top), seq)
        elif isinstance(msg, tl.Start):
            with self._state_lock:
                if not self.running:
                    self._t_start = time.monotonic()
                    self.running = True
            self._ack(seq, msg)
        elif isinstance(msg, (tl.Stop, tl.StopReset)):
            with self._state_lock:
                if self.running:
                    self._base_frames = self._clock_locked()[0]
                    self.running = False
                if isinstance(msg, tl.StopReset):
                    self._base_frames = 0
            self._ack(seq, msg)
        elif isinstance(msg, tl.ClockQuery):
            frames, ticks = self.clock()
            self._send(tl.Clock(frames, ticks, self.top, int(self.running)), seq)
        elif isinstance(msg, tl.Pulse):
            frames, _ = self.clock()
            frame = frames + 1 if msg.frame == tl.FRAME_NOW else msg.frame
            if msg.channel != 0 or not 1 <= msg.width_ticks <= self.top // 2:
                self._err(seq, msg, tl.ErrorCode.BAD_ARG)
            elif not self.running:
                self._err(seq, msg, tl.ErrorCode.BUSY)
            elif frame < frames + 1:  # the frame has begun, or its arming point has passed
                self._err(seq, msg, tl.ErrorCode.BAD_ARG)
            else:
                self.pulses.append((frame, msg.width_ticks))
                self._ack(seq, msg)
        elif isinstance(msg, tl.SetOutput):
            if msg.channel >= 4:
                self._err(seq, msg, tl.ErrorCode.BAD_ARG)
            else:
                self.outputs[msg.channel] = msg.level
                self._ack(seq, msg)
        elif isinstance(msg, tl.SetName):
            self.name = msg.name
            self._ack(seq, msg)
        else:
            self._err(seq, msg, tl.ErrorCode.UNKNOWN_TYPE)

    def close(self) -> None:
        self._stop.set()
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass
        self._thread.join(timeout=2)

    def __enter__(self) -> SoftwareTrigger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
