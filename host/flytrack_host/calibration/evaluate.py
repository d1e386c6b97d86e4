"""Checks of a calibration against a known truth (synthetic rigs): used by tests and the benchmark."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from flytrack_host.calibration.align import umeyama
from flytrack_host.calibration.observations import Observations
from flytrack_host.calibration.selfcal import refine_points
from flytrack_host.geometry.camera import Camera

__all__ = ["reprojection_error", "centre_error", "errors_against_truth"]


def reprojection_error(cameras: Mapping[str, Camera], obs: Observations, use: NDArray[np.bool_]) -> float:
    """Mean reprojection error (px) of the `use` observations, each frame triangulated and refined with
    these cameras: the same measure for any calibration, whichever program produced it."""
    cams = [cameras[n] for n in obs.camera_names]
    _, inv = obs.point_index()
    X = refine_points(cams, obs, inv, use, int(inv.max()) + 1)
    errs = []
    for c, cam in enumerate(cams):
        s = use & (obs.cam == c)
        e = np.linalg.norm(cam.project(X[inv[s]]) - obs.uv[s], axis=1)
        errs.append(e[np.isfinite(e)])
    return float(np.mean(np.concatenate(errs)))


def centre_error(cameras: Mapping[str, Camera], truth: Mapping[str, Camera]) -> float:
    """Largest camera-centre distance after the best similarity onto the true centres (world units)."""
    names = list(truth)
    a = np.array([cameras[n].center for n in names])
    b = np.array([truth[n].center for n in names])
    sim = umeyama(a, b)
    return float(np.max(np.linalg.norm(sim.apply(a) - b, axis=1)))


def errors_against_truth(cameras: Mapping[str, Camera], points: NDArray[np.float64],
                         truth: Mapping[str, Camera], true_points: NDArray[np.float64]
                         ) -> dict[str, dict[str, float]]:
    """Per camera of `truth`: after the similarity that best maps the calibration's triangulated
    points onto the same points' true positions (as `calibrate align` with known marks would), the
    distance of the camera centre from the true one (world units) and how far the calibrated camera
    projects the true points from where the true camera does (mean and 95th percentile, px; only
    points in the true camera's view)."""
    ok = np.all(np.isfinite(points), axis=1)  # (frames the calibration could not triangulate)
    sim = umeyama(points[ok], true_points[ok])
    out: dict[str, dict[str, float]] = {}
    for name, tc in truth.items():
        c = sim.apply_camera(cameras[name])
        vis = tc.in_view(true_points, margin=0.0)
        d = np.linalg.norm(c.project(true_points[vis]) - tc.project(true_points[vis]), axis=1)
        out[name] = {"centre": float(np.linalg.norm(c.center - tc.center)),
                     "proj_mean_px": float(np.mean(d)) if len(d) else float("nan"),
                     "proj_p95_px": float(np.percentile(d, 95)) if len(d) else float("nan")}
    return out
