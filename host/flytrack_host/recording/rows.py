"""Recording rows of the host pipeline: DATA2D rows of a camera frame, KALMAN and ASSOCIATION rows
of a tracked frame, DVS_COVARIANCE rows of an event camera's points (also used by the synthetic
recordings and retracking)."""

from __future__ import annotations

import numpy as np

from flytrack_host.intake.sync import (
    CameraFrame,
)
from flytrack_host.recording.schema import (
    ASSOCIATION,
    COV_NAMES,
    DATA2D,
    DVS_COVARIANCE,
    FLAG_DVS,
    FLAG_INCOMPLETE,
    FLAG_REJECTED,
    FLAG_TRACKED,
    FLAG_TRUNCATED,
    KALMAN,
)
from flytrack_host.tracking.types import FrameResult

_POINT_FIELDS = ("x_dist", "y_dist", "x_undist", "y_undist", "area", "peak_diff", "orientation",
                 "eccentricity", "cur_val", "mean_val", "sumsq_val")
_FLOAT_FIELDS = tuple(f for f in _POINT_FIELDS if f != "cur_val")

_INT_LIMITS = {name: np.iinfo(DATA2D[name]) for name in DATA2D.names if DATA2D[name].kind in "iu"}
_FALLBACK = {"trigger_frame": -1}  # out of range: "not mapped"; unsigned fields: 0


def _fit(name: str, value: int, bad: list[str]) -> int:
    """`value` if the DATA2D column holds it, else a fallback, and the column is named in `bad`."""
    lim = _INT_LIMITS[name]
    v = int(value)
    if lim.min <= v <= lim.max:
        return v
    bad.append(f"{name}={v}")
    return _FALLBACK.get(name, 0)


def data2d_rows(fr: CameraFrame, tf: int, timestamp: float, flags: int,
                range_errors: list[str] | None = None) -> np.ndarray:
    """One DATA2D row per point of a camera frame (one NaN row for a frame without points).

    Every integer is range-checked before it is written: a value the column cannot hold (a wild frame
    number from a misbehaving edge) is stored as -1 (trigger frame) or 0 and named in `range_errors`,
    and the row is flagged rejected; the frame is never lost."""
    pts = fr.points
    n = len(pts)
    bad: list[str] = []
    rows = np.zeros(max(n, 1), dtype=DATA2D)
    rows["trigger_frame"] = _fit("trigger_frame", tf, bad)
    rows["camera_index"] = _fit("camera_index", fr.camera_index, bad)
    rows["camera_frame"] = _fit("camera_frame", fr.camera_frame, bad)
    rows["timestamp"] = timestamp
    rows["cam_received_timestamp"] = fr.recv_time
    rows["device_timestamp_ns"] = _fit("device_timestamp_ns", fr.device_timestamp_ns, bad)
    rows["edge_recv_ns"] = _fit("edge_recv_ns", fr.edge_recv_ns, bad)
    rows["edge_done_ns"] = _fit("edge_done_ns", fr.edge_done_ns, bad)
    rows["n_points"] = _fit("n_points", n, bad)
    rows["total_points"] = _fit("total_points", fr.total_points, bad)
    if bad:
        flags = (flags & ~FLAG_TRACKED) | FLAG_REJECTED
        if range_errors is not None:
            range_errors.extend(bad)
    rows["flags"] = (flags | (FLAG_TRUNCATED if fr.truncated else 0) | (FLAG_INCOMPLETE if fr.incomplete else 0)
                     | (FLAG_DVS if fr.dvs else 0))
    if n:
        rows["frame_pt_idx"] = np.arange(n)
        names = pts.dtype.names or ()
        for f in _POINT_FIELDS:
            if f in names:
                rows[f] = pts[f]
    else:
        for f in _FLOAT_FIELDS:
            rows[f] = np.nan
    return rows


def dvs_covariance_rows(camera_index: int, tf: int, cov: np.ndarray) -> np.ndarray:
    """DVS_COVARIANCE rows of an event camera's points at trigger frame tf ((n, 3) var_x, var_y,
    cov_xy, in the order of the frame's points: frame_pt_idx 0..n-1, as data2d_rows numbers them)."""
    cov = np.asarray(cov, dtype=np.float64).reshape(-1, 3)
    rows = np.zeros(len(cov), dtype=DVS_COVARIANCE)
    rows["trigger_frame"] = tf
    rows["camera_index"] = camera_index
    rows["frame_pt_idx"] = np.arange(len(cov))
    rows["var_x"], rows["var_y"], rows["cov_xy"] = cov[:, 0], cov[:, 1], cov[:, 2]
    return rows


_COV_IU = np.triu_indices(6)  # COV_NAMES order (recording.schema.cov_upper)


def result_rows(result: FrameResult, timestamp: float) -> tuple[np.ndarray, np.ndarray]:
    """KALMAN and ASSOCIATION rows of a frame, column by column (the tracking thread makes them for
    every frame: one row at a time cost ~0.1 ms a frame more with 3 objects)."""
    est = result.estimates
    n = len(est)
    k = np.zeros(n, dtype=KALMAN)
    if n:
        states = np.array([np.asarray(e.state, dtype=np.float64)[:6] for e in est]).reshape(n, 6)
        covs = np.array([np.asarray(e.covariance, dtype=np.float64)[:6, :6] for e in est]).reshape(n, 6, 6)
        k["obj_id"] = [e.obj_id for e in est]
        k["trigger_frame"] = result.trigger_frame
        k["timestamp"] = timestamp
        for j, name in enumerate(("x", "y", "z", "xvel", "yvel", "zvel")):
            k[name] = states[:, j]
        upper = covs[:, _COV_IU[0], _COV_IU[1]]
        for j, name in enumerate(COV_NAMES):
            k[name] = upper[:, j]
        k["n_cameras"] = [e.n_cameras for e in est]
    a = np.zeros(len(result.associations), dtype=ASSOCIATION)
    for i, asc in enumerate(result.associations):
        a[i] = (asc.obj_id, result.trigger_frame, asc.camera_index, asc.point_index)
    return k, a
