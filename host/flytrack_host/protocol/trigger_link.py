"""Trigger serial link codec (protocol/SPEC.md §3): CRC-16, COBS, frames, typed messages, splitter.

A wire frame is `COBS(body) 0x00`; body = magic 'F', version, msg_id, seq, payload, CRC-16 (LE).
"""

from __future__ import annotations

import struct
from dataclasses import astuple, dataclass, fields
from enum import IntEnum
from typing import ClassVar

from .errors import ProtocolError
from .text import decode_text, encode_text

SERIAL_MAGIC = 0x46
SERIAL_VERSION = 2  # the SPEC's one PROTOCOL_VERSION
BAUD = 1_000_000  # SPEC section 3: the firmware's UART, exact at 16 MHz (firmware/avr_trigger/src/serial.c)
MAX_BODY = 64  # SPEC: the longest body
MIN_BODY = 6  # magic, version, msg_id, seq, CRC
# A COBS encoding of n bytes is at most n + ceil(n / 254) bytes: the longest legal frame before its delimiter.
MAX_WIRE_FRAME = MAX_BODY + 1
FRAME_NOW = 0xFFFFFFFF  # PULSE frame meaning "now"


class MsgId(IntEnum):
    GET_INFO = 0x01
    SET_RATE = 0x02
    START = 0x03
    STOP = 0x04
    STOP_RESET = 0x05
    CLOCK_QUERY = 0x06
    PULSE = 0x07
    SET_OUTPUT = 0x08
    SET_NAME = 0x09
    INFO = 0x81
    ACK = 0x82
    RATE = 0x83
    CLOCK = 0x84
    EVENT = 0x85
    ERROR = 0x86


class ErrorCode(IntEnum):
    BAD_CRC = 1
    BAD_COBS = 2
    UNKNOWN_TYPE = 3
    LENGTH_MISMATCH = 4
    BAD_ARG = 5
    BUSY = 6
    TOO_LONG = 7
    BAD_MAGIC = 8
    BAD_VERSION = 9


class Mcu(IntEnum):
    ATMEGA328P = 1
    ATMEGA32U4 = 2


# Prescaler code -> timer clock divisor (SPEC §3 timer terms).
PRESCALER_DIVISORS: dict[int, int] = {1: 1, 2: 8, 3: 64, 4: 256, 5: 1024}


# ---------------------------------------------------------------- CRC-16/CCITT-FALSE


