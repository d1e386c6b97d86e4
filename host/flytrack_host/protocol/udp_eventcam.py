"""UDP codec, event-camera messages (protocol/SPEC.md §1): DVS_CLUSTERS and DVS_WINGBEAT, with their
record dtypes and the covariance / period rules of DVS_CLUSTERS.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntFlag
from typing import ClassVar

import numpy as np

from .errors import ProtocolError
from .udp_header import HEADER_SIZE, MAX_DATAGRAM, FieldSpec, MsgType, UdpMessage, _empty, _finish_layout


class DvsFlags(IntFlag):
    SYNCED = 0x1  # DVS_CLUSTERS: trigger_frame and frame_period_us are valid


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

CLUSTERS_MAX = (MAX_DATAGRAM - HEADER_SIZE - 48) // CLUSTER_DTYPE.itemsize  # 35
WINGEDGES_MAX = 8


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
