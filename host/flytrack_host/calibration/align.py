"""Alignment of a calibration to the world frame by a similarity transform (Umeyama 1991).

Self-calibration is exact only up to rotation, translation and scale. Given the same physical points in
both frames (known 3D marks seen by the cameras, or measured camera centres), the least-squares
similarity Xw = s R Xc + T puts lengths in metres and z up.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from flytrack_host.geometry.camera import Camera

__all__ = ["AlignError", "Similarity", "umeyama", "align_cameras"]


class AlignError(ValueError):
    """The alignment cannot be computed; the message says what is wrong and what to do."""


@dataclass
class Similarity:
    s: float
    R: NDArray[np.float64]
    T: NDArray[np.float64]

    def apply(self, X: ArrayLike) -> NDArray[np.float64]:
        return self.s * np.atleast_2d(np.asarray(X, dtype=np.float64)) @ self.R.T + self.T

    def apply_camera(self, cam: Camera) -> Camera:
        """The same camera in the new frame: it projects apply(X) exactly where it projected X."""
        R = cam.R @ self.R.T
        t = self.s * cam.t - R @ self.T
        return Camera(name=cam.name, width=cam.width, height=cam.height, K=cam.K.copy(), R=R, t=t,
                      dist=cam.dist.copy())


def umeyama(src: ArrayLike, dst: ArrayLike, with_scale: bool = True) -> Similarity:
    """Least-squares similarity mapping src (N,3) onto dst (N,3): dst ~ s R src + T."""
    a = np.asarray(src, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(dst, dtype=np.float64).reshape(-1, 3)
    if len(a) != len(b):
        raise AlignError(f"{len(a)} source points but {len(b)} target points: give them in pairs.")
    if len(a) < 3:
        raise AlignError(f"alignment needs at least 3 point pairs (4 or more not all in a plane are better); "
                         f"got {len(a)}.")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise AlignError("alignment points contain NaN or infinity.")
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    ac, bc = a - ma, b - mb
    sv = np.linalg.svd(bc, compute_uv=False)
    if sv[1] < 1e-6 * max(sv[0], 1e-300):
        raise AlignError("the target points are (nearly) collinear, so the rotation about their line is "
                         "undetermined. Use at least 3 points that form a triangle (better: 4 not coplanar).")
    cov = bc.T @ ac / len(a)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_a = float(np.mean(np.sum(ac * ac, axis=1)))
    s = float(np.trace(np.diag(D) @ S) / var_a) if with_scale else 1.0
    T = mb - s * R @ ma
    return Similarity(s, R, T)


def align_cameras(cameras: Mapping[str, Camera], sim: Similarity) -> dict[str, Camera]:
    return {k: sim.apply_camera(c) for k, c in cameras.items()}
