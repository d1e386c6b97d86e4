"""UDP codec, host-side message (protocol/SPEC.md §1): LIVE_ESTIMATES, host -> stimulus programs."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntFlag
from typing import ClassVar

import numpy as np

from .udp_header import FieldSpec, MsgType, UdpMessage, _empty, _finish_layout


class LiveFlags(IntFlag):
    SPLIT = 0x1


OBJECT_DTYPE = np.dtype(
    {
        "names": ["obj_id", "x", "y", "z", "vx", "vy", "vz", "cov"],
        "formats": ["<u4"] + ["<f4"] * 6 + [("<f4", (6,))],
        "offsets": [0, 4, 8, 12, 16, 20, 24, 28],
        "itemsize": 52,
    }
)


LIVE_MAX_OBJECTS = 27


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
