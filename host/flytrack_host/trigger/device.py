"""Host driver of the FlyTrack trigger firmware (protocol/SPEC.md section 3) over a serial port.

The same driver talks to a board on /dev/ttyUSB0, to the firmware running in simavr (a pty) and to
the pure-Python SoftwareTrigger (a pty). A reader thread splits the byte stream into frames, hands
replies to the waiting request (matched by seq and message id), queues input events, and counts
what it had to drop (bad frames, stray replies). A clock thread can query the clock on a schedule
and feed the ClockModel.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import serial

from flytrack_host.protocol import trigger_link as tl
from flytrack_host.protocol.errors import ProtocolError
from flytrack_host.util import hostclock

from .clock_model import ClockModel, LinkTiming
from .common import PRESCALERS, ClockThread, RateChoice, SerialTrigger, TriggerError, choose_rate, open_serial

log = logging.getLogger(__name__)

# The firmware's time from a CLOCK_QUERY's last byte (its RX interrupt) to the clock sample: frame
# decode (COBS, CRC) and dispatch, measured in simavr on both MCUs (899 and 881 cycles at 16 MHz).
FIRMWARE_SAMPLE_DELAY_S = 56e-6
CONTROL_TIMEOUT_S = 2.0  # see TriggerDevice.control_timeout_s
FIRMWARE_BAUD = tl.BAUD  # the FlyTrack firmware's UART (protocol SPEC section 3)


def clock_link_timing(baudrate: float) -> LinkTiming:
    """Wire timing of a FlyTrack clock query: the request as TriggerDevice sends it (a leading
    delimiter, then the frame), the CLOCK reply's frame; sizes from the protocol's own encoder."""
    request = b"\0" + tl.encode_message(tl.ClockQuery(), 1)
    reply = tl.encode_message(tl.Clock(0, 0, 0, 0), 1)
    return LinkTiming.serial(baudrate, len(request), len(reply), FIRMWARE_SAMPLE_DELAY_S)

# What each request is answered with.
_REPLY_FOR: dict[type[tl.SerialMessage], type[tl.SerialMessage]] = {
    tl.GetInfo: tl.Info,
    tl.SetRate: tl.Rate,
    tl.Start: tl.Ack,
    tl.Stop: tl.Ack,
    tl.StopReset: tl.Ack,
    tl.ClockQuery: tl.Clock,
    tl.Pulse: tl.Ack,
    tl.SetOutput: tl.Ack,
    tl.SetName: tl.Ack,
}


@dataclass(frozen=True)
class ClockReading:
    host_t0: float
    host_t1: float
    frame_count: int  # trigger pulses started
    ticks: int
    top: int
    running: bool
    device_time_s: float  # seconds since frame 0 began


@dataclass(frozen=True)
class InputEvent:
    channel: int
    edge: int  # 0 falling, 1 rising
    frame: float  # fractional frame number (frame index + ticks / (TOP + 1))
    device_time_s: float
    host_time: float | None  # from the clock model, None before it has a fit


class TriggerDevice(SerialTrigger):
    """A FlyTrack trigger (firmware or simulator) on a serial port."""

    def __init__(
        self,
        port: str,
        baudrate: int = FIRMWARE_BAUD,
        reset_wait_s: float = 2.0,
        timeout_s: float = 0.5,
        model: ClockModel | None = None,
        connect_attempts: int = 3,
        wire_timed: bool = True,
    ) -> None:
        """wire_timed: the link carries bytes at `baudrate` (a board, the simavr harness), so the
        clock model places each clock sample from the wire times; False for a link that delivers
        at once (the SoftwareTrigger's pty): the model then takes the round trip's midpoint."""
        self.port = port
        self.timeout_s = timeout_s
        # Control requests (info, rate, start, stop, pulse, outputs) wait longer than clock queries: a
        # simulated box (simavr on a pty) on a loaded host missed 0.5 s for Start ("no reply to Start
        # from /dev/pts/0 within 0.5 s" ended fault-suite and closed-loop runs at load 10-13); a clock
        # query keeps `timeout_s` (a late one is useless to the clock model anyway).
        self.control_timeout_s = max(timeout_s, CONTROL_TIMEOUT_S)
        self.model = model or ClockModel()
        self.model.link = clock_link_timing(baudrate) if wire_timed else None
        self.stats = {"bad_frames": 0, "stray_replies": 0, "device_errors": 0, "events": 0}
        self._ser = open_serial(port, baudrate)
        self._lock = threading.Lock()  # one request at a time
        self._seq = 0
        self._pending: tuple[int, type[tl.SerialMessage], queue.Queue] | None = None
        self._events: queue.Queue[InputEvent] = queue.Queue()
        self._closed = threading.Event()
        self._clock_thread: ClockThread | None = None
        self.rate: RateChoice | None = None
        # An Arduino resets when the port opens (DTR) and its bootloader listens for ~1-2 s.
        if reset_wait_s > 0:
            time.sleep(reset_wait_s)
        self._ser.reset_input_buffer()
        self._reader = threading.Thread(target=self._read_loop, name=f"trigger-rx {port}", daemon=True)
        self._reader.start()
        self._info = self._handshake(connect_attempts)

    # ------------------------------------------------------------------ plumbing

    def _handshake(self, attempts: int) -> tl.Info:
        self._raw_seen = bytearray()
        for _ in range(attempts):
            try:
                # A leading delimiter ends whatever partial frame the device may hold.
                self._ser.write(b"\0")
                info = self._request(tl.GetInfo(), self.timeout_s)  # probing: retried, short
                assert isinstance(info, tl.Info)
                break
            except TriggerError:
                continue
        else:
            seen = bytes(self._raw_seen[:32])
            baud = self._ser.baudrate
            self.close()
            what = f"it sent {seen!r}" if seen else "it sent nothing"
            hint = "" if baud == FIRMWARE_BAUD else (
                f"; the port is at {baud} baud, the FlyTrack firmware talks at {FIRMWARE_BAUD} "
                "(rig file: drop trigger.baud, or set it to 1000000)")
            raise TriggerError(
                f"the device on {self.port} does not answer the FlyTrack trigger protocol ({what}); "
                f"is the right firmware flashed, and is nothing else using the port?{hint}"
            )
        if info.protocol_version != tl.SERIAL_VERSION:
            self.close()
            raise TriggerError(
                f"device speaks protocol version {info.protocol_version}, host speaks {tl.SERIAL_VERSION}")
        return info

    def _read_loop(self) -> None:
        splitter = tl.FrameSplitter()
        empty_reads = 0
        while not self._closed.is_set():
            try:
                data = self._ser.read(self._ser.in_waiting or 1)
                empty_reads = 0
            except serial.SerialException as exc:
                # A pty (simulator) can report readable with nothing to read while its other end is
                # between writes; only a long run of those means the device is gone.
                if "returned no data" in str(exc) and empty_reads < 2000:
                    empty_reads += 1
                    time.sleep(0.001)
                    continue
                if not self._closed.is_set():
                    log.error("trigger %s: serial port lost: %s", self.port, exc)
                break
            except (OSError, TypeError) as exc:
                if not self._closed.is_set():
                    log.error("trigger %s: serial port lost: %s", self.port, exc)
                break
            if not data:
                continue
            t_rx = hostclock.now()
            if len(getattr(self, "_raw_seen", b"")) < 64:
                self._raw_seen += data
            for frame in splitter.feed(data):
                try:
                    seq, msg = tl.decode_message(frame)
                except ProtocolError as exc:
                    self.stats["bad_frames"] += 1
                    log.debug("trigger %s: dropped frame: %s", self.port, exc)
                    continue
                self._dispatch(seq, msg, t_rx)

    def _dispatch(self, seq: int, msg: tl.SerialMessage, t_rx: float) -> None:
        if isinstance(msg, tl.Event):
            self.stats["events"] += 1
            self._events.put(self._make_event(msg))
            return
        pending = self._pending
        if pending is not None and seq == pending[0]:
            if isinstance(msg, (pending[1], tl.Error)):
                pending[2].put((msg, t_rx))
                return
        if isinstance(msg, tl.Error):
            self.stats["device_errors"] += 1
        self.stats["stray_replies"] += 1

    def _request(self, msg: tl.SerialMessage, timeout_s: float | None = None) -> tl.SerialMessage:
        return self._request_timed(msg, timeout_s or self.control_timeout_s)[0]

    def _request_timed(
        self, msg: tl.SerialMessage, timeout_s: float | None = None, on_written: Callable[[], None] | None = None
    ) -> tuple[tl.SerialMessage, float, float]:
        if self._closed.is_set():
            raise TriggerError(f"trigger on {self.port} is closed")
        with self._lock:
            self._seq = self._seq % 255 + 1  # 1..255: 0 is what unattributable errors carry
            box: queue.Queue = queue.Queue()
            self._pending = (self._seq, _REPLY_FOR[type(msg)], box)
            # The leading delimiter closes any partial frame left in the device (line noise, a
            # host that died mid-write): this request then always starts a fresh frame.
            wire = b"\0" + tl.encode_message(msg, self._seq)
            t0 = hostclock.now()
            try:
                self._ser.write(wire)
            except (serial.SerialException, OSError) as exc:
                raise TriggerError(f"cannot write to {self.port}: {exc}") from None
            if on_written is not None:
                on_written()
            try:
                reply, t1 = box.get(timeout=timeout_s or self.timeout_s)
            except queue.Empty:
                raise TriggerError(
                    f"no reply to {type(msg).__name__} from {self.port} within {timeout_s or self.timeout_s} s"
                ) from None
            finally:
                self._pending = None
        if isinstance(reply, tl.Error):
            try:
                name = tl.ErrorCode(reply.code).name
            except ValueError:
                name = f"code {reply.code}"
            raise TriggerError(f"device refused {type(msg).__name__}: {name}")
        return reply, t0, t1

    # ------------------------------------------------------------------ requests

    def info(self) -> tl.Info:
        info = self._request(tl.GetInfo())
        assert isinstance(info, tl.Info)
        self._info = info
        return info

    @property
    def f_cpu(self) -> int:
        return self._info.f_cpu

    def set_rate(self, fps: float) -> float:
        """Sets the frame rate closest to `fps` (device must be stopped); returns the exact rate."""
        choice = choose_rate(fps, self.f_cpu)
        reply = self._request(tl.SetRate(choice.prescaler_code, choice.top))
        assert isinstance(reply, tl.Rate)
        self.rate = RateChoice(reply.prescaler_code, reply.top, reply.f_cpu)
        self.model.frame_period_s = self.rate.period_s
        return self.rate.fps

    def start(self) -> None:
        self._request(tl.Start())

    def stop(self) -> None:
        self._request(tl.Stop())

    def stop_reset(self) -> None:
        self._request(tl.StopReset())
        self.model.reset()

    def _tick_s(self, top: int | None = None) -> float:
        if self.rate is None:
            raise TriggerError("frame rate unknown: call set_rate() first")
        return self.rate.tick_s

    def query_clock(self) -> ClockReading:
        """One clock query; the sample also goes to the clock model."""
        reply, t0, t1 = self._request_timed(tl.ClockQuery())
        assert isinstance(reply, tl.Clock)
        tick = self._tick_s()
        dev_t = ((reply.frame_count - 1) * (reply.top + 1) + reply.ticks) * tick
        r = ClockReading(t0, t1, reply.frame_count, reply.ticks, reply.top, bool(reply.running), dev_t)
        if r.running:
            self.model.add_sample(t0, t1, dev_t)
        return r

    def pulse(self, channel: int = 0, frame: int | None = None, width_s: float = 0.001) -> int:
        """Pulses `channel` during frame `frame` (None: the earliest reachable frame) for width_s.

        Returns the width in timer ticks actually asked for."""
        if not width_s > 0:
            raise TriggerError(f"pulse width must be positive, got {width_s} s")
        width_ticks = max(1, round(width_s / self._tick_s()))
        if width_ticks > 0xFFFF:
            raise TriggerError(f"pulse width {width_s} s is longer than the timer can count")
        self._request(tl.Pulse(channel, tl.FRAME_NOW if frame is None else int(frame), width_ticks))
        return width_ticks

    def pulse_timed(self, channel: int, frame: int | None, width_s: float,
                    on_written: Callable[[], None] | None = None) -> tuple[float, float]:
        """As `pulse`, returning (host time the request was written, host time its ACK arrived);
        `on_written` is called as soon as the request has been written to the port."""
        if not width_s > 0:
            raise TriggerError(f"pulse width must be positive, got {width_s} s")
        width_ticks = max(1, min(0xFFFF, round(width_s / self._tick_s())))
        _, t0, t1 = self._request_timed(tl.Pulse(channel, tl.FRAME_NOW if frame is None else int(frame), width_ticks),
                                        on_written=on_written)
        return t0, t1

    def set_output(self, channel: int, level: int | bool) -> None:
        self._request(tl.SetOutput(channel, 1 if level else 0))

    def set_name(self, name: str) -> None:
        self._request(tl.SetName(name))

    def _make_event(self, ev: tl.Event) -> InputEvent:
        frame = float("nan")
        dev_t = float("nan")
        host_t = None
        if self.rate is not None:
            frame = (ev.frame_count - 1) + ev.ticks / (self.rate.top + 1)
            dev_t = frame * self.rate.period_s
            if self.model.fitted:
                host_t = self.model.device_to_host(dev_t)
        return InputEvent(ev.channel, ev.edge, frame, dev_t, host_t)

    def events(self) -> list[InputEvent]:
        """Input events received since the last call."""
        out = []
        while True:
            try:
                out.append(self._events.get_nowait())
            except queue.Empty:
                return out

    # ------------------------------------------------------------------ lifetime

    def close(self) -> None:
        self._closed.set()  # before the port closes: the reader thread then exits quietly
        super().close()


__all__ = ["TriggerDevice", "TriggerError", "ClockReading", "InputEvent", "PRESCALERS"]
