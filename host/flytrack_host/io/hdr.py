"""HdrHistogram's serialized form and its interval log (`.hlog`), as Braid's .braidz carries them
(`reconstruct_latency_usec.hlog`, `reprojection_distance_100x_pixels.hlog`, schema >= 2).

Written from the format's published layout (HdrHistogram "V2" encoding):
- payload: big-endian int32 cookie 0x1c849313 (V2 base 0x1c849303 | 0x10), int32 payload length,
  int32 normalizing index offset (0), int32 significant digits, int64 lowest and highest trackable values,
  float64 integer-to-double ratio
  (1.0), then the counts array as ZigZag LEB128 varints, a run of k > 1 zero counts written as -k;
- compressed: int32 cookie 0x1c849314, int32 length, then the payload deflated (zlib); base64 of that is
  the "HISTFAAA..." string;
- log: '#[...]' header lines, a CSV header, then one line per interval:
  start (s), length (s), max value / 1e6, base64 histogram.
The counts index of a value follows HdrHistogram's bucket / sub-bucket layout. `decode` reads it back.
"""

from __future__ import annotations

import base64
import math
import struct
import zlib

import numpy as np

# The V2 cookie bases with 0x10 set: the word-size bits that mark the ZigZag LEB128 count encoding.
V2_COOKIE = 0x1C849303 | 0x10
V2_COMPRESSED_COOKIE = 0x1C849304 | 0x10


class Histogram:
    """Integer values in [lowest, highest] with `digits` significant decimal digits, HdrHistogram-style."""

    def __init__(self, lowest: int = 1, highest: int = 3_600_000_000, digits: int = 3) -> None:
        if lowest < 1 or highest < 2 * lowest or not 0 <= digits <= 5:
            raise ValueError("need 1 <= lowest, highest >= 2 lowest and 0 <= digits <= 5")
        self.lowest, self.highest, self.digits = int(lowest), int(highest), int(digits)
        largest_single = 2 * 10**digits
        self.sub_bucket_count_magnitude = max(int(math.ceil(math.log2(largest_single))), 1)
        self.sub_bucket_half_count_magnitude = self.sub_bucket_count_magnitude - 1
        self.sub_bucket_count = 1 << self.sub_bucket_count_magnitude
        self.sub_bucket_half_count = self.sub_bucket_count // 2
        self.unit_magnitude = int(math.floor(math.log2(lowest)))
        self.sub_bucket_mask = (self.sub_bucket_count - 1) << self.unit_magnitude
        smallest_untrackable = self.sub_bucket_count << self.unit_magnitude
        buckets = 1
        while smallest_untrackable <= self.highest:
            smallest_untrackable <<= 1
            buckets += 1
        self.bucket_count = buckets
        self.counts = np.zeros((buckets + 1) * self.sub_bucket_half_count, dtype=np.int64)
        self.total = 0
        self.max_value = 0

    def _index(self, v: int) -> int:
        lzcb = 64 - self.unit_magnitude - self.sub_bucket_half_count_magnitude - 1
        b = lzcb - (64 - (v | self.sub_bucket_mask).bit_length())
        sb = v >> (b + self.unit_magnitude)
        return ((b + 1) << self.sub_bucket_half_count_magnitude) + (sb - self.sub_bucket_half_count)

    def record(self, values: np.ndarray) -> int:
        """Record values (rounded to integers, clipped to [0, highest]); NaN/negative ones are skipped.
        Returns how many were recorded."""
        v = np.asarray(values, dtype=np.float64)
        v = v[np.isfinite(v) & (v >= 0)]
        for x in np.minimum(np.round(v), self.highest).astype(np.int64).tolist():
            self.counts[self._index(int(x))] += 1
            self.max_value = max(self.max_value, int(x))
        self.total += int(v.size)
        return int(v.size)

    def encode(self) -> str:
        """The base64 compressed V2 form ("HISTF...")."""
        n = self._index(self.max_value) + 1 if self.total else 0
        body = bytearray()
        c = self.counts[:n].tolist()
        i = 0
        while i < n:
            if c[i] == 0:
                j = i
                while j < n and c[j] == 0:
                    j += 1
                body += _zigzag(-(j - i) if j - i > 1 else 0)
                i = j
            else:
                body += _zigzag(c[i])
                i += 1
        head = struct.pack(">iiiiqqd", V2_COOKIE, len(body), 0, self.digits, self.lowest, self.highest, 1.0)
        packed = zlib.compress(head + bytes(body))
        return base64.b64encode(struct.pack(">ii", V2_COMPRESSED_COOKIE, len(packed)) + packed).decode("ascii")


def _zigzag(n: int) -> bytes:
    z = (n << 1) ^ (n >> 63)
    z &= (1 << 64) - 1
    out = bytearray()
    for _ in range(8):
        if z < 0x80:
            out.append(z)
            return bytes(out)
        out.append((z & 0x7F) | 0x80)
        z >>= 7
    out.append(z & 0xFF)  # the 9th byte carries 8 bits
    return bytes(out)


def _unzigzag(buf: bytes, pos: int) -> tuple[int, int]:
    z, shift = 0, 0
    for k in range(9):
        b = buf[pos]
        pos += 1
        if k == 8:
            z |= b << shift
            break
        z |= (b & 0x7F) << shift
        shift += 7
        if b < 0x80:
            break
    return (z >> 1) ^ -(z & 1), pos


def decode(text: str) -> tuple[dict[str, int], np.ndarray]:
    """A base64 compressed V2 histogram -> (header fields, counts array)."""
    raw = base64.b64decode(text)
    cookie, length = struct.unpack(">ii", raw[:8])
    if cookie != V2_COMPRESSED_COOKIE:
        raise ValueError(f"not a compressed V2 HdrHistogram (cookie {cookie:#x})")
    payload = zlib.decompress(raw[8:8 + length])
    ck, plen, _, digits, lowest, highest, _ = struct.unpack(">iiiiqqd", payload[:40])
    if ck != V2_COOKIE:
        raise ValueError(f"not a V2 HdrHistogram payload (cookie {ck:#x})")
    counts: list[int] = []
    pos, end = 40, 40 + plen
    while pos < end:
        v, pos = _unzigzag(payload, pos)
        counts.extend([0] * -v if v < 0 else [v])
    return {"digits": digits, "lowest": lowest, "highest": highest}, np.asarray(counts, dtype=np.int64)


def hlog_text(h: Histogram, start_s: float, length_s: float, tag_comment: str = "") -> str:
    """An HdrHistogram interval log with one interval holding `h` (Braid writes one per recording)."""
    lines = ["#[Histogram log format version 1.3]",
             f"#[StartTime: {start_s:.3f} (seconds since epoch)]"]
    if tag_comment:
        lines.append(f"#[{tag_comment}]")
    lines.append('"StartTimestamp","Interval_Length","Interval_Max","Interval_Compressed_Histogram"')
    lines.append(f"0.000,{length_s:.3f},{h.max_value / 1e6:.3f},{h.encode()}")
    return "\n".join(lines) + "\n"
