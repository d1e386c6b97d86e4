"""Data association by the nearest-neighbour standard filter (seed 000 section 3.2), vectorised.

For each target and camera the chosen point maximises the likelihood of eq. 3.13,
    p(z | target) = 1[dist2d < gate] * 1[area ok] * exp(-d_mahal(a, a_bar)),
where dist2d is the image distance from the point to the target's predicted (distorted) projection,
the area test compares the point's area with the target's running area, and d_mahal is the
Mahalanobis distance, under the predicted position covariance, from the predicted position a_bar to
the closest point a on the point's camera ray. Maximising exp(-d) is minimising d, so costs below are d.

All (point, target) pairs of a frame are evaluated in one batch. Each camera gives a target at most
one point. Then either (exclusive_points) a point feeds at most one target, clashes being settled per
camera by scipy's linear_sum_assignment over the summed d, or (flydra's way) targets choose
independently and the merge-prevention rule of section 3.2.1 runs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from flytrack_host.tracking.params import TrackingParams

F64 = NDArray[np.float64]
_BIG = 1e12


@dataclass(slots=True)
class PointSet:
    """The finite points of one frame from all cameras, concatenated in camera-slot order."""

    slot: NDArray[np.intp]  # (N,) camera slot of each point (non-decreasing)
    index: NDArray[np.intp]  # (N,) index of the point in its camera's detection array
    u: F64  # distorted pixel coordinates
    v: F64
    u_ideal: F64  # undistorted (pinhole) pixel coordinates
    v_ideal: F64
    area: F64
    orientation: F64  # radians, NaN when unknown
    eccentricity: F64  # NaN when unknown
    starts: NDArray[np.intp]  # (C + 1,) points of slot c are [starts[c], starts[c + 1])
    rays: F64  # (N, 3) world ray directions through (u_ideal, v_ideal), not normalised
    uv: F64  # (N, 2) (u, v) together
    orientation_ok: NDArray[np.bool_]  # (N,) angle known and the point elongated enough to use it
    rank: NDArray[np.intp]  # (N,) position of the point among its camera's rows of this set
    max_per_camera: int  # the most points any camera has in this set
    # (N, 3) where each point's ray line starts: None = its camera's centre; set for refractive cameras,
    # whose lines start on the interface (CameraArray.ray_lines).
    origins: F64 | None = None

    @property
    def n(self) -> int:
        return int(self.slot.shape[0])


@dataclass(slots=True)
class AssociationResult:
    assign: NDArray[np.intp]  # (C, T) point row in the PointSet, or -1
    cost: F64  # (C, T) Mahalanobis distance of the chosen point (inf where none)
    conflicts_resolved: int  # cameras where targets clashed over a point and the choice was global
    merges_prevented: int  # targets stripped of their points by the merge-prevention rule


def inv3(M: F64) -> F64:
    """Inverses of a stack of 3x3 matrices (..., 3, 3) by the adjugate: a few elementwise NumPy
    operations, much cheaper than np.linalg.inv's per-call overhead for a handful of matrices."""
    m = M.reshape(M.shape[:-2] + (9,))
    a, b, c, d, e, f, g, h, i = (m[..., k] for k in range(9))
    co_a, co_b, co_c = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * co_a + b * co_b + c * co_c
    out = np.stack(
        [co_a, c * h - b * i, b * f - c * e, co_b, a * i - c * g, c * d - a * f, co_c, b * g - a * h, a * e - b * d],
        axis=-1,
    )
    with np.errstate(divide="ignore", invalid="ignore"):  # singular: inf/NaN, by design (see below)
        return (out / det[..., None]).reshape(M.shape)


def ray_mahalanobis(mean: F64, cov_pos: F64, origins: F64, dirs: F64) -> F64:
    """Mahalanobis distance (N, T) from each target's mean (T, 3), covariance (T, 3, 3), to the
    closest point of each ray origins (N, 3) + s * dirs (N, 3).

    Minimising (o + s d - m)^T A (o + s d - m) over s (A = inverse covariance) gives
    d^2 = w^T A w - (d^T A w)^2 / (d^T A d) with w = m - o (seed 000, below eq. 3.12).
    """
    try:
        A = np.linalg.inv(cov_pos)  # (T, 3, 3), covariances are kept positive definite
    except np.linalg.LinAlgError:
        A = inv3(cov_pos)  # a singular one gives inf/NaN distances, which the gates refuse
    w = mean[None, :, :] - origins[:, None, :]  # (N, T, 3)
    Aw = (A[None] @ w[..., None])[..., 0]
    Ad = (A[None] @ dirs[:, None, :, None])[..., 0]  # (N, T, 3)
    wAw = np.einsum("ntk,ntk->nt", w, Aw)
    dAw = np.einsum("nk,ntk->nt", dirs, Aw)
    dAd = np.einsum("nk,ntk->nt", dirs, Ad)
    d2 = wAw - dAw * dAw / dAd
    return np.sqrt(np.maximum(d2, 0.0))


