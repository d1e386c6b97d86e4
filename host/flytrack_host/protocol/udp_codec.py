"""UDP codec, datagram level (protocol/SPEC.md §1): decode_datagram and encode for every message
type, and the splitting of FEATURES and LIVE_ESTIMATES over several datagrams.

Record arrays are decoded with one `np.frombuffer` on a little-endian structured dtype.
"""

from __future__ import annotations

import math
import struct
from dataclasses import fields, replace

import numpy as np

from .errors import ProtocolError
from .text import decode_text, encode_text
from .udp_eventcam import DvsClusters, _check_dvs_clusters
from .udp_frame import _SPLIT, FEATURES_MAX_POINTS, FeatureFlags, FeatureFrame, ImageChunk, _check_image
from .udp_header import _BY_TYPE, HEADER, HEADER_SIZE, MAGIC, MAX_PARTS, UDP_VERSION, UdpMessage, _check_finite_records
from .udp_live import LIVE_MAX_OBJECTS, LiveEstimates, LiveFlags

# Registration order of the families above is import order; list the types by type code as before.
UDP_MESSAGE_TYPES: tuple[type[UdpMessage], ...] = tuple(sorted(_BY_TYPE.values(), key=lambda c: int(c.TYPE)))


# ---------------------------------------------------------------- decoding

# Per message type, what the decoder walks its fields for, listed once (field order kept, so the
# first error found is the same): the count field, the float fields, the enum and text fields.
_LAYOUT: dict[type, tuple[str | None, tuple[str, ...], tuple[tuple[str, str], ...]]] = {}


def _layout(cls: type[UdpMessage]) -> tuple[str | None, tuple[str, ...], tuple[tuple[str, str], ...]]:
    lay = _LAYOUT.get(cls)
    if lay is None:
        count_name = next((nm for nm, _, kind in cls._FIELDS if kind == "n"), None)
        floats = tuple(nm for nm, _, kind in cls._FIELDS if kind in "fd")
        checked = tuple((nm, kind) for nm, _, kind in cls._FIELDS if kind in ("e", "s"))
        lay = _LAYOUT[cls] = (count_name, floats, checked)
    return lay


_FIELD_NAMES: dict[type, frozenset[str] | None] = {}


def _message(cls: type[UdpMessage], vals: dict) -> UdpMessage:
    """`cls(**vals)`; when `vals` gives every field (as decoding does), the instance's fields are set in
    one step: a frozen dataclass's __init__ sets each through object.__setattr__ (a third of a FEATURES
    datagram's decoding on the host's tracking thread). The messages have no __post_init__."""
    if cls not in _FIELD_NAMES:
        _FIELD_NAMES[cls] = None if hasattr(cls, "__post_init__") else frozenset(f.name for f in fields(cls))
    names = _FIELD_NAMES[cls]
    if names is None or len(vals) != len(names) or vals.keys() != names:
        return cls(**vals)
    msg = object.__new__(cls)
    msg.__dict__.update(vals)
    return msg


