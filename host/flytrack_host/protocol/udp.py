"""UDP datagram codec (protocol/SPEC.md §1): edge <-> host and host -> stimulus programs.

Record arrays (feature points, clusters, wing edges, live objects) are decoded with one
`np.frombuffer` on a little-endian structured dtype and checked with vectorised bit tests, so the
cost per datagram does not grow with a Python loop over records.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field, fields, replace
from enum import IntEnum, IntFlag
from typing import Any, ClassVar

import numpy as np

from .errors import ProtocolError
from .text import decode_text, encode_text

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


class FeatureFlags(IntFlag):
    SPLIT = 0x1
    TRUNCATED = 0x2


class LiveFlags(IntFlag):
    SPLIT = 0x1


class DvsFlags(IntFlag):
    SYNCED = 0x1  # DVS_CLUSTERS: trigger_frame and frame_period_us are valid


class PixelFormat(IntEnum):
    MONO8 = 0
    MONO16 = 1
    YUYV = 2


class CameraState(IntEnum):
    IDLE = 0
    RUNNING = 1
    ERROR = 2
    STOPPED = 3


class Command(IntEnum):
    SET_PARAM = 1
    TAKE_BACKGROUND = 2
    SEND_FULL_IMAGE = 3
    SEND_REGIONS = 4
    START = 5
    STOP = 6


class AckStatus(IntEnum):
    OK = 0
    UNKNOWN_COMMAND = 1
    UNKNOWN_PARAM = 2
    BAD_VALUE = 3
    FAILED = 4


class ImageKind(IntEnum):
    FULL_FRAME = 0
    REGION = 1


CAMERA_ANY = 0xFFFF  # CONTROL camera_index: whatever camera the edge serves

# ---------------------------------------------------------------- record dtypes (explicit offsets, LE)

POINT_DTYPE = np.dtype(
    {
        "names": ["x_dist", "y_dist", "x_undist", "y_undist", "area", "peak_diff", "orientation",
                  "eccentricity", "cur_val", "reserved", "mean_val", "sumsq_val"],
        "formats": ["<f4"] * 8 + ["<u2", "<u2", "<f4", "<f4"],
        "offsets": [0, 4, 8, 12, 16, 20, 24, 28, 32, 34, 36, 40],
        "itemsize": 44,
    }
)  # fmt: skip
CLUSTER_DTYPE = np.dtype(
    {
        "names": ["id", "x", "y", "vx", "vy", "size", "mass", "var_x", "var_y", "cov_xy"],
        "formats": ["<u4"] + ["<f4"] * 9,
        "offsets": [0, 4, 8, 12, 16, 20, 24, 28, 32, 36],
        "itemsize": 40,
    }
)
WINGEDGE_DTYPE = np.dtype(
    {
        "names": ["edge_id", "reserved", "angle", "amplitude", "frequency", "phase"],
        "formats": ["u1", ("u1", (3,)), "<f4", "<f4", "<f4", "<f4"],
        "offsets": [0, 1, 4, 8, 12, 16],
        "itemsize": 20,
    }
)
OBJECT_DTYPE = np.dtype(
    {
        "names": ["obj_id", "x", "y", "z", "vx", "vy", "vz", "cov"],
        "formats": ["<u4"] + ["<f4"] * 6 + [("<f4", (6,))],
        "offsets": [0, 4, 8, 12, 16, 20, 24, 28],
        "itemsize": 52,
    }
)

FEATURES_MAX_POINTS = (MAX_DATAGRAM - HEADER_SIZE - 56) // POINT_DTYPE.itemsize  # 32
CLUSTERS_MAX = (MAX_DATAGRAM - HEADER_SIZE - 48) // CLUSTER_DTYPE.itemsize  # 35
WINGEDGES_MAX = 8
LIVE_MAX_OBJECTS = 27
IMAGE_MAX_CHUNK = MAX_DATAGRAM - HEADER_SIZE - 36  # 1428
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
    words = np.frombuffer(buf, "<u4", count * dtype.itemsize // 4, offset).reshape(count, -1)
    # The common case on the per-datagram path: no word of any record has an all-ones exponent, so
    # no float is NaN or inf (one pass, no column gathers); otherwise the column checks below decide.
    if not ((words & _EXP) == _EXP).any():
        return
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


# ---------------------------------------------------------------- messages


@_finish_layout
@dataclass(frozen=True, eq=False)
class FeatureFrame(UdpMessage):
    """FEATURES (0x01): one datagram of a camera frame's feature points."""

    TYPE: ClassVar[MsgType] = MsgType.FEATURES
    _FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        ("camera_index", "H", "u"), ("n_points", "H", "n"), ("seq", "I", "u"), ("camera_frame", "Q", "u"),
        ("trigger_frame", "q", "u"), ("device_timestamp_ns", "Q", "u"), ("edge_recv_ns", "Q", "u"),
        ("edge_done_ns", "Q", "u"), ("total_points", "H", "u"), ("part_index", "B", "u"),
        ("part_count", "B", "u"), ("reserved", "4x", "x"),
    )  # fmt: skip
    _FLAG_MASK: ClassVar[int] = int(FeatureFlags.SPLIT | FeatureFlags.TRUNCATED)
    _ARRAY: ClassVar[str | None] = "points"
    _DTYPE: ClassVar[np.dtype | None] = POINT_DTYPE
    _MAX: ClassVar[int] = FEATURES_MAX_POINTS
    _NAN_OK: ClassVar[tuple[str, ...]] = ("orientation", "eccentricity")

    camera_index: int
    seq: int
    camera_frame: int
    trigger_frame: int = -1
    device_timestamp_ns: int = 0
    edge_recv_ns: int = 0
    edge_done_ns: int = 0
    total_points: int = 0
    part_index: int = 0
    part_count: int = 1
    flags: int = 0
    points: np.ndarray = field(default_factory=lambda: _empty(POINT_DTYPE))

    @property
    def n_points(self) -> int:
        return len(self.points)

    @property
    def split(self) -> bool:
        return bool(self.flags & FeatureFlags.SPLIT)

    @property
    def truncated(self) -> bool:
        return bool(self.flags & FeatureFlags.TRUNCATED)


