"""2D detections from any source (FlyTrack recording, .braidz, flydra .h5) in one form, and the
frame bundles the tracker eats, rebuilt from them."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field

import numpy as np

from flytrack_host.camera import Camera
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


def iter_bundles(rows: np.ndarray, fps: float, camera_indices: list[int] | None = None) -> Iterator[FrameBundle]:
    """One FrameBundle per trigger frame present, in frame order. Rows never given to the tracker
    live (rejected ones) are left out; late rows are used: offline nothing is late. Event cameras'
    rows (FLAG_DVS) are left out too: the tracker weighs them by their covariance (SPEC 1.6), which
    the recording does not keep, and as frame points they could start targets."""
    ok = (rows["trigger_frame"] >= 0) & ((rows["flags"] & (FLAG_REJECTED | FLAG_DVS)) == 0)
    rows = rows[ok]
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
        for cam in np.unique(grp["camera_index"]):
            g = grp[grp["camera_index"] == cam]
            g = g[np.isfinite(g["x_dist"]) & np.isfinite(g["y_dist"])]
            pts = np.zeros(len(g), dtype=POINT_DTYPE)
            for f in _PT_FIELDS:
                pts[f] = g[f]
            det[int(cam)] = pts
        missing = tuple(c for c in cams_all if c not in det)
        yield FrameBundle(trigger_frame=frame, timestamp=t, detections=det, missing_cameras=missing)


def n_frames(rows: np.ndarray) -> int:
    ok = (rows["trigger_frame"] >= 0) & ((rows["flags"] & (FLAG_REJECTED | FLAG_DVS)) == 0)
    return int(len(np.unique(rows["trigger_frame"][ok])))
