"""Unit tests of the trigger serial link codec (SPEC §3)."""

from __future__ import annotations

import struct

import pytest

from flytrack_host.protocol.errors import ProtocolError
from flytrack_host.protocol.trigger_link import (
    SERIAL_MESSAGE_TYPES,
    Ack,
    Clock,
    ClockQuery,
    Error,
    Event,
    FrameSplitter,
    GetInfo,
    Info,
    Pulse,
    Rate,
    SetName,
    SetOutput,
    SetRate,
    Start,
    Stop,
    StopReset,
    cobs_decode,
    cobs_encode,
    crc16_ccitt_false,
    decode_frame,
    decode_message,
    encode_frame,
    encode_message,
)


def test_crc_check_value() -> None:
    assert crc16_ccitt_false(b"123456789") == 0x29B1
    assert crc16_ccitt_false(b"") == 0xFFFF


# Examples worked by hand from the COBS definition (code byte = distance to the next zero).
@pytest.mark.parametrize(
    ("raw", "enc"),
    [
        (b"", b"\x01"),
        (b"\x00", b"\x01\x01"),
        (b"\x00\x00", b"\x01\x01\x01"),
        (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
        (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
        (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
        (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255)) + b"\x01"),
        (bytes(range(0, 255)), b"\x01\xff" + bytes(range(1, 255)) + b"\x01"),
    ],
)
def test_cobs_known(raw: bytes, enc: bytes) -> None:
    assert cobs_encode(raw) == enc
    assert cobs_decode(enc) == raw


@pytest.mark.parametrize("bad", [b"\x05\x11\x22", b"\x03\x11\x00\x01", b"\x00", b"\x02\x11\x00"])
def test_cobs_bad(bad: bytes) -> None:
    with pytest.raises(ProtocolError) as e:
        cobs_decode(bad)
    assert e.value.name == "BAD_COBS"


def _body(msg_id: int, seq: int, payload: bytes, magic: int = 0x46, version: int = 2) -> bytes:
    b = bytes((magic, version, msg_id, seq)) + payload
    return b + struct.pack("<H", crc16_ccitt_false(b))


def test_frame_layout_independent() -> None:
    # SET_RATE prescaler 3, top 12499, seq 9: built by hand, compared with the codec.
    body = b"\x46\x02\x02\x09" + struct.pack("<BH", 3, 12499)
    body += struct.pack("<H", crc16_ccitt_false(body))
    wire = encode_message(SetRate(3, 12499), 9)
    assert wire[-1] == 0 and 0 not in wire[:-1]
    assert cobs_decode(wire[:-1]) == body
    assert decode_frame(wire[:-1]) == (2, 9, struct.pack("<BH", 3, 12499))


@pytest.mark.parametrize(
    ("body", "name"),
    [
        (b"\x46\x01\x01", "TRUNCATED"),
        (b"", "TRUNCATED"),
        (_body(1, 0, b"")[:-1] + b"\x00", "BAD_CRC"),
        (_body(1, 0, b"", magic=0x47), "BAD_MAGIC"),
        (_body(1, 0, b"", version=1), "BAD_VERSION"),
        (_body(1, 0, b"", version=3), "BAD_VERSION"),
        (_body(0x42, 0, b""), "UNKNOWN_TYPE"),
        (_body(1, 0, b"\x00"), "LENGTH_MISMATCH"),
        (_body(2, 0, b"\x03\x00"), "LENGTH_MISMATCH"),
        (_body(2, 0, b"\x06\x00\x01"), "BAD_FIELD"),
        (_body(2, 0, b"\x00\x00\x01"), "BAD_FIELD"),
        (_body(8, 0, b"\x00\x02"), "BAD_FIELD"),
        (_body(0x85, 0, b"\x00\x02" + bytes(6)), "BAD_FIELD"),
        (_body(0x81, 0, b"\x01\x01\x00\x00\x03\x04" + bytes(22)), "BAD_FIELD"),
        (_body(9, 0, b"ab\x00c" + bytes(12)), "BAD_FIELD"),
    ],
)
def test_decode_errors(body: bytes, name: str) -> None:
    with pytest.raises(ProtocolError) as e:
        decode_message(cobs_encode(body))
    assert e.value.name == name


MESSAGES = [
    GetInfo(), SetRate(5, 65535), Start(), Stop(), StopReset(), ClockQuery(),
    Pulse(2, 0xFFFFFFFF, 100), SetOutput(1, 1), SetName("rig A"),
    Info(1, 0, 3, 1, 2, 4, 16_000_000, "trigger-box-0001"), Ack(7), Rate(16_000_000, 3, 2499),
    Clock(123456, 17, 2499, 1), Event(0, 1, 99, 2000), Error(3, 0x42),
]  # fmt: skip


def test_every_type_listed() -> None:
    assert {type(m) for m in MESSAGES} == set(SERIAL_MESSAGE_TYPES)


@pytest.mark.parametrize("msg", MESSAGES, ids=lambda m: type(m).__name__)
@pytest.mark.parametrize("seq", [0, 1, 255])
def test_roundtrip(msg, seq: int) -> None:
    wire = encode_message(msg, seq)
    assert wire.endswith(b"\0") and 0 not in wire[:-1]
    assert decode_message(wire[:-1]) == (seq, msg)


def test_encode_rejects_bad_values() -> None:
    for bad in (SetRate(0, 1), SetOutput(0, 2), SetName("x" * 17), SetName("a\0b"), Pulse(256, 0, 0)):
        with pytest.raises(ProtocolError):
            encode_message(bad, 0)
    with pytest.raises(ProtocolError):
        encode_frame(1, 0, bytes(60))


def test_rate_hz() -> None:
    assert Rate(16_000_000, 3, 2499).frame_rate_hz == pytest.approx(100.0)


def test_splitter_chunks_and_resync() -> None:
    a = encode_message(Ack(1), 1)
    b = encode_message(Clock(5, 6, 7, 1), 2)
    stream = b"\x13\x37garbage" + b"\0" + a + b"\0\0" + b
    sp = FrameSplitter()
    got: list[bytes] = []
    for i in range(0, len(stream), 3):  # arbitrary chunking
        got += sp.feed(stream[i : i + 3])
    assert got[0] == b"\x13\x37garbage"
    with pytest.raises(ProtocolError):
        decode_message(got[0])
    assert [decode_message(f) for f in got[1:]] == [(1, Ack(1)), (2, Clock(5, 6, 7, 1))]
    assert sp.pending == 0 and sp.dropped_too_long == 0


def test_splitter_drops_overlong() -> None:
    sp = FrameSplitter()
    a = encode_message(Ack(1), 1)
    out = sp.feed(b"\x01" * 100)
    out += sp.feed(b"\x01" * 100 + b"\0" + a)
    assert out == [a[:-1]]
    assert sp.dropped_too_long == 1
    # exactly at the limit is kept
    assert sp.feed(b"\x02" * sp.max_frame_len + b"\0") == [b"\x02" * sp.max_frame_len]
    assert sp.dropped_too_long == 1