@_finish_layout
@dataclass(frozen=True, eq=False)
class EdgeStatus(UdpMessage):
    """STATUS (0x02): the edge's heartbeat, once a second."""

    TYPE: ClassVar[MsgType] = MsgType.STATUS
    _FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        ("camera_index", "H", "u"), ("width", "H", "u"), ("height", "H", "u"), ("pixel_format", "B", "e"),
        ("state", "B", "e"), ("seq", "I", "u"), ("last_error_code", "I", "u"), ("frames_seen", "Q", "u"),
        ("frames_dropped", "Q", "u"), ("fps", "f", "f"), ("proc_us_mean", "f", "f"),
        ("proc_us_max", "f", "f"), ("reserved", "4x", "x"), ("camera_name", "32s", "s"),
        ("last_error", "64s", "s"),
    )  # fmt: skip
    _ENUMS: ClassVar[dict[str, type[IntEnum]]] = {"pixel_format": PixelFormat, "state": CameraState}

    camera_index: int
    width: int
    height: int
    pixel_format: int
    state: int
    seq: int
    last_error_code: int = 0
    frames_seen: int = 0
    frames_dropped: int = 0
    fps: float = 0.0
    proc_us_mean: float = 0.0
    proc_us_max: float = 0.0
    camera_name: str = ""
    last_error: str = ""


@_finish_layout
@dataclass(frozen=True, eq=False)
class Control(UdpMessage):
    """CONTROL (0x03): host -> edge command, answered by CONTROL_ACK."""

    TYPE: ClassVar[MsgType] = MsgType.CONTROL
    _FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        ("request_id", "I", "u"), ("camera_index", "H", "u"), ("command", "B", "e"), ("reserved", "x", "x"),
        ("param", "24s", "s"), ("value", "d", "d"),
    )  # fmt: skip
    _ENUMS: ClassVar[dict[str, type[IntEnum]]] = {"command": Command}

    request_id: int
    camera_index: int
    command: int
    param: str = ""
    value: float = 0.0


