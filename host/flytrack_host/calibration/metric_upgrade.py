"""Euclidean (metric) upgrade of a projective reconstruction through the absolute dual quadric.

A projective reconstruction (P_i, X_j) differs from a metric one by an unknown 4x4 H: P_i H = K_i [R_i|t_i].
The absolute dual quadric Q* (a symmetric 4x4 of rank 3) projects into every image as the dual image of
the absolute conic, w*_i = P_i Q* P_i^T ~ K_i K_i^T. Once the pixels are normalised with a guessed
focal length f0 and the image centre (x' = (x - c) / f0), cameras with zero skew, square pixels and a
principal point near the centre have w*_i ~ diag(a, a, 1). That gives equations linear in the 10
entries of Q* (Pollefeys et al.; the weights say how much each assumption can be trusted):

    w*_12 = 0 (zero skew), w*_11 = w*_22 (square pixels), w*_13 = w*_23 = 0 (principal point at the
    centre), and weakly w*_11 = w*_33, w*_22 = w*_33 (focal length near the guess; in later rounds near
the previous round's estimate, so that the prior does not bias an otherwise exact solution).

The least-squares Q* is made rank 3 by its eigen-decomposition Q* = V diag(d) V^T (smallest |d| set to
zero); then H = V diag(sqrt|d1|, sqrt|d2|, sqrt|d3|, 1) satisfies Q* = H diag(1,1,1,0) H^T, so P_i H are
metric cameras and H^-1 X_j metric points, up to a similarity (and, as for any Q*, a mirror image: the
one that puts the points in front of the cameras is kept).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["MetricUpgradeError", "MetricReconstruction", "metric_upgrade"]

F64 = NDArray[np.float64]
_IU = np.triu_indices(4)


class MetricUpgradeError(ValueError):
    """No metric upgrade could be found; the message says why."""


@dataclass
class MetricReconstruction:
    P: F64  # (m, 3, 4) metric cameras, pixel coordinates, sign chosen so that points are in front
    X: F64  # (n, 3) metric points
    H: F64  # (4, 4) the upgrade applied to the input: P_metric ~ P H, X_metric ~ H^-1 X
    eigenvalues: F64  # (4,) of the least-squares Q* (before the rank-3 projection), largest |d| first
    in_front: float  # fraction of the observed points that are in front of their cameras


def _omega_rows(P: F64) -> dict[tuple[int, int], F64]:
    """Coefficients of entry (a, b) of P Q P^T in the 10 upper-triangle unknowns of Q."""
    out = {}
    for a in range(3):
        for b in range(a, 3):
            C = np.outer(P[a], P[b])
            C = C + C.T - np.diag(np.diag(C))  # Q is symmetric: Q_kl = Q_lk counted once (k <= l)
            out[(a, b)] = C[_IU]
    return out


def _q_from_vec(q: F64) -> F64:
    Q = np.zeros((4, 4))
    Q[_IU] = q
    return Q + Q.T - np.diag(np.diag(Q))


def metric_upgrade(P: F64, X: F64, sizes: Sequence[tuple[int, int]], focal_guess: Sequence[float],
                   seen: NDArray[np.bool_] | None = None, rounds: int = 4) -> MetricReconstruction:
    """Upgrade projective cameras P (m, 3, 4, pixel coordinates) and points X (4, n) to a metric frame."""
    P = np.asarray(P, dtype=np.float64)
    X = np.asarray(X, dtype=np.float64)
    m = len(P)
    if m < 3:
        raise MetricUpgradeError(f"the metric upgrade needs at least 3 cameras (it has {m}): with 2, the "
                                 "focal lengths are not determined. Use an intrinsics file or add cameras.")
    # Condition the projective frame: rows of G^-1 X orthonormal (times sqrt n).
    U, s, _ = np.linalg.svd(X, full_matrices=False)
    G = U * (s / np.sqrt(X.shape[1]))
    Pn = []
    for Pi, (w, h), f0 in zip(P, sizes, focal_guess, strict=True):
        N = np.array([[1.0 / f0, 0.0, -(w - 1) / 2.0 / f0], [0.0, 1.0 / f0, -(h - 1) / 2.0 / f0], [0.0, 0.0, 1.0]])
        Q = N @ Pi @ G
        Pn.append(Q / np.linalg.norm(Q))
    nu = np.ones(m)  # scale of w*_33 per camera, refined in each round so the weights mean pixels / f0
    a = np.ones(m)  # (f / f0)^2 per camera: the focal prior starts at the guess, then follows the estimate
    Qs = np.eye(4)
    d = np.zeros(4)
    for _ in range(rounds):
        rows = []
        for i, Pi in enumerate(Pn):
            o = _omega_rows(Pi)
            rows += [o[(0, 1)] / (0.01 * nu[i]),  # skew
                     (o[(0, 0)] - o[(1, 1)]) / (0.05 * nu[i]),  # square pixels
                     o[(0, 2)] / (0.1 * nu[i]), o[(1, 2)] / (0.1 * nu[i]),  # principal point near the centre
                     (o[(0, 0)] - a[i] * o[(2, 2)]) / (9.0 * nu[i]),  # focal length near the guess, then
                     (o[(1, 1)] - a[i] * o[(2, 2)]) / (9.0 * nu[i])]  # near the last round's (no bias on exact data)
        A = np.asarray(rows)
        _, _, Vt = np.linalg.svd(A)
        Qs = _q_from_vec(Vt[-1])
        om33 = np.array([Pi[2] @ Qs @ Pi[2] for Pi in Pn])
        if np.sum(om33 > 0) < m / 2:
            Qs, om33 = -Qs, -om33
        nu = np.maximum(np.abs(om33), 1e-12)
        om_f = np.array([(Pi[0] @ Qs @ Pi[0] + Pi[1] @ Qs @ Pi[1]) / 2 for Pi in Pn]) / nu
        a = np.where(om_f > 0, om_f, a)
    d, V = np.linalg.eigh(Qs)
    order = np.argsort(-np.abs(d))
    d, V = d[order], V[:, order]
    if np.sum(d[:3] > 0) < 3:
        raise MetricUpgradeError("the absolute dual quadric is not positive semi-definite: the projective "
                                 "reconstruction or the camera assumptions (square pixels, centred principal "
                                 "point) are badly off. Give a focal length guess or an intrinsics file.")
    H = np.column_stack([V[:, :3] * np.sqrt(d[:3]), V[:, 3]])
    Hf = G @ H
    Xm = np.linalg.solve(Hf, X)
    best: MetricReconstruction | None = None
    # H and H diag(1,1,1,-1) are both upgrades (a point reflection apart): keep the one in front.
    for flip in (1.0, -1.0):
        F = np.diag([1.0, 1.0, 1.0, flip])
        Pm = np.einsum("mij,jk->mik", P, Hf @ F)
        Xh = F @ Xm
        with np.errstate(divide="ignore", invalid="ignore"):
            Xe = (Xh[:3] / Xh[3]).T
        sgn = np.sign(np.linalg.det(Pm[:, :, :3]))
        Pm = Pm * sgn[:, None, None]  # det of the left 3x3 block > 0: depth = third row . [X, 1]
        depth = np.einsum("mj,nj->mn", Pm[:, 2, :3], Xe) + Pm[:, 2, 3][:, None]
        mask = np.ones(depth.shape, dtype=bool) if seen is None else np.asarray(seen, dtype=bool)
        front = float(np.mean(depth[mask] > 0))
        if best is None or front > best.in_front:
            best = MetricReconstruction(P=Pm, X=Xe, H=Hf @ F, eigenvalues=d, in_front=front)
    assert best is not None
    return best