def decode_datagram(buf: bytes | bytearray | memoryview) -> UdpMessage:
    """One UDP datagram -> its message; raises ProtocolError with the first SPEC error that applies.

    Order: TRUNCATED (header), BAD_MAGIC, BAD_VERSION, UNKNOWN_TYPE, TRUNCATED (fixed part),
    LENGTH_MISMATCH (header length vs bytes, fixed size), COUNT_OVERFLOW (count vs limit and payload),
    LENGTH_MISMATCH (bytes after the records), NOT_FINITE, BAD_FIELD.
    """
    if not isinstance(buf, bytes):
        buf = bytes(buf)  # decoded arrays view the buffer: never alias memory the caller may reuse
    n = len(buf)
    if n < HEADER_SIZE:
        raise ProtocolError("TRUNCATED", f"datagram of {n} bytes is shorter than the {HEADER_SIZE}-byte header")
    magic, version, mtype, length, flags = HEADER.unpack_from(buf)
    if magic != MAGIC:
        raise ProtocolError("BAD_MAGIC", f"magic is {magic.hex()}, expected 4654 ('FT')")
    if version != UDP_VERSION:
        raise ProtocolError("BAD_VERSION", f"protocol version {version}, this reader speaks {UDP_VERSION}")
    cls = _BY_TYPE.get(mtype)
    if cls is None:
        raise ProtocolError("UNKNOWN_TYPE", f"unknown message type 0x{mtype:02X}")
    name = cls.__name__
    payload = n - HEADER_SIZE
    fixed = cls._STRUCT.size
    if payload < fixed:
        raise ProtocolError("TRUNCATED", f"{name}: {payload} payload bytes, the fixed part is {fixed}")
    if length != payload:
        raise ProtocolError("LENGTH_MISMATCH", f"{name}: header length {length}, {payload} payload bytes received")
    vals = dict(zip(cls._NAMES, cls._STRUCT.unpack_from(buf, HEADER_SIZE), strict=True))

    rec_off = HEADER_SIZE + fixed
    count = 0
    count_name, floats, checked = _layout(cls)
    if count_name is None:
        if payload != fixed:
            raise ProtocolError("LENGTH_MISMATCH", f"{name}: {payload} payload bytes, the type fixes {fixed}")
    else:
        count = vals.pop(count_name)
        rec_size = cls._DTYPE.itemsize if cls._DTYPE is not None else 1
        if count > cls._MAX:
            raise ProtocolError("COUNT_OVERFLOW", f"{name}: {count_name} = {count}, at most {cls._MAX}")
        need = fixed + count * rec_size
        if need > payload:
            raise ProtocolError(
                "COUNT_OVERFLOW", f"{name}: {count_name} = {count} needs {need} payload bytes, {payload} received"
            )
        if cls is FeatureFrame and not flags & _SPLIT and count > vals["total_points"]:
            raise ProtocolError(
                "COUNT_OVERFLOW", f"FeatureFrame: n_points {count} > total_points {vals['total_points']}"
            )
        if need != payload:
            raise ProtocolError(
                "LENGTH_MISMATCH", f"{name}: {payload - need} bytes after the {count} records of {count_name}"
            )

    # NOT_FINITE: fixed floats, then records
    for nm in floats:
        if not math.isfinite(vals[nm]):
            raise ProtocolError("NOT_FINITE", f"{name}.{nm} is {vals[nm]}")
    if cls._DTYPE is not None:
        _check_finite_records(buf, rec_off, count, cls._DTYPE, cls._COLS, f"{name}.{cls._ARRAY}")

    # BAD_FIELD: enums, texts, cross-field rules
    for nm, kind in checked:
        if kind == "e":
            enum = cls._ENUMS[nm]
            try:
                vals[nm] = enum(vals[nm])
            except ValueError:
                raise ProtocolError("BAD_FIELD", f"{name}.{nm} = {vals[nm]} is not a {enum.__name__}") from None
        elif kind == "s":
            vals[nm] = decode_text(vals[nm], f"{name}.{nm}")
    if "part_count" in vals:
        if vals["part_count"] < 1:
            raise ProtocolError("BAD_FIELD", f"{name}: part_count is 0")
        if vals["part_index"] >= vals["part_count"]:
            raise ProtocolError(
                "BAD_FIELD", f"{name}: part_index {vals['part_index']} >= part_count {vals['part_count']}"
            )
    if cls is ImageChunk:
        _check_image(vals, count)
    elif cls is DvsClusters:
        _check_dvs_clusters(vals, flags, buf, rec_off, count)

    if cls._ARRAY is not None:
        if cls._DTYPE is None:
            vals[cls._ARRAY] = buf[rec_off : rec_off + count]
        else:
            vals[cls._ARRAY] = np.frombuffer(buf, cls._DTYPE, count, rec_off)
    if cls._FLAG_MASK:
        vals["flags"] = flags & cls._FLAG_MASK
    return _message(cls, vals)


# ---------------------------------------------------------------- encoding