@_finish_layout
@dataclass(frozen=True, eq=False)
class ControlAck(UdpMessage):
    """CONTROL_ACK (0x04). `command` is echoed as received, so it is not range-checked."""

    TYPE: ClassVar[MsgType] = MsgType.CONTROL_ACK
    _FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        ("request_id", "I", "u"), ("camera_index", "H", "u"), ("command", "B", "u"), ("status", "B", "e"),
        ("message", "48s", "s"),
    )  # fmt: skip
    _ENUMS: ClassVar[dict[str, type[IntEnum]]] = {"status": AckStatus}

    request_id: int
    camera_index: int
    command: int
    status: int
    message: str = ""


@_finish_layout
@dataclass(frozen=True, eq=False)
class ImageChunk(UdpMessage):
    """IMAGE (0x05): one chunk of a full frame or a region; `data` is the chunk's pixel bytes."""

    TYPE: ClassVar[MsgType] = MsgType.IMAGE
    _FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        ("camera_index", "H", "u"), ("kind", "B", "e"), ("bytes_per_pixel", "B", "u"), ("image_id", "I", "u"),
        ("camera_frame", "Q", "u"), ("x0", "H", "u"), ("y0", "H", "u"), ("width", "H", "u"),
        ("height", "H", "u"), ("offset", "I", "u"), ("total_bytes", "I", "u"), ("chunk_len", "H", "n"),
        ("reserved", "2x", "x"),
    )  # fmt: skip
    _ENUMS: ClassVar[dict[str, type[IntEnum]]] = {"kind": ImageKind}
    _ARRAY: ClassVar[str | None] = "data"
    _MAX: ClassVar[int] = IMAGE_MAX_CHUNK

    camera_index: int
    kind: int
    bytes_per_pixel: int
    image_id: int
    camera_frame: int
    x0: int
    y0: int
    width: int
    height: int
    offset: int
    total_bytes: int
    data: bytes = b""

    @property
    def chunk_len(self) -> int:
        return len(self.data)


@_finish_layout
@dataclass(frozen=True, eq=False)
class DvsClusters(UdpMessage):
    """DVS_CLUSTERS (0x10): event-camera cluster tracks of one time slice, stated at t_end_us, with
    each cluster's position covariance and (flag SYNCED) the trigger frame at t_end_us."""

    TYPE: ClassVar[MsgType] = MsgType.DVS_CLUSTERS
    _FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        ("camera_index", "H", "u"), ("n_clusters", "H", "n"), ("seq", "I", "u"), ("t_start_us", "Q", "u"),
        ("t_end_us", "Q", "u"), ("edge_done_ns", "Q", "u"), ("trigger_frame", "d", "d"),
        ("frame_period_us", "f", "f"), ("syncs", "I", "u"),
    )  # fmt: skip
    _FLAG_MASK: ClassVar[int] = int(DvsFlags.SYNCED)
    _ARRAY: ClassVar[str | None] = "clusters"
    _DTYPE: ClassVar[np.dtype | None] = CLUSTER_DTYPE
    _MAX: ClassVar[int] = CLUSTERS_MAX

    camera_index: int
    seq: int
    t_start_us: int
    t_end_us: int
    edge_done_ns: int = 0
    trigger_frame: float = 0.0
    frame_period_us: float = 0.0
    syncs: int = 0
    flags: int = 0
    clusters: np.ndarray = field(default_factory=lambda: _empty(CLUSTER_DTYPE))

    @property
    def n_clusters(self) -> int:
        return len(self.clusters)

    @property
    def synced(self) -> bool:
        return bool(self.flags & DvsFlags.SYNCED)


def _check_dvs_clusters(vals: dict, flags: int, buf: bytes, rec_off: int, count: int) -> None:
    """BAD_FIELD rules of SPEC 1.6: a covariance per cluster, a period when SYNCED."""
    period = vals["frame_period_us"]
    if period < 0 or (flags & DvsFlags.SYNCED and not period > 0):
        raise ProtocolError("BAD_FIELD", f"DvsClusters.frame_period_us = {period} (SYNCED: {bool(flags & 1)})")
    if count:
        c = np.frombuffer(buf, CLUSTER_DTYPE, count, rec_off)
        # float32 products are exact in float64: the same test as the C codec's
        vx, vy, cxy = (c[k].astype(np.float64) for k in ("var_x", "var_y", "cov_xy"))
        bad = (vx < 0) | (vy < 0) | (cxy * cxy > vx * vy)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ProtocolError("BAD_FIELD", f"DvsClusters.clusters[{i}]: var_x {vx[i]}, var_y {vy[i]}, "
                                f"cov_xy {cxy[i]} is not a covariance")


