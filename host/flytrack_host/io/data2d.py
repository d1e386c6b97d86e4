"""2D detections from any source (FlyTrack recording, .braidz, flydra .h5) in one form, and the
frame bundles the tracker eats, rebuilt from them."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from flytrack_host.geometry.camera import Camera
from flytrack_host.protocol import POINT_DTYPE
from flytrack_host.recording.schema import DATA2D, FLAG_DVS, FLAG_REJECTED
from flytrack_host.tracking.types import FrameBundle

_PT_FIELDS = ("x_dist", "y_dist", "x_undist", "y_undist", "area", "peak_diff", "orientation", "eccentricity",
              "cur_val", "mean_val", "sumsq_val")


@dataclass
class Data2D:
    """DATA2D rows plus what is needed to track them again."""

    rows: np.ndarray  # DATA2D dtype
    cam_names: dict[int, str]  # camera index -> name in the calibration
    fps: float | None = None
    calibration: tuple[str, bytes] | None = None  # (file name, bytes), e.g. ("calibration.xml", ...)
    source: str = ""
    notes: list[str] = field(default_factory=list)
    tracking_params: dict | None = None
    cameras: dict[int, Camera] | None = None  # when the source carries a calibration in another form
    # trigger_clock_info rows (start_timestamp, framecount, tcnt or fraction, stop_timestamp), if any
    clock_samples: np.ndarray | None = None
    # DVS_COVARIANCE rows: the event cameras' points' covariances (FlyTrack recordings since they are kept)
    dvs_cov: np.ndarray | None = None
    # A FlyTrack recording in parts read part by part (recording.source.RecordingSource): `rows` and
    # `dvs_cov` are then empty and a re-track streams the parts (load_2d(..., stream=True)).
    parts: Any = None


def empty_rows(n: int) -> np.ndarray:
    rows = np.zeros(n, dtype=DATA2D)
    for f in ("timestamp", "x_dist", "y_dist", "x_undist", "y_undist", "area", "peak_diff", "orientation",
              "eccentricity", "mean_val", "sumsq_val"):
        rows[f] = np.nan
    return rows


def fill_undistorted(rows: np.ndarray, cameras: Mapping[int, Camera]) -> int:
    """Compute x_undist/y_undist where they are NaN but x_dist is finite; returns rows filled."""
    need = np.isnan(rows["x_undist"]) & np.isfinite(rows["x_dist"]) & np.isfinite(rows["y_dist"])
    filled = 0
    for cam, camera in cameras.items():
        sel = need & (rows["camera_index"] == cam)
        if not sel.any():
            continue
        uv = np.stack([rows["x_dist"][sel], rows["y_dist"][sel]], axis=1).astype(np.float64)
        ideal = camera.undistort(uv)
        rows["x_undist"][sel] = ideal[:, 0]
        rows["y_undist"][sel] = ideal[:, 1]
        filled += int(sel.sum())
    return filled


def _usable(rows: np.ndarray, dvs_cov: np.ndarray | None) -> np.ndarray:
    """Rows a re-track gives the tracker: never rejected ones, and event cameras' rows (FLAG_DVS)
    only with their covariance (the tracker weighs them by it, SPEC 1.6; as plain frame points they
    could start targets)."""
    ok = (rows["trigger_frame"] >= 0) & ((rows["flags"] & FLAG_REJECTED) == 0)
    dvs = (rows["flags"] & FLAG_DVS) != 0
    if dvs_cov is None or len(dvs_cov) == 0:
        return ok & ~dvs
    have = np.isin(_dvs_keys(rows["trigger_frame"], rows["camera_index"], rows["frame_pt_idx"]),
                   _dvs_keys(dvs_cov["trigger_frame"], dvs_cov["camera_index"], dvs_cov["frame_pt_idx"]))
    return ok & (~dvs | have)


def _dvs_keys(tf: np.ndarray, cam: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """One int64 per (trigger frame, camera, point index): frames below 2^31 (248 days at 100 fps)."""
    return (tf.astype(np.int64) << 32) | (cam.astype(np.int64) << 16) | idx.astype(np.int64)


def dvs_rows_left_out(rows: np.ndarray, dvs_cov: np.ndarray | None) -> int:
    """Event cameras' points a re-track cannot use (no covariance recorded for them)."""
    dvs = (rows["trigger_frame"] >= 0) & ((rows["flags"] & FLAG_DVS) != 0) & np.isfinite(rows["x_dist"])
    return int((dvs & ~_usable(rows, dvs_cov)).sum())


