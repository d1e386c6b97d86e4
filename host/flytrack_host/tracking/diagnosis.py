"""Why a run produced no estimates although 2D points arrived: reasons with numbers, from the tracker's
counters (Tracker.stats), the rig and the parameters. Used by `flytrack retrack` and the live run."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from flytrack_host.geometry.camera import Camera
from flytrack_host.tracking.params import TrackingParams


def newborn_position_std(cameras: Mapping[int, Camera], params: TrackingParams) -> float:
    """Rough position std (world units) of a target seen once by every camera at the rig's centre:
    depth x pixel noise / focal length, divided by sqrt(cameras / 2)."""
    cams = list(cameras.values())
    if not cams:
        return float("nan")
    centres = np.stack([c.center for c in cams])
    mid = centres.mean(axis=0)
    depth = float(np.median(np.linalg.norm(centres - mid, axis=1)))
    f = float(np.median([0.5 * (c.K[0, 0] + c.K[1, 1]) for c in cams]))
    return depth * params.measurement_noise_px / f / np.sqrt(max(len(cams), 2) / 2.0)


def why_no_estimates(
    stats: Mapping[str, int], cameras: Mapping[int, Camera], params: TrackingParams,
    missing_calibration: list[str] | None = None, cameras_with_points: list[int] | None = None,
) -> list[str]:
    """Reasons (one sentence each, with numbers) that a run with these counters reported nothing.
    `cameras_with_points`: the calibrated camera indices that gave at least one point, when known."""
    why: list[str] = []
    if missing_calibration:
        why.append(f"camera(s) {', '.join(missing_calibration)} have 2D data but no calibration: their points "
                   "were not used")
    if stats.get("unknown_camera_points", 0):
        why.append(f"{stats['unknown_camera_points']} points came from camera indices the calibration does not "
                   "have")
    if stats.get("points", 0) == 0:
        why.append("no usable 2D point reached the tracker"
                   + (f" ({stats['nonfinite_points']} were NaN/inf)" if stats.get("nonfinite_points") else ""))
        return why
    centres = np.stack([c.center for c in cameras.values()]) if cameras else np.zeros((1, 3))
    spread = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max())
    std = newborn_position_std(cameras, params)
    thr = params.death_position_std_m
    need = max(2, params.birth_min_cameras)
    seen = sorted(set(cameras_with_points)) if cameras_with_points is not None else sorted(cameras)
    if stats.get("births", 0) == 0 and len(seen) < need:
        # One camera alone cannot place a point in 3D: blaming the calibration here would mislead.
        names = ", ".join(cameras[i].name if i in cameras else str(i) for i in seen) or "none"
        why.append(f"no target was born: 2D points came from {len(seen)} calibrated camera(s) ({names}) of "
                   f"{len(cameras)} in the calibration; a 3D position needs points from at least {need} cameras")
    elif stats.get("births", 0) == 0:
        if stats.get("birth_hypotheses", 0) == 0:
            why.append(f"no target was born: no pair of points from two cameras agreed within "
                       f"{2.5 * params.birth_max_reproj_px:g} px (epipolar gate) in {stats.get('frames', 0)} frames; "
                       "the calibration does not match these 2D points (camera names or order, units, distortion?)")
        else:
            why.append(f"no target was born: none of {stats['birth_hypotheses']} hypotheses had a mean reprojection "
                       f"error <= {params.birth_max_reproj_px:g} px over >= {params.birth_min_cameras} cameras; "
                       "the calibration does not match these 2D points")
    elif stats.get("confirmed", 0) == 0:
        dropped = stats.get("tentative_dropped", 0)
        msg = (f"every new target died before confirmation ({stats['births']} born, {dropped} dropped; "
               f"confirmation needs {params.confirm_min_frames} frames)")
        if std > thr:
            msg += (f": position std about {std:.3g} > {thr:g} m at birth (camera centres up to {spread:.3g} units "
                    "from the rig's centre); is the calibration in metres?")
        why.append(msg)
    elif spread > 50:
        why.append(f"camera centres lie up to {spread:.3g} units from the rig's centre: is the calibration in metres?")
    return why
