"""UDP codec, common part (protocol/SPEC.md §1): the header, message types, the record checks and
the UdpMessage base every message family builds on.

Record arrays are checked with vectorised bit tests on their f32 words, so the cost per datagram
does not grow with a Python loop over records.
"""

from __future__ import annotations

import struct
from dataclasses import fields
from enum import IntEnum
from typing import Any, ClassVar

import numpy as np

from .errors import ProtocolError

MAGIC = b"FT"
UDP_VERSION = 2  # SPEC §4: 2 since DVS_CLUSTERS carries covariance and a trigger-frame stamp
HEADER = struct.Struct("<2sBBHH")  # magic, version, type, length, flags
HEADER_SIZE = HEADER.size
MAX_DATAGRAM = 1472  # Ethernet MTU less IPv4 and UDP headers


class MsgType(IntEnum):
    FEATURES = 0x01
    STATUS = 0x02
    CONTROL = 0x03
    CONTROL_ACK = 0x04
    IMAGE = 0x05
    DVS_CLUSTERS = 0x10
    DVS_WINGBEAT = 0x11
    LIVE_ESTIMATES = 0x20


MAX_PARTS = 255

_EXP = np.uint32(0x7F800000)
_MANT = np.uint32(0x007FFFFF)


def _f32_words(dtype: np.dtype, allow_nan: tuple[str, ...] = ()) -> tuple[list[int], list[int]]:
    """Word columns (4-byte units) of a record's f32 values: (no NaN allowed, NaN allowed)."""
    strict: list[int] = []
    nan_ok: list[int] = []
    for name in dtype.names:
        sub, off = dtype.fields[name][:2]
        base = sub.base if sub.subdtype else sub
        if base != np.dtype("<f4"):
            continue
        cols = [off // 4 + k for k in range(int(np.prod(sub.shape)) if sub.shape else 1)]
        (nan_ok if name in allow_nan else strict).extend(cols)
    return strict, nan_ok


def _check_finite_records(buf: Any, offset: int, count: int, dtype: np.dtype, cols: tuple, what: str) -> None:
    """NOT_FINITE if an f32 record field is inf (anywhere) or NaN (where not allowed): bit tests on words."""
    if count == 0:
        return
    strict, nan_ok = cols
    f = np.frombuffer(buf, "<f4", count * dtype.itemsize // 4, offset)
    # The common case on the per-datagram path: no word of any record has an all-ones exponent (read
    # as float32, every word is finite), so no float is NaN or inf (one pass, no column gathers);
    # otherwise the column checks below decide.
    if np.isfinite(f).all():
        return
    words = f.view("<u4").reshape(count, -1)
    if strict:
        w = words[:, strict]
        bad = (w & _EXP) == _EXP
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise ProtocolError("NOT_FINITE", f"{what}[{i}] has a NaN or infinite {_col_name(dtype, strict[j])}")
    if nan_ok:
        w = words[:, nan_ok]
        bad = ((w & _EXP) == _EXP) & ((w & _MANT) == 0)
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise ProtocolError("NOT_FINITE", f"{what}[{i}] has an infinite {_col_name(dtype, nan_ok[j])}")


def _col_name(dtype: np.dtype, col: int) -> str:
    best = ""
    for name in dtype.names:
        if dtype.fields[name][1] <= col * 4:
            best = name
    return best


# ---------------------------------------------------------------- message base


# Field kinds in _FIELDS: "u" int, "e" enum (checked), "f" f32 finite, "d" f64 finite, "s" text,
# "n" record count (derived from the record array), "x" reserved (written 0, ignored).
FieldSpec = tuple[str, str, str]


class UdpMessage:
    """Base of the UDP message dataclasses. Subclasses describe their fixed part in _FIELDS."""

    TYPE: ClassVar[MsgType]
    _FIELDS: ClassVar[tuple[FieldSpec, ...]]
    _FLAG_MASK: ClassVar[int] = 0  # defined flag bits; others are ignored on reading
    _ENUMS: ClassVar[dict[str, type[IntEnum]]] = {}
    _ARRAY: ClassVar[str | None] = None  # name of the record-array field
    _DTYPE: ClassVar[np.dtype | None] = None
    _MAX: ClassVar[int] = 0
    _NAN_OK: ClassVar[tuple[str, ...]] = ()
    # derived by _finish_layout
    _STRUCT: ClassVar[struct.Struct]
    _NAMES: ClassVar[tuple[str, ...]]  # value names in struct order (no reserved)
    _COLS: ClassVar[tuple]

    @property
    def fixed_size(self) -> int:
        return self._STRUCT.size

    def header_flags(self) -> int:
        return int(getattr(self, "flags", 0)) & self._FLAG_MASK

    # -- equality: arrays compare bit for bit (NaN payloads included), f32 fields as the float32 sent
    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        f32 = {name for name, _, kind in self._FIELDS if kind == "f"}
        for f in fields(self):  # type: ignore[arg-type]
            a, b = getattr(self, f.name), getattr(other, f.name)
            if f.name in f32:
                if np.float32(a).tobytes() != np.float32(b).tobytes():
                    return False
            elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                a, b = np.asarray(a), np.asarray(b)
                if a.dtype != b.dtype or a.shape != b.shape or a.tobytes() != b.tobytes():
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]

    def _records(self) -> Any:
        return getattr(self, self._ARRAY) if self._ARRAY else None

    def _record_bytes(self) -> bytes:
        recs = self._records()
        if self._DTYPE is None:
            return bytes(recs)
        arr = np.asarray(recs)
        if arr.dtype != self._DTYPE:
            raise ProtocolError("BAD_FIELD", f"{self._ARRAY} must have dtype {self._ARRAY.upper()}_DTYPE")
        if "reserved" in self._DTYPE.names and np.any(arr["reserved"]):
            arr = arr.copy()
            arr["reserved"] = 0  # reserved fields are written as zero
        return np.ascontiguousarray(arr.reshape(-1)).tobytes()

    def _count(self) -> int:
        recs = self._records()
        return len(recs) if recs is not None else 0


def _finish_layout(cls: type[UdpMessage]) -> type[UdpMessage]:
    cls._STRUCT = struct.Struct("<" + "".join(code for _, code, _ in cls._FIELDS))
    cls._NAMES = tuple(name for name, _, kind in cls._FIELDS if kind != "x")
    if cls._DTYPE is not None:
        cls._COLS = _f32_words(cls._DTYPE, cls._NAN_OK)
    _BY_TYPE[int(cls.TYPE)] = cls
    return cls


_BY_TYPE: dict[int, type[UdpMessage]] = {}


def _empty(dtype: np.dtype) -> np.ndarray:
    return np.zeros(0, dtype)
