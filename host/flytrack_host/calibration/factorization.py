"""Projective factorisation of a multi-camera measurement matrix with missing entries (Sturm & Triggs).

The views of n points in m cameras, scaled by their projective depths, form the 3m x n matrix
W = [lambda_ij x_ij], which equals P X (3m x 4 times 4 x n) and so has rank 4. Depths and missing
entries are unknown; this module finds them by alternating three steps until W stops changing:

1. balance W (each point column, then each camera's row triplet, to unit mean-square size) so that no
   camera or point dominates and the trivial solution (all depths 0) is out of reach;
2. the best rank-4 approximation of W by SVD gives P (3m x 4) and X (4 x n);
3. each observed depth becomes the one that brings lambda_ij x_ij closest to P_i X_j, and each missing
   entry of W is filled with P_i X_j (iterative rank-4 imputation, as in Svoboda's toolbox filling).

Depths start at 1 (the affine approximation); points are normalised per camera first (Hartley:
centroid at 0, mean distance sqrt 2), which the SVD needs to be well conditioned. The result is a
projective reconstruction: every P_i H, H^-1 X_j reprojects the same for any 4x4 H.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["FactorizationError", "ProjectiveReconstruction", "hartley_normalization", "projective_factorization"]

F64 = NDArray[np.float64]


class FactorizationError(ValueError):
    """The measurement matrix cannot be factorised (too few points or views); the message says why."""


@dataclass
class ProjectiveReconstruction:
    P: F64  # (m, 3, 4) projective cameras, in pixel coordinates
    X: F64  # (4, n) homogeneous points
    depths: F64  # (m, n) projective depths (NaN where the point is not seen)
    iterations: int
    change: float  # relative change of W in the last iteration
    rms_px: float  # RMS reprojection error of the observed entries, pixels
    singular_ratio: float = float("nan")  # 4th / 3rd singular value of the balanced W: ~0 for a planar scene

    def project(self) -> F64:
        """(m, n, 2) pixel projection of every point in every camera."""
        x = np.einsum("mij,jn->mni", self.P, self.X)
        with np.errstate(divide="ignore", invalid="ignore"):
            return x[..., :2] / x[..., 2:3]


def hartley_normalization(uv: F64) -> F64:
    """3x3 T moving the points' centroid to 0 and their mean distance from it to sqrt(2)."""
    c = uv.mean(axis=0)
    d = float(np.mean(np.linalg.norm(uv - c, axis=1)))
    s = np.sqrt(2.0) / d if d > 0 else 1.0
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])


def projective_factorization(uv: F64, seen: NDArray[np.bool_], max_iter: int = 300, tol: float = 1e-6,
                             ) -> ProjectiveReconstruction:
    """Projective cameras and points from uv (m, n, 2) pixels where seen (m, n) is True.

    Each point must be seen by at least 2 cameras and each camera must see at least 6 points."""
    uv = np.asarray(uv, dtype=np.float64)
    seen = np.asarray(seen, dtype=bool)
    m, n = seen.shape
    if m < 2:
        raise FactorizationError(f"projective factorisation needs at least 2 cameras, got {m}")
    if np.any(seen.sum(axis=0) < 2):
        raise FactorizationError("every point of the measurement matrix must be seen by at least 2 cameras")
    if np.any(seen.sum(axis=1) < 6) or n < 8:
        raise FactorizationError("every camera must see at least 6 points (and 8 in all) to be factorised")
    T = np.stack([hartley_normalization(uv[i][seen[i]]) for i in range(m)])
    xh = np.concatenate([uv, np.ones((m, n, 1))], axis=2)
    xn = np.einsum("mij,mnj->mni", T, xh)  # (m, n, 3) normalised homogeneous image points
    xn[~seen] = 0.0
    lam = seen.astype(float)
    fill = np.zeros((m, n, 3))  # current estimate P_i X_j, used where the point is not seen
    W = np.where(seen[..., None], lam[..., None] * xn, fill)
    change = np.inf
    done = 0
    for _ in range(max_iter):
        done += 1
        # 1. balance: columns (points), then row triplets (cameras), to unit mean square per entry.
        col = np.sqrt(np.sum(W * W, axis=(0, 2)) / m)
        W = W / np.where(col > 0, col, 1.0)[None, :, None]
        row = np.sqrt(np.sum(W * W, axis=(1, 2)) / n)
        W = W / np.where(row > 0, row, 1.0)[:, None, None]
        # 2. rank 4.
        M = W.transpose(0, 2, 1).reshape(3 * m, n)
        # Leading 4 left singular vectors from the small 3m x 3m Gram matrix (n >> 3m): same subspace as
        # the SVD of M, at a fraction of the cost.
        ev, V = np.linalg.eigh(M @ M.T)
        Pm = V[:, -4:]
        X = Pm.T @ M
        R = (Pm @ X).reshape(m, 3, n).transpose(0, 2, 1)  # (m, n, 3) rank-4 estimate of W
        # 3. depths of the observed entries (least squares along the ray), fill of the missing ones.
        num = np.sum(R * xn, axis=2)
        den = np.sum(xn * xn, axis=2)
        lam = np.where(seen, num / np.where(den > 0, den, 1.0), 0.0)
        W_new = np.where(seen[..., None], lam[..., None] * xn, R)
        change = float(np.linalg.norm(W_new - W) / max(np.linalg.norm(W), 1e-300))
        W = W_new
        if change < tol:
            break
    P = np.linalg.solve(T, Pm.reshape(m, 3, 4))  # undo the normalisation: pixel-coordinate cameras
    P /= np.linalg.norm(P, axis=(1, 2), keepdims=True)
    rec = ProjectiveReconstruction(P=P, X=X, depths=np.where(seen, lam, np.nan), iterations=done, change=change,
                                   rms_px=float("nan"),
                                   singular_ratio=float(np.sqrt(max(ev[-4], 0.0) / max(ev[-3], 1e-300))))
    err = np.linalg.norm(rec.project() - uv, axis=2)[seen]
    rec.rms_px = float(np.sqrt(np.mean(err * err)))
    return rec
