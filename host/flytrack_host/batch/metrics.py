"""The figures a batch reports per (recording, parameter set): coverage, objects, track lengths, and
the reprojection error of each 3D estimate to the 2D points the tracker associated with it."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from flytrack_host.geometry.camera import Camera
from flytrack_host.io.reprojection import recording_reprojection
from flytrack_host.recording.reader import Recording


def reprojection_errors(rec: Recording, cameras: Mapping[int, Camera]) -> np.ndarray:
    """Distance in pixels (distorted image) from each associated 2D point to its estimate's projection."""
    return recording_reprojection({n: rec.table(n) for n in ("kalman_estimates", "data_association",
                                                             "data2d_distorted")}, cameras)


def recording_metrics(rec: Recording, cameras: Mapping[int, Camera]) -> dict[str, Any]:
    k = rec.table("kalman_estimates")
    frames_2d = np.unique(rec.table("data2d_distorted")["trigger_frame"])
    frames_2d = frames_2d[frames_2d >= 0]
    covered = np.unique(k["trigger_frame"])
    ids, lengths = np.unique(k["obj_id"], return_counts=True)
    err = reprojection_errors(rec, cameras)
    nan = float("nan")
    return {
        "frames_2d": int(len(frames_2d)),
        "frames_covered": int(len(covered)),
        "coverage": len(covered) / len(frames_2d) if len(frames_2d) else nan,
        "estimates": int(len(k)),
        "objects": int(len(ids)),
        "track_len_mean": float(lengths.mean()) if len(lengths) else nan,
        "track_len_median": float(np.median(lengths)) if len(lengths) else nan,
        "track_len_max": int(lengths.max()) if len(lengths) else 0,
        "reproj_points": int(len(err)),
        "reproj_px_mean": float(err.mean()) if len(err) else nan,
        "reproj_px_median": float(np.median(err)) if len(err) else nan,
        "reproj_px_p95": float(np.percentile(err, 95)) if len(err) else nan,
    }