def _crc_table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16_ccitt_false(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor ('123456789' -> 0x29B1)."""
    for b in data:
        crc = ((crc << 8) & 0xFFFF) ^ _CRC_TABLE[(crc >> 8) ^ b]
    return crc


# ---------------------------------------------------------------- COBS


def cobs_encode(data: bytes) -> bytes:
    """COBS-encode `data` (no delimiter is appended). The output contains no zero byte."""
    out = bytearray()
    for segment in bytes(data).split(b"\0"):
        # Each zero-free segment becomes blocks of at most 254 bytes; 0xFF blocks carry no implied zero.
        while len(segment) >= 254:
            out.append(0xFF)
            out += segment[:254]
            segment = segment[254:]
        out.append(len(segment) + 1)
        out += segment
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Decode one COBS frame (without its delimiter); BAD_COBS on a zero byte or a code past the end."""
    data = bytes(data)
    out = bytearray()
    i = 0
    n = len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise ProtocolError("BAD_COBS", f"zero byte inside a COBS frame at offset {i}")
        end = i + code
        if end > n:
            raise ProtocolError("BAD_COBS", f"COBS code {code} at offset {i} points past the frame end ({n})")
        block = data[i + 1 : end]
        if 0 in block:
            raise ProtocolError("BAD_COBS", f"zero byte inside a COBS frame at offset {i + 1 + block.index(0)}")
        out += block
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


# ---------------------------------------------------------------- frames


def encode_frame(msg_id: int, seq: int, payload: bytes) -> bytes:
    """Wire bytes of one frame: COBS(magic, version, msg_id, seq, payload, CRC) followed by 0x00."""
    if not 0 <= msg_id <= 0xFF or not 0 <= seq <= 0xFF:
        raise ProtocolError("BAD_FIELD", f"msg_id {msg_id} / seq {seq} must be bytes")
    body = bytes((SERIAL_MAGIC, SERIAL_VERSION, msg_id, seq)) + bytes(payload)
    if len(body) + 2 > MAX_BODY:
        raise ProtocolError("LENGTH_MISMATCH", f"body of {len(body) + 2} bytes exceeds {MAX_BODY}")
    body += struct.pack("<H", crc16_ccitt_false(body))
    return cobs_encode(body) + b"\0"


def decode_frame(frame: bytes) -> tuple[int, int, bytes]:
    """Check one frame (without its 0x00 delimiter) -> (msg_id, seq, payload).

    Checks in SPEC order: COBS, size, CRC, magic, version, msg_id known, payload size for the msg_id.
    """
    body = cobs_decode(frame)
    if len(body) < MIN_BODY:
        raise ProtocolError("TRUNCATED", f"frame body is {len(body)} bytes, at least {MIN_BODY} needed")
    (crc,) = struct.unpack_from("<H", body, len(body) - 2)
    calc = crc16_ccitt_false(body[:-2])
    if crc != calc:
        raise ProtocolError("BAD_CRC", f"CRC is 0x{crc:04X}, the body gives 0x{calc:04X}")
    if body[0] != SERIAL_MAGIC:
        raise ProtocolError("BAD_MAGIC", f"magic is 0x{body[0]:02X}, expected 0x{SERIAL_MAGIC:02X}")
    if body[1] != SERIAL_VERSION:
        raise ProtocolError("BAD_VERSION", f"serial protocol version {body[1]}, this reader speaks {SERIAL_VERSION}")
    msg_id, seq = body[2], body[3]
    cls = _BY_ID.get(msg_id)
    if cls is None:
        raise ProtocolError("UNKNOWN_TYPE", f"unknown serial msg_id 0x{msg_id:02X}")
    payload = body[4:-2]
    if len(payload) != cls._SIZE:
        raise ProtocolError(
            "LENGTH_MISMATCH",
            f"{cls.__name__} payload is {len(payload)} bytes, the msg_id fixes {cls._SIZE}",
        )
    return msg_id, seq, payload


# ---------------------------------------------------------------- typed messages


@dataclass(frozen=True)
class SerialMessage:
    """Base of the typed serial messages. Subclasses set MSG_ID and _FMT (struct, after the header)."""

    MSG_ID: ClassVar[int]
    _FMT: ClassVar[str] = "<"
    _SIZE: ClassVar[int] = 0
    _TEXT: ClassVar[dict[str, int]] = {}  # text field -> size
    _RANGES: ClassVar[dict[str, tuple[int, int]]] = {}  # field -> inclusive range checked on reading

    def payload(self) -> bytes:
        values = []
        for f in fields(self):
            v = getattr(self, f.name)
            values.append(encode_text(v, self._TEXT[f.name], f.name) if f.name in self._TEXT else int(v))
        self._check_ranges(values)
        try:
            return struct.pack(self._FMT, *values)
        except struct.error as exc:
            raise ProtocolError("BAD_FIELD", f"{type(self).__name__}: {exc}") from None

    @classmethod
    def _check_ranges(cls, values: list) -> None:
        for f, v in zip(fields(cls), values, strict=True):
            lo_hi = cls._RANGES.get(f.name)
            if lo_hi is not None and not lo_hi[0] <= v <= lo_hi[1]:
                raise ProtocolError("BAD_FIELD", f"{cls.__name__}.{f.name} = {v} is outside {lo_hi[0]}..{lo_hi[1]}")

    @classmethod
    def from_payload(cls, payload: bytes) -> SerialMessage:
        values = list(struct.unpack(cls._FMT, payload))
        cls._check_ranges(values)
        for i, f in enumerate(fields(cls)):
            if f.name in cls._TEXT:
                values[i] = decode_text(values[i], f.name)
        return cls(*values)

    def values(self) -> tuple:
        return astuple(self)

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))


_PRESCALER = (1, 5)


@dataclass(frozen=True)
class GetInfo(SerialMessage):
    MSG_ID: ClassVar[int] = MsgId.GET_INFO


@dataclass(frozen=True)
class SetRate(SerialMessage):
    MSG_ID: ClassVar[int] = MsgId.SET_RATE
    _FMT: ClassVar[str] = "<BH"
    _RANGES: ClassVar[dict[str, tuple[int, int]]] = {"prescaler_code": _PRESCALER}
    prescaler_code: int
    top: int


@dataclass(frozen=True)
class Start(SerialMessage):
    MSG_ID: ClassVar[int] = MsgId.START


@dataclass(frozen=True)
class Stop(SerialMessage):
    MSG_ID: ClassVar[int] = MsgId.STOP


@dataclass(frozen=True)
class StopReset(SerialMessage):
    MSG_ID: ClassVar[int] = MsgId.STOP_RESET


@dataclass(frozen=True)
class ClockQuery(SerialMessage):
    MSG_ID: ClassVar[int] = MsgId.CLOCK_QUERY


@dataclass(frozen=True)
class Pulse(SerialMessage):
    MSG_ID: ClassVar[int] = MsgId.PULSE
    _FMT: ClassVar[str] = "<BIH"
    channel: int
    frame: int  # FRAME_NOW = now
    width_ticks: int


@dataclass(frozen=True)
class SetOutput(SerialMessage):
    MSG_ID: ClassVar[int] = MsgId.SET_OUTPUT
    _FMT: ClassVar[str] = "<BB"
    _RANGES: ClassVar[dict[str, tuple[int, int]]] = {"level": (0, 1)}
    channel: int
    level: int