def encode(msg: UdpMessage) -> bytes:
    """One datagram for `msg`, exactly as given (a FeatureFrame must hold at most 32 points).

    The result is checked by decode_datagram, so nothing a reader would reject is ever sent.
    """
    cls = type(msg)
    if cls not in _BY_TYPE.values():
        raise TypeError(f"not a UDP message: {cls.__name__}")
    values = []
    for nm, code, kind in cls._FIELDS:
        if kind == "x":
            continue
        if kind == "n":
            values.append(msg._count())
        elif kind == "s":
            values.append(encode_text(getattr(msg, nm), int(code[:-1]), f"{cls.__name__}.{nm}"))
        elif kind in "fd":
            values.append(float(getattr(msg, nm)))
        else:
            values.append(int(getattr(msg, nm)))
    if cls._ARRAY is not None and msg._count() > cls._MAX:
        raise ProtocolError(
            "COUNT_OVERFLOW", f"{cls.__name__}: {msg._count()} {cls._ARRAY}, at most {cls._MAX} per datagram"
        )
    try:
        body = cls._STRUCT.pack(*values)
    except (struct.error, OverflowError) as exc:
        raise ProtocolError("BAD_FIELD", f"{cls.__name__}: a field is out of range ({exc})") from None
    if cls._ARRAY is not None:
        body += msg._record_bytes()
    out = HEADER.pack(MAGIC, UDP_VERSION, int(cls.TYPE), len(body), msg.header_flags()) + body
    decode_datagram(out)  # same rules as every reader
    return out


def encode_features(frame: FeatureFrame, truncate: bool = False) -> list[bytes]:
    """The datagrams of one camera frame holding all of `frame.points`.

    Up to 32 points: one datagram. More: SPLIT over ceil(n / 32) datagrams (seq + 0, + 1, ...), or with
    truncate=True one datagram with the 32 strongest points by peak_diff (kept in their original
    order) and TRUNCATED set. TRUNCATED is also set whenever total_points exceeds the points sent.
    """
    pts = np.asarray(frame.points)
    n = len(pts)
    total = frame.total_points
    if total < n:
        raise ProtocolError("COUNT_OVERFLOW", f"total_points {total} < the {n} points of the frame")
    flags = frame.flags & ~(FeatureFlags.SPLIT | FeatureFlags.TRUNCATED)
    if n <= FEATURES_MAX_POINTS or truncate:
        if n > FEATURES_MAX_POINTS:
            keep = np.sort(np.argsort(-pts["peak_diff"], kind="stable")[:FEATURES_MAX_POINTS])
            pts = pts[keep]
        if total > len(pts):
            flags |= FeatureFlags.TRUNCATED
        return [encode(replace(frame, points=pts, flags=int(flags), part_index=0, part_count=1))]
    parts = -(-n // FEATURES_MAX_POINTS)
    if parts > MAX_PARTS:
        raise ProtocolError("COUNT_OVERFLOW", f"{n} points need {parts} datagrams, at most {MAX_PARTS}")
    flags |= FeatureFlags.SPLIT
    if total > n:
        flags |= FeatureFlags.TRUNCATED
    return [
        encode(
            replace(
                frame,
                seq=(frame.seq + i) & 0xFFFFFFFF,
                points=pts[i * FEATURES_MAX_POINTS : (i + 1) * FEATURES_MAX_POINTS],
                flags=int(flags),
                part_index=i,
                part_count=parts,
            )
        )
        for i in range(parts)
    ]


def encode_live_estimates(est: LiveEstimates) -> list[bytes]:
    """The datagrams of one tracked frame: up to 27 objects in one, more SPLIT over several (seq + i)."""
    objs = np.asarray(est.objects)
    if len(objs) <= LIVE_MAX_OBJECTS:
        return [encode(replace(est, part_index=0, part_count=1, flags=est.flags & ~LiveFlags.SPLIT))]
    parts = -(-len(objs) // LIVE_MAX_OBJECTS)
    if parts > MAX_PARTS:
        raise ProtocolError("COUNT_OVERFLOW", f"{len(objs)} objects need {parts} datagrams, at most {MAX_PARTS}")
    return [
        encode(
            replace(
                est,
                seq=(est.seq + i) & 0xFFFFFFFF,
                part_index=i,
                part_count=parts,
                flags=int(est.flags | LiveFlags.SPLIT),
                objects=objs[i * LIVE_MAX_OBJECTS : (i + 1) * LIVE_MAX_OBJECTS],
            )
        )
        for i in range(parts)
    ]
