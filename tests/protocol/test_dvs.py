"""DVS128 USB word decoding (SPEC §2) and the canonical text helpers."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from flytrack_host.protocol import EVENT_DTYPE, DvsDecoder, ProtocolError, encode_events, fmt_f32
from flytrack_host.protocol.text import decode_text, encode_text, escape_text


def word(x: int, y: int, p: int, ts: int, reset: int = 0, wrap: int = 0) -> bytes:
    return bytes([(x << 1) | p, y]) + struct.pack("<H", ts | reset << 14 | wrap << 15)


def test_decode_by_hand() -> None:
    dec = DvsDecoder()
    ev = dec.decode(word(5, 6, 1, 100) + word(0, 0, 0, 0, wrap=1) + word(7, 8, 0, 3))
    assert ev.dtype == EVENT_DTYPE
    assert ev.tolist() == [(100, 5, 6, 1), (0x4000 + 3, 7, 8, 0)]  # (t, x, y, p)
    assert dec.offset == 0x4000
    # state carries to the next packet; RESET returns the offset to 0
    ev = dec.decode(word(1, 1, 1, 9) + word(0, 0, 0, 0, reset=1) + word(2, 2, 0, 4))
    assert ev["t"].tolist() == [0x4000 + 9, 4]
    assert dec.offset == 0


def test_rejected_packet_leaves_state() -> None:
    dec = DvsDecoder()
    dec.decode(word(0, 0, 0, 0, wrap=1))
    for bad, name in ((word(0, 0, 0, 0, wrap=1) + b"\x00", "TRUNCATED"),
                      (word(0, 0, 0, 0, wrap=1) + word(0, 0, 0, 0, reset=1, wrap=1), "BAD_FIELD"),
                      (word(0, 0x80, 0, 0, wrap=1), "BAD_FIELD"),  # SYNC on a WRAP word
                      (word(0, 0x80, 0, 0, reset=1), "BAD_FIELD")):  # fmt: skip
        with pytest.raises(ProtocolError) as e:
            dec.decode(bad)
        assert e.value.name == name
    assert dec.offset == 0x4000


def test_sync_words() -> None:
    """SYNC (byte 1 bit 7, the bridge's external input) is a timed word, not an address event."""
    dec = DvsDecoder()
    pkt = word(5, 6, 1, 100) + word(0, 0x80, 0, 120) + word(0, 0, 0, 0, wrap=1) + word(0, 0x80, 0, 7) + word(7, 8, 0, 9)
    ev, sync = dec.decode_with_sync(pkt)
    assert ev.tolist() == [(100, 5, 6, 1), (0x4000 + 9, 7, 8, 0)]  # (t, x, y, p)
    assert sync.tolist() == [120, 0x4000 + 7]
    assert dec.sync_decoded == 2 and dec.events_decoded == 2
    assert DvsDecoder().decode(pkt).tolist() == ev.tolist()  # decode() leaves them out


def test_encode_events_inserts_wraps() -> None:
    t = np.array([1, 0x4000 * 5 + 2])
    b = encode_events([1, 2], [3, 4], [1, 0], t)
    assert len(b) == 4 * (2 + 5)
    assert DvsDecoder().decode(b)["t"].tolist() == t.tolist()
    with pytest.raises(ValueError):
        encode_events([1, 2], [3, 4], [1, 0], [5, 4])  # times going backwards


def test_text_field_rules() -> None:
    assert decode_text(b"abc\0\0\0", "f") == "abc"
    assert decode_text(b"abcdef", "f") == "abcdef"  # a full field has no NUL
    with pytest.raises(ProtocolError) as e:
        decode_text(b"ab\0c\0\0", "f")
    assert e.value.name == "BAD_FIELD"
    raw = b"\xff\xfeok"  # not UTF-8: kept exactly
    assert encode_text(decode_text(raw + b"\0", "f"), 5, "f") == raw + b"\0"
    assert escape_text("a b\\c=\t\u00e9") == "a\\x20b\\x5cc=\\x09\\xc3\\xa9"


def test_f32_text() -> None:
    assert fmt_f32(0.1) == "0.100000001"
    assert fmt_f32(float("-nan")) == "nan"
    assert fmt_f32(float("-inf")) == "-inf"
    assert fmt_f32(1e-45) == "1.40129846e-45"