@dataclass(frozen=True)
class SetName(SerialMessage):
    MSG_ID: ClassVar[int] = MsgId.SET_NAME
    _FMT: ClassVar[str] = "<16s"
    _TEXT: ClassVar[dict[str, int]] = {"name": 16}
    name: str


@dataclass(frozen=True)
class Info(SerialMessage):
    MSG_ID: ClassVar[int] = MsgId.INFO
    _FMT: ClassVar[str] = "<6B2xI16s"  # 2x: u16 reserved, written 0, ignored
    _TEXT: ClassVar[dict[str, int]] = {"name": 16}
    _RANGES: ClassVar[dict[str, tuple[int, int]]] = {"mcu": (1, 2)}
    protocol_version: int
    fw_major: int
    fw_minor: int
    fw_patch: int
    mcu: int
    n_outputs: int
    f_cpu: int
    name: str


@dataclass(frozen=True)
class Ack(SerialMessage):
    MSG_ID: ClassVar[int] = MsgId.ACK
    _FMT: ClassVar[str] = "<B"
    acked_id: int


@dataclass(frozen=True)
class Rate(SerialMessage):
    MSG_ID: ClassVar[int] = MsgId.RATE
    _FMT: ClassVar[str] = "<IBH"
    _RANGES: ClassVar[dict[str, tuple[int, int]]] = {"prescaler_code": _PRESCALER}
    f_cpu: int
    prescaler_code: int
    top: int

    @property
    def frame_rate_hz(self) -> float:
        return self.f_cpu / ((self.top + 1) * PRESCALER_DIVISORS[self.prescaler_code])


@dataclass(frozen=True)
class Clock(SerialMessage):
    MSG_ID: ClassVar[int] = MsgId.CLOCK
    _FMT: ClassVar[str] = "<IHHB"
    frame_count: int
    ticks: int
    top: int
    running: int


@dataclass(frozen=True)
class Event(SerialMessage):
    MSG_ID: ClassVar[int] = MsgId.EVENT
    _FMT: ClassVar[str] = "<BBIH"
    _RANGES: ClassVar[dict[str, tuple[int, int]]] = {"edge": (0, 1)}
    channel: int
    edge: int  # 0 falling, 1 rising
    frame_count: int
    ticks: int


@dataclass(frozen=True)
class Error(SerialMessage):
    MSG_ID: ClassVar[int] = MsgId.ERROR
    _FMT: ClassVar[str] = "<BB"
    code: int  # ErrorCode; not range-checked on reading (SPEC lists no check)
    msg_id: int  # the request's id, 0 if unknown


SERIAL_MESSAGE_TYPES: tuple[type[SerialMessage], ...] = (
    GetInfo, SetRate, Start, Stop, StopReset, ClockQuery, Pulse, SetOutput, SetName,
    Info, Ack, Rate, Clock, Event, Error,
)  # fmt: skip
for _cls in SERIAL_MESSAGE_TYPES:
    _cls._SIZE = struct.calcsize(_cls._FMT)
_BY_ID: dict[int, type[SerialMessage]] = {int(c.MSG_ID): c for c in SERIAL_MESSAGE_TYPES}


def encode_message(msg: SerialMessage, seq: int) -> bytes:
    """Wire bytes (incl. the trailing 0x00) of a typed message."""
    return encode_frame(int(msg.MSG_ID), seq, msg.payload())


def decode_message(frame: bytes) -> tuple[int, SerialMessage]:
    """One frame (without delimiter) -> (seq, typed message); raises ProtocolError."""
    msg_id, seq, payload = decode_frame(frame)
    return seq, _BY_ID[msg_id].from_payload(payload)


# ---------------------------------------------------------------- stream splitting


class FrameSplitter:
    """Cuts a byte stream into frames at 0x00 delimiters.

    A frame longer than `max_frame_len` before its delimiter is dropped whole (counted in
    `dropped_too_long`); empty frames (repeated delimiters) are skipped. Garbage ends at the next
    delimiter, so the splitter is back in step after it: the caller's decode_frame rejects the
    garbage frame itself.
    """

    def __init__(self, max_frame_len: int = MAX_WIRE_FRAME) -> None:
        self.max_frame_len = max_frame_len
        self.dropped_too_long = 0
        self.frames = 0
        self._buf = bytearray()
        self._overlong = False

    def feed(self, data: bytes) -> list[bytes]:
        out: list[bytes] = []
        pieces = bytes(data).split(b"\0")
        for k, piece in enumerate(pieces):
            if not self._overlong:
                self._buf += piece
                if len(self._buf) > self.max_frame_len:
                    self._overlong = True
                    self._buf.clear()
            if k == len(pieces) - 1:
                break  # no delimiter after this piece yet
            if self._overlong:
                self.dropped_too_long += 1
                self._overlong = False
            elif self._buf:
                out.append(bytes(self._buf))
                self.frames += 1
            self._buf.clear()
        return out

    @property
    def pending(self) -> int:
        """Bytes held waiting for a delimiter."""
        return len(self._buf)

    def reset(self) -> None:
        self._buf.clear()
        self._overlong = False