@_finish_layout
@dataclass(frozen=True, eq=False)
class DvsWingbeat(UdpMessage):
    """DVS_WINGBEAT (0x11): wing-edge estimates of a tethered animal."""

    TYPE: ClassVar[MsgType] = MsgType.DVS_WINGBEAT
    _FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        ("camera_index", "H", "u"), ("n_edges", "H", "n"), ("seq", "I", "u"), ("t_us", "Q", "u"),
        ("edge_done_ns", "Q", "u"),
    )  # fmt: skip
    _ARRAY: ClassVar[str | None] = "edges"
    _DTYPE: ClassVar[np.dtype | None] = WINGEDGE_DTYPE
    _MAX: ClassVar[int] = WINGEDGES_MAX

    camera_index: int
    seq: int
    t_us: int
    edge_done_ns: int = 0
    edges: np.ndarray = field(default_factory=lambda: _empty(WINGEDGE_DTYPE))

    @property
    def n_edges(self) -> int:
        return len(self.edges)


@_finish_layout
@dataclass(frozen=True, eq=False)
class LiveEstimates(UdpMessage):
    """LIVE_ESTIMATES (0x20): host -> stimulus programs, the tracked objects of one trigger frame."""

    TYPE: ClassVar[MsgType] = MsgType.LIVE_ESTIMATES
    _FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        ("trigger_frame", "Q", "u"), ("trigger_time", "d", "d"), ("seq", "I", "u"), ("n_objects", "H", "n"),
        ("part_index", "B", "u"), ("part_count", "B", "u"), ("latency_ms", "f", "f"), ("reserved", "4x", "x"),
    )  # fmt: skip
    _FLAG_MASK: ClassVar[int] = int(LiveFlags.SPLIT)
    _ARRAY: ClassVar[str | None] = "objects"
    _DTYPE: ClassVar[np.dtype | None] = OBJECT_DTYPE
    _MAX: ClassVar[int] = LIVE_MAX_OBJECTS

    trigger_frame: int
    trigger_time: float
    seq: int
    latency_ms: float = 0.0
    part_index: int = 0
    part_count: int = 1
    flags: int = 0
    objects: np.ndarray = field(default_factory=lambda: _empty(OBJECT_DTYPE))

    @property
    def n_objects(self) -> int:
        return len(self.objects)


UDP_MESSAGE_TYPES: tuple[type[UdpMessage], ...] = tuple(_BY_TYPE.values())


# ---------------------------------------------------------------- decoding


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
    count_name = next((nm for nm, _, kind in cls._FIELDS if kind == "n"), None)
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
        if cls is FeatureFrame and not flags & FeatureFlags.SPLIT and count > vals["total_points"]:
            raise ProtocolError(
                "COUNT_OVERFLOW", f"FeatureFrame: n_points {count} > total_points {vals['total_points']}"
            )
        if need != payload:
            raise ProtocolError(
                "LENGTH_MISMATCH", f"{name}: {payload - need} bytes after the {count} records of {count_name}"
            )

    # NOT_FINITE: fixed floats, then records
    for nm, _, kind in cls._FIELDS:
        if kind in "fd" and not math.isfinite(vals[nm]):
            raise ProtocolError("NOT_FINITE", f"{name}.{nm} is {vals[nm]}")
    if cls._DTYPE is not None:
        _check_finite_records(buf, rec_off, count, cls._DTYPE, cls._COLS, f"{name}.{cls._ARRAY}")

    # BAD_FIELD: enums, texts, cross-field rules
    for nm, _code, kind in cls._FIELDS:
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
    return cls(**vals)


def _check_image(vals: dict, chunk_len: int) -> None:
    bpp = vals["bytes_per_pixel"]
    if bpp not in (1, 2):
        raise ProtocolError("BAD_FIELD", f"ImageChunk.bytes_per_pixel = {bpp}, must be 1 or 2")
    expect = vals["width"] * vals["height"] * bpp
    if vals["total_bytes"] != expect:
        raise ProtocolError(
            "BAD_FIELD", f"ImageChunk.total_bytes = {vals['total_bytes']}, width x height x bpp = {expect}"
        )
    if vals["offset"] + chunk_len > vals["total_bytes"]:
        raise ProtocolError(
            "BAD_FIELD",
            f"ImageChunk: offset {vals['offset']} + chunk_len {chunk_len} > total_bytes {vals['total_bytes']}",
        )


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


