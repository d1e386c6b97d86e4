"""The figures a batch reports per (recording, parameter set): coverage, objects, track lengths, and
the reprojection error of each 3D estimate to the 2D points the tracker associated with it.

A recording in parts is read part by part (the rows of a tracked frame, its estimates and their 2D
points, are in one part): what is kept across parts is the frames seen, the objects' track lengths and
the reprojection errors (8 bytes per associated point)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.geometry.camera import Camera
from flytrack_host.io.reprojection import recording_reprojection
from flytrack_host.recording.reader import Recording
from flytrack_host.recording.source import RecordingSource, open_source

TABLES = ["kalman_estimates", "data_association", "data2d_distorted"]


def reprojection_errors(rec: Recording, cameras: Mapping[int, Camera]) -> np.ndarray:
    """Distance in pixels (distorted image) from each associated 2D point to its estimate's projection."""
    return recording_reprojection({n: rec.table(n) for n in TABLES}, cameras)


def recording_metrics(rec: Recording | RecordingSource | Path, cameras: Mapping[int, Camera]) -> dict[str, Any]:
    frames_2d: np.ndarray = np.zeros(0, dtype=np.int64)
    covered: np.ndarray = np.zeros(0, dtype=np.int64)
    lengths: Counter[int] = Counter()
    n_est = 0
    errs = []
    for t in open_source(rec).iter_tables(TABLES):
        k = t["kalman_estimates"]
        f2 = t["data2d_distorted"]["trigger_frame"]
        frames_2d = np.union1d(frames_2d, f2[f2 >= 0])
        covered = np.union1d(covered, k["trigger_frame"])
        ids, counts = np.unique(k["obj_id"], return_counts=True)
        lengths.update(dict(zip(ids.tolist(), counts.tolist(), strict=True)))
        n_est += len(k)
        errs.append(recording_reprojection(t, cameras))
    err = np.concatenate(errs) if errs else np.zeros(0)
    lens = np.array(list(lengths.values()), dtype=np.int64)
    nan = float("nan")
    return {
        "frames_2d": int(len(frames_2d)),
        "frames_covered": int(len(covered)),
        "coverage": len(covered) / len(frames_2d) if len(frames_2d) else nan,
        "estimates": int(n_est),
        "objects": int(len(lens)),
        "track_len_mean": float(lens.mean()) if len(lens) else nan,
        "track_len_median": float(np.median(lens)) if len(lens) else nan,
        "track_len_max": int(lens.max()) if len(lens) else 0,
        "reproj_points": int(len(err)),
        "reproj_px_mean": float(err.mean()) if len(err) else nan,
        "reproj_px_median": float(np.median(err)) if len(err) else nan,
        "reproj_px_p95": float(np.percentile(err, 95)) if len(err) else nan,
    }
