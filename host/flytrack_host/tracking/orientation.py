"""Body orientation: the 3D line best matching each camera's 2D body axis (seed 000 appendix B).

A camera that sees an elongated blob at pixel (u, v) with major-axis angle theta constrains the body
axis to the plane through the camera centre that contains the image line through (u, v) along theta.
Near the target's position X that plane is {X + e : a_perp . (J e) = 0}, J being the 2x3 Jacobian of
the distorted projection at X and a_perp the image normal of the line, so its normal is n = J^T a_perp.
Using J keeps lens distortion in the model without undistorting a second image point.
The body axis is the unit vector e minimising sum_i (n_i . e)^2 over the unit normals: the right
singular vector of the stacked normals with the smallest singular value (the best line of
intersection of the planes). The sign is not observable: the tracker keeps it continuous in time.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from flytrack_host.geometry.camera import Camera

F64 = NDArray[np.float64]


def plane_normals(J: F64, theta: F64) -> F64:
    """Unit plane normals (..., 3) from Jacobians J (..., 2, 3) and image angles theta (...)."""
    a_perp = np.stack([-np.sin(theta), np.cos(theta)], axis=-1)  # (..., 2)
    n = (np.swapaxes(J, -1, -2) @ a_perp[..., None])[..., 0]
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    return n / np.where(norm > 0, norm, 1.0)


def axes_from_normals(normals: F64, min_plane_angle_deg: float) -> tuple[F64, NDArray[np.bool_]]:
    """Best intersection direction of each set of planes: normals (T, C, 3), zero rows for cameras
    that do not contribute. Returns unit axes (T, 3) and a mask (T,) of sets whose planes are not
    all (nearly) parallel."""
    # The right singular vectors of N are the eigenvectors of N^T N (3x3, cheaper to decompose), its
    # eigenvalues the squared singular values, in ascending order.
    lam, vec = np.linalg.eigh(np.swapaxes(normals, 1, 2) @ normals)
    axes = vec[:, :, 0]
    s = np.sqrt(np.maximum(lam, 0.0))
    # Two unit normals at angle phi give singular values sqrt(1 +- cos phi): s1/s0 = tan(phi / 2).
    ratio = s[:, 1] / np.maximum(s[:, 2], 1e-300)
    ok = ratio >= np.tan(np.radians(min_plane_angle_deg) / 2.0)
    return axes, ok


def body_axis(
    cameras: Sequence[Camera], position: ArrayLike, theta: Sequence[float], min_plane_angle_deg: float = 10.0
) -> F64 | None:
    """One target: body axis (3,) from its position and each camera's image angle (radians), or None
    when fewer than two cameras or nearly parallel planes leave it undefined."""
    if len(cameras) != len(theta):
        raise ValueError("one image angle per camera is needed")
    if len(cameras) < 2:
        return None
    J = np.stack([cam.project_jacobian(position)[1] for cam in cameras])
    n = plane_normals(J, np.asarray(theta, dtype=np.float64))
    axes, ok = axes_from_normals(n[None], min_plane_angle_deg)
    return axes[0] if ok[0] else None
