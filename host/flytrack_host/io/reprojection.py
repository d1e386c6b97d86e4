"""The reprojection error of 3D estimates to the 2D points the tracker associated with them: the one
computation behind `flytrack compare`, the `.braidz` reprojection histogram and batch results."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pandas as pd

from flytrack_host.geometry.camera import Camera


def associated_reprojection(est: pd.DataFrame, assoc: pd.DataFrame, rows: np.ndarray,
                            cameras: Mapping[int, Camera]) -> np.ndarray:
    """Distance (px, distorted image) from each associated 2D point to its estimate's projection.

    est: obj_id, frame, x, y, z (m); assoc: obj_id, frame, camn, pt_idx; rows: DATA2D rows (the points,
    keyed by camera_index, trigger_frame, frame_pt_idx); cameras: camera index -> Camera. Pairs whose
    point, camera or projection is missing are left out."""
    if est.empty or assoc.empty or not len(rows):
        return np.zeros(0)
    ok = np.isfinite(rows["x_dist"]) & np.isfinite(rows["y_dist"])
    r = rows[ok]
    pts = pd.DataFrame({"camn": r["camera_index"].astype(np.int64), "frame": r["trigger_frame"].astype(np.int64),
                        "pt_idx": r["frame_pt_idx"].astype(np.int64), "u": r["x_dist"], "v": r["y_dist"]})
    pts = pts.drop_duplicates(["camn", "frame", "pt_idx"])
    a = assoc[["obj_id", "frame", "camn", "pt_idx"]].astype(np.int64)
    e = est[["obj_id", "frame", "x", "y", "z"]].astype({"obj_id": np.int64, "frame": np.int64})
    m = a.merge(e, on=["obj_id", "frame"]).merge(pts, on=["camn", "frame", "pt_idx"])
    out = []
    for camn, g in m.groupby("camn"):
        cam = cameras.get(int(camn))
        if cam is None:
            continue
        uv = cam.project(g[["x", "y", "z"]].to_numpy(dtype=np.float64))
        out.append(np.hypot(uv[:, 0] - g["u"].to_numpy(), uv[:, 1] - g["v"].to_numpy()))
    d = np.concatenate(out) if out else np.zeros(0)
    return d[np.isfinite(d)]


def recording_reprojection(tables: Mapping[str, np.ndarray], cameras: Mapping[int, Camera]) -> np.ndarray:
    """associated_reprojection over a FlyTrack recording's tables (kalman_estimates, data_association,
    data2d_distorted)."""
    k = tables["kalman_estimates"]
    a = tables["data_association"]
    est = pd.DataFrame({"obj_id": k["obj_id"], "frame": k["trigger_frame"], "x": k["x"], "y": k["y"], "z": k["z"]})
    assoc = pd.DataFrame({"obj_id": a["obj_id"], "frame": a["trigger_frame"], "camn": a["camera_index"],
                          "pt_idx": a["pt_idx"]})
    return associated_reprojection(est, assoc, tables["data2d_distorted"], cameras)