def iter_bundles(rows: np.ndarray, fps: float, camera_indices: list[int] | None = None,
                 dvs_cov: np.ndarray | None = None) -> Iterator[FrameBundle]:
    """One FrameBundle per trigger frame present, in frame order. Rows never given to the tracker
    live (rejected ones) are left out; late rows are used: offline nothing is late. Event cameras'
    rows (FLAG_DVS) join with their covariance from `dvs_cov` (DVS_COVARIANCE rows) as the live run
    gave them (FrameBundle.point_cov); without it they are left out."""
    rows = rows[_usable(rows, dvs_cov)]
    cov_of: dict[int, np.ndarray] = {}
    if dvs_cov is not None and len(dvs_cov):
        keys = _dvs_keys(dvs_cov["trigger_frame"], dvs_cov["camera_index"], dvs_cov["frame_pt_idx"])
        cov_of = dict(zip(keys.tolist(), np.column_stack([dvs_cov["var_x"], dvs_cov["var_y"], dvs_cov["cov_xy"]]),
                          strict=True))
    order = np.lexsort((rows["frame_pt_idx"], rows["camera_index"], rows["trigger_frame"]))
    rows = rows[order]
    if len(rows) == 0:
        return
    tf = rows["trigger_frame"]
    starts = np.flatnonzero(np.r_[True, tf[1:] != tf[:-1]])
    ends = np.r_[starts[1:], len(rows)]
    cams_all = sorted(set(camera_indices or [])) or sorted(set(rows["camera_index"].tolist()))
    for s, e in zip(starts, ends, strict=True):
        grp = rows[s:e]
        frame = int(grp["trigger_frame"][0])
        ts = grp["timestamp"][np.isfinite(grp["timestamp"])]
        t = float(ts[0]) if len(ts) else frame / fps
        det: dict[int, np.ndarray] = {}
        point_cov: dict[int, np.ndarray] = {}
        for cam in np.unique(grp["camera_index"]):
            g = grp[grp["camera_index"] == cam]
            g = g[np.isfinite(g["x_dist"]) & np.isfinite(g["y_dist"])]
            pts = np.zeros(len(g), dtype=POINT_DTYPE)
            for f in _PT_FIELDS:
                pts[f] = g[f]
            det[int(cam)] = pts
            if len(g) and (g["flags"][0] & FLAG_DVS):
                keys = _dvs_keys(g["trigger_frame"], g["camera_index"], g["frame_pt_idx"]).tolist()
                point_cov[int(cam)] = np.array([cov_of[k] for k in keys], dtype=np.float64).reshape(-1, 3)
        missing = tuple(c for c in cams_all if c not in det)
        yield FrameBundle(trigger_frame=frame, timestamp=t, detections=det, missing_cameras=missing,
                          point_cov=point_cov)


def n_frames(rows: np.ndarray, dvs_cov: np.ndarray | None = None) -> int:
    """Bundles iter_bundles gives for these rows."""
    return int(len(np.unique(rows["trigger_frame"][_usable(rows, dvs_cov)])))


def infer_fps(rows: np.ndarray) -> tuple[float, str] | None:
    """The frame rate from the 2D rows themselves, for a source that does not say it (a Braid textlog
    with "unknown fps"), as braid-offline does: frames per second between the first and last frames, on
    the trigger timestamps where every frame has one, else on the host's receive times. A straight-line
    fit of frame number against each frame's median time keeps one late packet from moving it.
    Returns (fps, how it was found) or None when fewer than two frames span a time."""
    tf = rows["trigger_frame"]
    ok = tf >= 0
    for column, what in (("timestamp", "trigger timestamps"), ("cam_received_timestamp", "host receive times")):
        t = rows[column]
        use = ok & np.isfinite(t)
        if column == "timestamp" and not np.array_equal(use, ok):
            continue  # some frames lack a trigger time: use the receive times, which all rows have
        frames, inverse = np.unique(tf[use], return_inverse=True)
        if len(frames) < 2:
            continue
        order = np.argsort(inverse, kind="stable")
        bounds = np.flatnonzero(np.diff(inverse[order])) + 1
        times = np.array([np.median(g) for g in np.split(t[use][order], bounds)])
        if times[-1] - times[0] <= 0:
            continue
        slope = float(np.polyfit(times - times[0], frames.astype(np.float64), 1)[0])
        if np.isfinite(slope) and slope > 0:
            return slope, f"the {what} of frames {int(frames[0])}-{int(frames[-1])}"
    return None
