"""Births of new targets from unclaimed points (seed 000 section 3.2.3).

Points no existing target claimed are triangulated over combinations of 2 .. birth_max_combination
cameras, one point per camera. A hypothesis passes when its 3D point lies in front of all its cameras
and its mean reprojection error (undistorted pixels) is at most birth_max_reproj_px. The passing
hypothesis with the most cameras (then the smallest error) starts a target; its points, and the
unclaimed points of other cameras that reproject within the threshold of it, are used up; repeat while
hypotheses remain.

Speed: all tuples of one size are triangulated in one batched SVD. A k+1-camera tuple is only tried
when it extends a passing k-camera tuple; this loses nothing in practice, because a tuple whose mean
error is under the threshold always contains a pair whose own best fit is under it too (the mean of
the pair errors at the tuple's point is at most the tuple's mean for the best pair).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from flytrack_host.tracking.association import PointSet
from flytrack_host.tracking.observation import CameraArray
from flytrack_host.tracking.params import TrackingParams

F64 = NDArray[np.float64]
_PREFILTER = 4.0  # a pair goes to the SVD when its midpoint's error is under this many thresholds


@dataclass(slots=True)
class Birth:
    position: F64  # (3,) triangulated world point
    rows: NDArray[np.intp]  # PointSet rows used (one per camera), hypothesis points first
    n_hypothesis_cameras: int
    reproj_px: float  # mean reprojection error of the hypothesis


def triangulate_batch(P: F64, uv_ideal: F64) -> F64:
    """Linear (DLT) triangulation of M points, each seen in k cameras: P (M, k, 3, 4) projection
    matrices, uv_ideal (M, k, 2) undistorted pixels -> (M, 3). Same algebra as camera.triangulate
    (row-normalised homogeneous system, smallest right singular vector), batched."""
    u = uv_ideal[..., 0, None]
    v = uv_ideal[..., 1, None]
    rows_u = u * P[..., 2, :] - P[..., 0, :]  # (M, k, 4)
    rows_v = v * P[..., 2, :] - P[..., 1, :]
    A = np.concatenate([rows_u, rows_v], axis=1)  # (M, 2k, 4)
    A /= np.linalg.norm(A, axis=2, keepdims=True)
    _, _, vt = np.linalg.svd(A)
    Xh = vt[:, -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        return Xh[:, :3] / Xh[:, 3:4]


def _evaluate(cams: CameraArray, points: PointSet, tuples: NDArray[np.intp]) -> tuple[F64, F64]:
    """Triangulate tuples (M, k) of point rows; return points (M, 3) and mean reprojection errors
    (M,), inf where the point is behind a camera or not finite."""
    M, k = tuples.shape
    slots = points.slot[tuples]  # (M, k)
    uv = np.stack([points.u_ideal[tuples], points.v_ideal[tuples]], axis=-1)
    X = triangulate_batch(cams.P[slots], uv)
    Xr = np.repeat(X, k, axis=0)
    proj, front = cams.project_ideal(slots.ravel(), np.nan_to_num(Xr))
    err = np.linalg.norm(proj - uv.reshape(-1, 2), axis=1).reshape(M, k).mean(axis=1)
    good = front.reshape(M, k).all(axis=1) & np.isfinite(X).all(axis=1) & np.isfinite(err)
    return X, np.where(good, err, np.inf)


def find_births(
    cams: CameraArray,
    points: PointSet,
    free: NDArray[np.bool_],
    params: TrackingParams,
    existing: F64 | None = None,
) -> list[Birth]:
    """Births from the points where `free` (N,) is True. `existing` (T, 3): positions of current
    targets, for params.birth_min_separation_m."""
    rows = np.flatnonzero(free)
    if rows.size < params.birth_min_cameras:
        return []
    sl = points.slot[rows]  # non-decreasing
    if 1 + int(np.count_nonzero(sl[1:] != sl[:-1])) < params.birth_min_cameras:
        return []
    thr = params.birth_max_reproj_px
    i, j = np.triu_indices(rows.size, 1)
    diff_cam = points.slot[rows[i]] != points.slot[rows[j]]
    tuples = np.stack([rows[i[diff_cam]], rows[j[diff_cam]]], axis=1)
    tuples = tuples[_midpoint_error(cams, points, tuples) <= _PREFILTER * thr]
    hyps: list[tuple[NDArray[np.intp], F64, F64]] = []  # (tuples, X, err) per size
    k = 2
    while tuples.shape[0]:
        X, err = _evaluate(cams, points, tuples)
        passed = err <= thr
        if not passed.any():
            break
        hyps.append((tuples[passed], X[passed], err[passed]))
        if k >= params.birth_max_combination:
            break
        tuples = _extend(points, tuples[passed], rows)
        k += 1
    if not hyps:
        return []

    # Greedy choice: most cameras first, then smallest error.
    cand_rows: list[NDArray[np.intp]] = []
    cand_X: list[F64] = []
    cand_err: list[float] = []
    for tup, X, err in reversed(hyps):
        order = np.argsort(err, kind="stable")
        for o in order:
            cand_rows.append(tup[o])
            cand_X.append(X[o])
            cand_err.append(float(err[o]))
    used = ~free.copy()
    births: list[Birth] = []
    min_sep = params.birth_min_separation_m
    for tup, X, err in zip(cand_rows, cand_X, cand_err, strict=True):
        if tup.size < params.birth_min_cameras or used[tup].any():
            continue
        if min_sep > 0:
            others = [existing] if existing is not None and existing.size else []
            others += [b.position[None, :] for b in births]
            if others and np.min(np.linalg.norm(np.concatenate(others) - X, axis=1)) < min_sep:
                continue
        used[tup] = True
        extra = _absorb(cams, points, used, X, tup, thr)
        used[extra] = True
        births.append(Birth(X.copy(), np.concatenate([tup, extra]), int(tup.size), err))
    return births


def _midpoint_error(cams: CameraArray, points: PointSet, pairs: NDArray[np.intp]) -> F64:
    """Cheap prefilter for pairs: the mean reprojection error of the midpoint of the two rays' closest
    approach (inf when the rays meet behind a camera). The DLT point's error is close to the optimum,
    which is never above the midpoint's; the midpoint's can exceed it by about the ratio of the two
    cameras' depths, hence the margin _PREFILTER. Saves an SVD per chance pair of false positives."""
    a, b = pairs[:, 0], pairs[:, 1]
    ca, cb = cams.centers[points.slot[a]], cams.centers[points.slot[b]]
    da, db = points.rays[a], points.rays[b]
    w = ca - cb
    aa = np.einsum("ij,ij->i", da, da)
    ab = np.einsum("ij,ij->i", da, db)
    bb = np.einsum("ij,ij->i", db, db)
    aw = np.einsum("ij,ij->i", da, w)
    bw = np.einsum("ij,ij->i", db, w)
    den = aa * bb - ab * ab
    ok = den > 1e-12 * aa * bb
    den = np.where(ok, den, 1.0)
    s = (ab * bw - bb * aw) / den
    t = (aa * bw - ab * aw) / den
    ok &= (s > 0) & (t > 0)
    X = 0.5 * (ca + s[:, None] * da + cb + t[:, None] * db)
    slots = np.concatenate([points.slot[a], points.slot[b]])
    proj, front = cams.project_ideal(slots, np.concatenate([X, X]))
    uv = np.stack([points.u_ideal[np.concatenate([a, b])], points.v_ideal[np.concatenate([a, b])]], axis=1)
    err = np.linalg.norm(proj - uv, axis=1).reshape(2, -1).mean(axis=0)
    ok &= front.reshape(2, -1).all(axis=0)
    return np.where(ok, err, np.inf)


