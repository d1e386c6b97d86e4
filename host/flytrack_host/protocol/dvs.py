"""DVS128 USB event words (protocol/SPEC.md §2): vectorised decoding with wrap/reset state, encoding.

A bulk packet is a plain run of 4-byte words: byte 0 = x << 1 | polarity, byte 1 = y | SYNC << 7,
bytes 2-3 = u16 LE with a 14-bit timestamp, bit 14 RESET and bit 15 WRAP. A SYNC word is an external-input
event (the bridge's sync input, wired to the trigger's frame output) at its timestamp, not an address event.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import ProtocolError

TS_BITS = 14
TS_MASK = (1 << TS_BITS) - 1
WRAP_US = 1 << TS_BITS  # 0x4000: what a WRAP word adds to the running offset
RESET_BIT = 0x4000  # in the u16 at bytes 2-3
WRAP_BIT = 0x8000
SYNC_BIT = 0x8000  # in the u16 at bytes 0-1 (byte 1, bit 7)
DVS_WIDTH = DVS_HEIGHT = 128

#: One address event, 16 bytes, the C struct ft_event of edge/events: t (us), x, y, p (1 = ON). The one event
#: layout of the project: the event-file readers (flytrack_host.dvs.events) and this decoder both give it.
EVENT_DTYPE = np.dtype({"names": ["t", "x", "y", "p"], "formats": ["<i8", "<u2", "<u2", "u1"],
                        "offsets": [0, 8, 10, 12], "itemsize": 16})
# Raw fields of every word (the canonical text of §5 lists these).
DVS_WORD_DTYPE = np.dtype(
    [("x", "u1"), ("y", "u1"), ("polarity", "u1"), ("reset", "u1"), ("wrap", "u1"), ("ts", "<u2"), ("sync", "u1")]
)


def _words(packet: bytes | bytearray | memoryview | np.ndarray) -> np.ndarray:
    """The u32 words of a packet, validated (TRUNCATED, BAD_FIELD) before anything is used."""
    raw = np.frombuffer(packet, np.uint8) if not isinstance(packet, np.ndarray) else packet.view(np.uint8)
    if raw.size % 4:
        raise ProtocolError("TRUNCATED", f"DVS packet of {raw.size} bytes is not a whole number of 4-byte words")
    w = raw.view("<u4")
    hi = w >> 16
    both = (hi & (RESET_BIT | WRAP_BIT)) == (RESET_BIT | WRAP_BIT)
    if both.any():
        raise ProtocolError("BAD_FIELD", f"DVS word {int(np.argmax(both))} has both RESET and WRAP set")
    special_sync = ((w & SYNC_BIT) != 0) & ((hi & (RESET_BIT | WRAP_BIT)) != 0)
    if special_sync.any():
        i = int(np.argmax(special_sync))
        raise ProtocolError("BAD_FIELD", f"DVS word {i} has SYNC (byte 1, bit 7) set on a RESET or WRAP word")
    return w


class DvsDecoder:
    """Turns packets into events with 64-bit microsecond times: t = offset + ts14.

    `offset` grows by 0x4000 on each WRAP word and returns to 0 on a RESET word; it carries over from
    one packet to the next. A rejected packet leaves the state untouched.
    """

    def __init__(self, offset: int = 0) -> None:
        self.offset = offset
        self.events_decoded = 0
        self.sync_decoded = 0

    def reset(self) -> None:
        self.offset = 0

    def decode(self, packet: bytes | bytearray | memoryview) -> np.ndarray:
        """The address events of a packet (SYNC words are skipped: see decode_with_sync)."""
        return self.decode_with_sync(packet)[0]

    def decode_with_sync(self, packet: bytes | bytearray | memoryview) -> tuple[np.ndarray, np.ndarray]:
        """(address events, t_us of the SYNC words as uint64), both in stream order."""
        w = _words(packet)
        n = w.size
        if n == 0:
            return np.zeros(0, EVENT_DTYPE), np.zeros(0, np.uint64)
        hi = (w >> 16).astype(np.uint32)
        is_reset = (hi & RESET_BIT) != 0
        is_wrap = (hi & WRAP_BIT) != 0
        cw = np.cumsum(is_wrap, dtype=np.uint64)  # wraps up to and including each word
        idx = np.arange(n)
        last_reset = np.maximum.accumulate(np.where(is_reset, idx, -1))
        since_reset = cw - cw[np.maximum(last_reset, 0)]  # a RESET word is never also a WRAP
        offs = np.where(
            last_reset >= 0, since_reset * np.uint64(WRAP_US), np.uint64(self.offset) + cw * np.uint64(WRAP_US)
        )
        timed = ~(is_reset | is_wrap)
        is_sync = timed & ((w & SYNC_BIT) != 0)
        ev = timed & ~is_sync
        we = w[ev]
        out = np.empty(int(ev.sum()), EVENT_DTYPE)
        out["x"] = (we >> 1) & 0x7F
        out["y"] = (we >> 8) & 0x7F
        out["p"] = we & 1
        out["t"] = offs[ev] + ((we >> 16) & TS_MASK)
        sync_t = (offs[is_sync] + ((w[is_sync] >> 16) & TS_MASK)).astype(np.uint64)
        self.offset = int(offs[-1])
        self.events_decoded += out.size
        self.sync_decoded += sync_t.size
        return out, sync_t


@dataclass(frozen=True, eq=False)
class DvsPacket:
    """The raw words of one packet (DVS_WORD_DTYPE), for the golden vectors and exact re-encoding."""

    words: np.ndarray

    def __eq__(self, other: object) -> bool:
        return isinstance(other, DvsPacket) and self.words.tobytes() == other.words.tobytes()

    __hash__ = None  # type: ignore[assignment]


def decode_dvs_words(packet: bytes | bytearray | memoryview) -> DvsPacket:
    w = _words(packet)
    out = np.empty(w.size, DVS_WORD_DTYPE)
    out["x"] = (w >> 1) & 0x7F
    out["polarity"] = w & 1
    out["y"] = (w >> 8) & 0x7F
    hi = w >> 16
    out["ts"] = hi & TS_MASK
    out["reset"] = (hi & RESET_BIT) != 0
    out["wrap"] = (hi & WRAP_BIT) != 0
    out["sync"] = (w & SYNC_BIT) != 0
    return DvsPacket(out)


def encode_dvs_words(packet: DvsPacket) -> bytes:
    wd = packet.words
    limits = (("x", 127), ("y", 127), ("polarity", 1), ("reset", 1), ("wrap", 1), ("ts", TS_MASK), ("sync", 1))
    for name, top in limits:
        if np.any(wd[name] > top):
            raise ProtocolError("BAD_FIELD", f"DVS word field {name} above {top}")
    if np.any(wd["reset"] & wd["wrap"]):
        raise ProtocolError("BAD_FIELD", "DVS word with both RESET and WRAP")
    if np.any(wd["sync"] & (wd["reset"] | wd["wrap"])):
        raise ProtocolError("BAD_FIELD", "DVS word with SYNC on a RESET or WRAP word")
    w = (
        (wd["x"].astype("<u4") << 1)
        | wd["polarity"].astype("<u4")
        | (wd["y"].astype("<u4") << 8)
        | (wd["sync"].astype("<u4") << 15)
        | (wd["ts"].astype("<u4") << 16)
        | (wd["reset"].astype("<u4") << 30)
        | (wd["wrap"].astype("<u4") << 31)
    )
    return w.astype("<u4").tobytes()


class DvsEncoder:
    """Events -> words, inserting WRAP words as the times pass 0x4000 boundaries (for tests and simulators).

    `offset` mirrors the DvsDecoder's running offset (a multiple of 0x4000).
    """

    def __init__(self, offset: int = 0) -> None:
        self.offset = offset

    def encode(self, x: np.ndarray, y: np.ndarray, polarity: np.ndarray, t_us: np.ndarray) -> bytes:
        x, y, p = (np.asarray(a, np.int64) for a in (x, y, polarity))
        t = np.asarray(t_us, np.uint64)
        n = t.size
        if not (x.size == y.size == p.size == n):
            raise ValueError("x, y, polarity and t_us must have one entry per event")
        if n == 0:
            return b""
        if np.any((x < 0) | (x > 127) | (y < 0) | (y > 127) | (p < 0) | (p > 1)):
            raise ProtocolError("BAD_FIELD", "x and y must be in 0..127, polarity in 0..1")
        if t[0] < self.offset or np.any(np.diff(t.astype(np.int64)) < 0):
            raise ValueError("event times must be non-decreasing and not before the running offset")
        k = (t // np.uint64(WRAP_US)).astype(np.int64)
        wraps = np.diff(k, prepend=self.offset // WRAP_US)  # WRAP words needed before each event
        pos = np.arange(n) + np.cumsum(wraps)
        out = np.full(n + int(wraps.sum()), WRAP_BIT << 16, "<u4")
        ts = (t - k.astype(np.uint64) * np.uint64(WRAP_US)).astype(np.uint32)
        out[pos] = (x << 1 | p | y << 8).astype(np.uint32) | (ts << np.uint32(16))
        self.offset = int(k[-1]) * WRAP_US
        return out.tobytes()


def encode_events(x, y, polarity, t_us, offset: int = 0) -> bytes:
    """Words for events (times non-decreasing, >= offset) starting from a decoder at `offset`."""
    return DvsEncoder(offset).encode(x, y, polarity, t_us)


def dvs_event_times(packet: DvsPacket, offset: int = 0) -> np.ndarray:
    """t_us of each word as a fresh DvsDecoder at `offset` assigns it (address events and SYNC words; -1 for
    RESET and WRAP words)."""
    dec = DvsDecoder(offset)
    ev, sync_t = dec.decode_with_sync(encode_dvs_words(packet))
    wd = packet.words
    timed = ~(wd["reset"].astype(bool) | wd["wrap"].astype(bool))
    is_sync = timed & wd["sync"].astype(bool)
    out = np.full(wd.size, -1, np.int64)
    out[timed & ~is_sync] = ev["t"]
    out[is_sync] = sync_t.astype(np.int64)
    return out
