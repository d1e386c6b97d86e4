"""Import flydra's `.h5` (PyTables) 2D data for re-tracking.

Tables read: `data2d_distorted` (camn, frame, timestamp, cam_received_timestamp, x, y, area, slope,
eccentricity, frame_pt_idx, cur_val, mean_val, sumsqf_val) and `cam_info` (camn, cam_id). PyTables
tables are HDF5 compound datasets, so h5py reads them. The calibration, when present, is the group
flydra's reconstructor writes: `calibration/pmat/<cam_id>` (3x4), `calibration/resolution/<cam_id>`
and `calibration/intrinsic_nonlinear/<cam_id>` (k1, k2, p1, p2[, k3]).
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pandas as pd

from flytrack_host.camera import Camera
from flytrack_host.io.braidz import _rows_from_braid_df
from flytrack_host.io.data2d import Data2D


class FlydraH5Error(Exception):
    pass


def _text(v: object) -> str:
    return v.decode() if isinstance(v, bytes) else str(v)


def read_flydra_calibration(h5: h5py.File) -> dict[str, Camera]:
    if "calibration" not in h5 or "pmat" not in h5["calibration"]:
        return {}
    g = h5["calibration"]
    cams = {}
    for cam_id, ds in g["pmat"].items():
        P = np.asarray(ds[...], dtype=np.float64)
        w, h = (int(v) for v in np.asarray(g["resolution"][cam_id][...]).ravel()[:2]) \
            if "resolution" in g and cam_id in g["resolution"] else (640, 480)
        dist = np.zeros(5)
        if "intrinsic_nonlinear" in g and cam_id in g["intrinsic_nonlinear"]:
            nl = np.asarray(g["intrinsic_nonlinear"][cam_id][...], dtype=np.float64).ravel()
            dist[: min(5, nl.size)] = nl[:5]
        cams[cam_id] = Camera.from_P(cam_id, P, w, h, dist)
    return cams


def read_flydra_h5(path: Path | str) -> Data2D:
    path = Path(path)
    try:
        h5 = h5py.File(path, "r")
    except OSError as exc:
        raise FlydraH5Error(f"{path}: not an HDF5 file: {exc}") from None
    with h5:
        if "data2d_distorted" not in h5:
            raise FlydraH5Error(f"{path}: no data2d_distorted table; not a flydra 2D data file")
        raw = h5["data2d_distorted"][...]
        if raw.dtype.names is None or "camn" not in raw.dtype.names or "x" not in raw.dtype.names:
            raise FlydraH5Error(f"{path}: data2d_distorted is not a table with camn, frame, x, y columns")
        df = pd.DataFrame({n: raw[n] for n in raw.dtype.names})
        names: dict[int, str] = {}
        if "cam_info" in h5:
            ci = h5["cam_info"][...]
            names = {int(r["camn"]): _text(r["cam_id"]) for r in ci}
        by_id = read_flydra_calibration(h5)
        fps = None
        for key in ("fps", "framerate"):
            if key in h5.attrs:
                fps = float(h5.attrs[key])
    rows = _rows_from_braid_df(df)
    cameras = {camn: by_id[cid] for camn, cid in names.items() if cid in by_id} if by_id else None
    return Data2D(rows=rows, cam_names=names, fps=fps, calibration=None, source=str(path), cameras=cameras)