def associate(
    points: PointSet,
    n_cameras: int,
    pred_uv: F64,
    front: NDArray[np.bool_],
    mean: F64,
    cov_pos: F64,
    target_area: F64,
    centers: F64,
    params: TrackingParams,
) -> AssociationResult:
    """Choose, for every target and camera, at most one point (see the module docstring).

    pred_uv (C, T, 2) and front (C, T): predicted distorted projections and in-front mask;
    mean (T, 3), cov_pos (T, 3, 3): predicted positions and their covariance; target_area (T,);
    centers (C, 3): camera centres.
    """
    T = mean.shape[0]
    assign = np.full((n_cameras, T), -1, dtype=np.intp)
    best = np.full((n_cameras, T), np.inf)
    if T == 0 or points.n == 0:
        return AssociationResult(assign, best, 0, 0)
    slot = points.slot
    d = points.uv[:, None, :] - pred_uv[slot]  # (N, T, 2)
    d2d_sq = np.einsum("ntk,ntk->nt", d, d)
    ok = front[slot]
    ok &= d2d_sq < params.gate_px**2
    ratio = points.area[:, None] / target_area
    r = params.area_gate_ratio
    ok &= ratio < r
    ok &= ratio > 1.0 / r
    if params.min_area_px > 0:  # at 0, ratio > 1 / r > 0 already implies area > 0 (or no target area)
        ok &= points.area[:, None] > params.min_area_px
    if not ok.any():
        return AssociationResult(assign, best, 0, 0)
    origins = centers[slot] if points.origins is None else points.origins
    dm = ray_mahalanobis(mean, cov_pos, origins, points.rays)
    ok &= dm < params.max_mahalanobis
    cost = np.where(ok, dm, np.inf)

    # Pad to (camera, point-in-camera, target) so one argmin picks each camera's nearest neighbour.
    padded = np.full((n_cameras, points.max_per_camera, T), np.inf)
    padded[slot, points.rank] = cost
    j = np.argmin(padded, axis=1)  # (C, T)
    best = padded.min(axis=1)  # the value at j
    found = np.isfinite(best)
    assign = np.where(found, points.starts[:-1, None] + j, -1)

    conflicts = merges = 0
    if params.exclusive_points:
        chosen = assign[found]
        if T > 1 and chosen.size > 1 and np.bincount(chosen, minlength=points.n).max() > 1:
            for c in range(n_cameras):
                row = assign[c][assign[c] >= 0]
                if row.size > 1 and np.unique(row).size < row.size:
                    conflicts += 1
                    _assign_camera_globally(c, padded[c], points.starts[c], assign, best)
    else:
        merges = _prevent_merges(assign, d2d_sq, best)
    return AssociationResult(assign, best, conflicts, merges)


def _assign_camera_globally(c: int, cost_c: F64, start: int, assign: NDArray[np.intp], best: F64) -> None:
    """One camera: a one-to-one choice of points for targets minimising the summed distance."""
    rows = np.flatnonzero(np.isfinite(cost_c).any(axis=1))
    cols = np.flatnonzero(np.isfinite(cost_c).any(axis=0))
    sub = cost_c[np.ix_(rows, cols)]
    r_i, c_i = linear_sum_assignment(np.where(np.isfinite(sub), sub, _BIG))
    assign[c, :] = -1
    best[c, :] = np.inf
    for ri, ci in zip(r_i, c_i, strict=True):
        if np.isfinite(sub[ri, ci]):  # a target left with only a _BIG stand-in gets none
            assign[c, cols[ci]] = start + rows[ri]
            best[c, cols[ci]] = sub[ri, ci]


def _prevent_merges(assign: NDArray[np.intp], d2d_sq: F64, best: F64) -> int:
    """Seed 000 section 3.2.1: targets holding the exact same non-empty set of points keep them
    only for the target whose predicted observations are closest to them; the others go without."""
    T = assign.shape[1]
    groups: dict[bytes, list[int]] = {}
    for t in range(T):
        col = assign[:, t]
        if (col >= 0).any():
            groups.setdefault(col.tobytes(), []).append(t)
    stripped = 0
    for members in groups.values():
        if len(members) < 2:
            continue
        col = assign[:, members[0]]
        rows = col[col >= 0]
        # Image distance from each member's prediction to the shared points, summed over cameras.
        dist = np.sqrt(d2d_sq[rows][:, members]).sum(axis=0)
        keep = members[int(np.argmin(dist))]
        for t in members:
            if t != keep:
                assign[:, t] = -1
                best[:, t] = np.inf
                stripped += 1
    return stripped