def make_points(n: int) -> np.ndarray:
    """A zeroed point array of n records (POINT_DTYPE)."""
    return np.zeros(n, POINT_DTYPE)


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


def join_feature_parts(parts: list[FeatureFrame]) -> FeatureFrame:
    """Reassemble the SPLIT datagrams of one camera frame (any order) into one FeatureFrame.

    Raises ProtocolError (BAD_FIELD) when parts are missing, repeated or from different frames.
    """
    if not parts:
        raise ProtocolError("BAD_FIELD", "no parts to join")
    first = min(parts, key=lambda p: p.part_index)
    count = first.part_count
    key = (first.camera_index, first.camera_frame, count)
    if any((p.camera_index, p.camera_frame, p.part_count) != key for p in parts):
        raise ProtocolError("BAD_FIELD", "parts of different frames (camera_index, camera_frame, part_count)")
    if sorted(p.part_index for p in parts) != list(range(count)):
        raise ProtocolError("BAD_FIELD", f"parts {sorted(p.part_index for p in parts)} of {count}")
    ordered = sorted(parts, key=lambda p: p.part_index)
    points = np.concatenate([p.points for p in ordered]) if count > 1 else first.points
    truncated = any(p.flags & FeatureFlags.TRUNCATED for p in parts)
    flags = (first.flags & ~FeatureFlags.SPLIT & ~FeatureFlags.TRUNCATED) | (
        FeatureFlags.TRUNCATED if truncated else 0
    )
    return replace(first, points=points, part_index=0, part_count=1, flags=int(flags))


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


def image_chunks(
    camera_index: int, kind: int, image_id: int, camera_frame: int, x0: int, y0: int, pixels: np.ndarray
) -> list[ImageChunk]:
    """Cut a 2-D uint8 or uint16 image into IMAGE chunks of at most 1428 bytes (16-bit little-endian)."""
    pixels = np.asarray(pixels)
    if pixels.ndim != 2 or pixels.dtype not in (np.uint8, np.uint16):
        raise ProtocolError("BAD_FIELD", "an image is a 2-D uint8 or uint16 array")
    raw = np.ascontiguousarray(pixels, pixels.dtype.newbyteorder("<")).tobytes()
    h, w = pixels.shape
    bpp = pixels.dtype.itemsize
    return [
        ImageChunk(camera_index, kind, bpp, image_id, camera_frame, x0, y0, w, h, off, len(raw),
                   raw[off : off + IMAGE_MAX_CHUNK])  # fmt: skip
        for off in range(0, max(len(raw), 1), IMAGE_MAX_CHUNK)
    ]


def assemble_image(chunks: list[ImageChunk]) -> np.ndarray:
    """The image of a complete set of IMAGE chunks (any order); BAD_FIELD when chunks are missing or mixed."""
    if not chunks:
        raise ProtocolError("BAD_FIELD", "no chunks")
    c0 = chunks[0]
    key = (c0.camera_index, c0.image_id, c0.width, c0.height, c0.bytes_per_pixel, c0.total_bytes)
    if any((c.camera_index, c.image_id, c.width, c.height, c.bytes_per_pixel, c.total_bytes) != key for c in chunks):
        raise ProtocolError("BAD_FIELD", "chunks of different images")
    buf = bytearray(c0.total_bytes)
    covered = np.zeros(c0.total_bytes, bool)
    for c in chunks:
        buf[c.offset : c.offset + c.chunk_len] = c.data
        covered[c.offset : c.offset + c.chunk_len] = True
    if not covered.all():
        raise ProtocolError("BAD_FIELD", f"{int((~covered).sum())} image bytes missing")
    dtype = np.dtype("<u2") if c0.bytes_per_pixel == 2 else np.dtype(np.uint8)
    return np.frombuffer(bytes(buf), dtype).reshape(c0.height, c0.width)
