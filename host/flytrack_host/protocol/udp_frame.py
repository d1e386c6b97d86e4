"""UDP codec, frame-camera messages (protocol/SPEC.md §1): FEATURES, STATUS, CONTROL, CONTROL_ACK
and IMAGE, with their record dtype and the helpers that join split frames and cut/assemble images.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import IntEnum, IntFlag
from typing import ClassVar

import numpy as np

from .errors import ProtocolError
from .udp_header import HEADER_SIZE, MAX_DATAGRAM, FieldSpec, MsgType, UdpMessage, _empty, _finish_layout


class FeatureFlags(IntFlag):
    SPLIT = 0x1
    TRUNCATED = 0x2


# The flags as plain ints for the per-datagram path: `int & IntFlag` goes through enum's Python code
# (several microseconds a datagram on the host's tracking thread).
_SPLIT = int(FeatureFlags.SPLIT)
_TRUNCATED = int(FeatureFlags.TRUNCATED)


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


POINT_DTYPE = np.dtype(
    {
        "names": ["x_dist", "y_dist", "x_undist", "y_undist", "area", "peak_diff", "orientation",
                  "eccentricity", "cur_val", "reserved", "mean_val", "sumsq_val"],
        "formats": ["<f4"] * 8 + ["<u2", "<u2", "<f4", "<f4"],
        "offsets": [0, 4, 8, 12, 16, 20, 24, 28, 32, 34, 36, 40],
        "itemsize": 44,
    }
)  # fmt: skip

FEATURES_MAX_POINTS = (MAX_DATAGRAM - HEADER_SIZE - 56) // POINT_DTYPE.itemsize  # 32
IMAGE_MAX_CHUNK = MAX_DATAGRAM - HEADER_SIZE - 36  # 1428


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
        return bool(self.flags & _SPLIT)

    @property
    def truncated(self) -> bool:
        return bool(self.flags & _TRUNCATED)


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


def make_points(n: int) -> np.ndarray:
    """A zeroed point array of n records (POINT_DTYPE)."""
    return np.zeros(n, POINT_DTYPE)


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
