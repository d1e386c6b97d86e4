"""Typed messages between the synchroniser, the tracker and the recorder.

The synchroniser hands the tracker one `FrameBundle` per trigger frame; the tracker answers with one
`FrameResult`. Point arrays are the protocol's NumPy structured dtype (flytrack_host.protocol), so the
bytes off the wire reach the tracker without a copy into Python objects.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray


@dataclass(slots=True)
class FrameBundle:
    """Everything the cameras reported for one trigger frame."""

    trigger_frame: int
    timestamp: float  # host clock, seconds (Unix epoch), from the trigger clock model
    # camera_index -> structured array of points (protocol point dtype), possibly empty.
    detections: dict[int, np.ndarray]
    # Cameras expected but not (yet) heard from when the bundle was closed.
    missing_cameras: tuple[int, ...] = ()
    # camera_index -> (n, 3) var_x, var_y, cov_xy (px^2) of detections[camera_index]: points with
    # their own measurement covariance (event cameras, SPEC 1.6). They update targets with that
    # covariance as R (tracking/own_covariance.py) and never start one.
    point_cov: dict[int, np.ndarray] = field(default_factory=dict)


@dataclass(slots=True)
class Estimate:
    obj_id: int
    state: NDArray[np.float64]  # (6,) x, y, z, vx, vy, vz (m, m/s)
    covariance: NDArray[np.float64]  # (6, 6)
    n_cameras: int  # cameras whose points updated this estimate in this frame
    orientation: NDArray[np.float64] | None = None  # (3,) unit body axis, when estimable


@dataclass(slots=True)
class Association:
    obj_id: int
    camera_index: int
    point_index: int  # index into FrameBundle.detections[camera_index]


@dataclass(slots=True)
class FrameResult:
    trigger_frame: int
    timestamp: float
    estimates: list[Estimate] = field(default_factory=list)
    associations: list[Association] = field(default_factory=list)
    born: list[int] = field(default_factory=list)
    died: list[int] = field(default_factory=list)
