"""What goes into the synchroniser (`CameraFrame`) and what comes out of it (bundles, untracked
frames, events), and its per-camera counters."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flytrack_host.tracking.types import FrameBundle


@dataclass(slots=True)
class CameraFrame:
    """One camera frame as received (split parts already joined). `points` is the protocol's
    structured point array, straight from the datagram bytes."""

    camera_index: int
    camera_frame: int
    trigger_frame: int  # from the edge; -1 when it does not know
    points: np.ndarray
    recv_time: float  # host clock when the frame (its last part) arrived
    device_timestamp_ns: int = 0
    edge_recv_ns: int = 0
    edge_done_ns: int = 0
    total_points: int = 0
    truncated: bool = False
    incomplete: bool = False  # a split frame with parts missing
    restarted: bool = False  # the first frame from a restarted edge (the receiver saw a new sender)
    dvs: bool = False  # made from an event camera's clusters (flytrack_host.dvs.clusters)


@dataclass(slots=True)
class SyncedBundle:
    bundle: FrameBundle
    frames: dict[int, CameraFrame]
    first_arrival: float
    last_arrival: float
    closed_by: str  # "complete", "deadline" or "flush"


@dataclass(slots=True)
class UntrackedFrame:
    """A frame that is recorded but not tracked: late, duplicate, future-dated, suspect, unmapped."""

    frame: CameraFrame
    trigger_frame: int  # best mapping, -1 if none
    reason: str


@dataclass(slots=True)
class SyncEvent:
    kind: str  # "dead", "alive", "clock_jump", "drift", "synchronized", "restart", "reanchor"
    camera_index: int
    message: str
    global_jump: bool = False


SyncOutput = SyncedBundle | UntrackedFrame | SyncEvent


@dataclass
class CameraSyncStats:
    frames: int = 0
    tracked: int = 0
    late: int = 0
    duplicate: int = 0
    future: int = 0
    suspect: int = 0
    clock_jumps: int = 0
    drift: int = 0
    deaths: int = 0
    revivals: int = 0
    early: int = 0  # frames numbered ahead of their arrival (misnumbered by the edge)
    restarts: int = 0  # edge restarts (re-mapped by arrival)
    missed: int = 0  # trigger frames an edge missed while it was down (restart gap)
    ahead: int = 0  # mappings found ahead of the other cameras' arrivals and re-mapped
