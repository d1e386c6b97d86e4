"""Direct linear transform: one camera's 3x4 projection matrix from 6 or more known 2D/3D pairs.

Hartley's normalisation (centroid at the origin, mean distance sqrt(2) in 2D and sqrt(3) in 3D) keeps the
linear system well conditioned; the matrix is then decomposed into K, R, t (Camera.from_P). Lens
distortion is ignored here (as in flydra's first calibration step): refine with `selfcal` afterwards.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from flytrack_host.geometry.camera import Camera

__all__ = ["DLTError", "dlt", "dlt_camera"]


class DLTError(ValueError):
    """The DLT cannot be computed; the message says what is wrong and what to do."""


def _norm_transform(X: np.ndarray) -> np.ndarray:
    d = X.shape[1]
    c = X.mean(axis=0)
    mean_dist = float(np.mean(np.linalg.norm(X - c, axis=1)))
    s = np.sqrt(d) / mean_dist
    T = np.eye(d + 1)
    T[:d, :d] *= s
    T[:d, d] = -s * c
    return T


def dlt(xyz: ArrayLike, uv: ArrayLike) -> np.ndarray:
    """3x4 projection matrix P with uv ~ P [xyz; 1], from N >= 6 pairs (not all in a plane)."""
    X = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    x = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(X) != len(x):
        raise DLTError(f"{len(X)} 3D points but {len(x)} image points: give them in pairs.")
    if len(X) < 6:
        raise DLTError(f"DLT needs at least 6 point pairs per camera (10 or more spread through the volume are "
                       f"better); got {len(X)}.")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(x))):
        raise DLTError("the DLT points contain NaN or infinity.")
    sv = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    if sv[2] < 1e-3 * sv[0]:
        kind = "collinear" if sv[1] < 1e-3 * sv[0] else "coplanar"
        raise DLTError(f"the 3D points are {kind}: a DLT needs points that span a volume (use marks at "
                       "different heights, not only on the floor).")
    T3 = _norm_transform(X)
    T2 = _norm_transform(x)
    Xn = (np.hstack([X, np.ones((len(X), 1))]) @ T3.T)
    xn = (np.hstack([x, np.ones((len(x), 1))]) @ T2.T)
    A = np.zeros((2 * len(X), 12))
    A[0::2, 0:4] = Xn
    A[0::2, 8:12] = -xn[:, 0:1] * Xn
    A[1::2, 4:8] = Xn
    A[1::2, 8:12] = -xn[:, 1:2] * Xn
    _, _, vt = np.linalg.svd(A)
    Pn = vt[-1].reshape(3, 4)
    P = np.linalg.solve(T2, Pn @ T3)
    return P / np.linalg.norm(P[2, :3])


def dlt_camera(name: str, xyz: ArrayLike, uv: ArrayLike, width: int, height: int) -> tuple[Camera, float]:
    """A Camera from the DLT, and its mean reprojection error in pixels."""
    P = dlt(xyz, uv)
    try:
        cam = Camera.from_P(name, P, width, height)
    except ValueError as exc:
        raise DLTError(f"camera {name}: {exc}. Check that the 2D/3D pairs correspond.") from None
    X = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    err = np.linalg.norm(cam.project(X) - np.asarray(uv, dtype=np.float64).reshape(-1, 2), axis=1)
    if np.any(~np.isfinite(err)):
        raise DLTError(f"camera {name}: some 3D points come out behind the camera; the 2D/3D pairs do not "
                       "correspond (check their order).")
    return cam, float(np.mean(err))