def _extend(points: PointSet, tuples: NDArray[np.intp], rows: NDArray[np.intp]) -> NDArray[np.intp]:
    """All tuples of one more point (from a camera not yet in the tuple), without duplicates."""
    M, k = tuples.shape
    new = np.repeat(rows[None, :], M, axis=0)  # (M, R)
    cam_new = points.slot[new]
    cam_old = points.slot[tuples]  # (M, k)
    ok = (cam_new[:, :, None] != cam_old[:, None, :]).all(axis=2)
    mi, ri = np.nonzero(ok)
    if mi.size == 0:
        return np.empty((0, k + 1), dtype=np.intp)
    ext = np.concatenate([tuples[mi], new[mi, ri][:, None]], axis=1)
    ext.sort(axis=1)
    return np.unique(ext, axis=0)


def _absorb(
    cams: CameraArray, points: PointSet, used: NDArray[np.bool_], X: F64, tup: NDArray[np.intp], thr: float
) -> NDArray[np.intp]:
    """Free points of cameras outside the hypothesis lying within thr px of X's projection
    (nearest one per camera): the same animal seen by more cameras than the combination size."""
    cand = np.flatnonzero(~used)
    if cand.size == 0:
        return cand
    cand = cand[~np.isin(points.slot[cand], points.slot[tup])]
    if cand.size == 0:
        return cand
    proj, front = cams.project_ideal(points.slot[cand], np.broadcast_to(X, (cand.size, 3)))
    err = np.hypot(proj[:, 0] - points.u_ideal[cand], proj[:, 1] - points.v_ideal[cand])
    ok = front & (err <= thr)
    cand, err = cand[ok], err[ok]
    if cand.size == 0:
        return cand
    order = np.lexsort((err, points.slot[cand]))
    cand = cand[order]
    first = np.ones(cand.size, dtype=bool)
    first[1:] = points.slot[cand][1:] != points.slot[cand][:-1]
    return cand[first]
