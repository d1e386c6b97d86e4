"""Births of new targets from unclaimed points (seed 000 section 3.2.3), bounded per frame.

The paper triangulates every combination of 2 .. n cameras; with 10 newcomers in 11 cameras that is
hundreds of thousands of hypotheses. Here the search is guided instead, with the same acceptance test:

1. Seeds: pairs of unclaimed points from two cameras whose Sampson distance (the first-order
   reprojection error of the best 3D point for the pair, from the pair's fundamental matrix,
   CameraArray.fundamental, on undistorted pixels) is at most birth_max_reproj_px * _SEED_GATE.
   and whose rays come closest in front of both cameras. A pair passing on its own has a Sampson
   distance of about twice its mean error at most (e_a + e_b <= 2 thr gives sqrt(e_a^2 + e_b^2) <=
   2 thr); _SEED_GATE = 2.5 leaves a margin over that.
   Seeds are ranked by Sampson distance and at most birth_max_hypotheses are evaluated per frame:
   the rest wait for the next frame (their points stay unclaimed, so a birth is at most a frame late).
2. Each seed is triangulated (DLT) and projected into every other camera; the nearest unclaimed point
   there within _EXTEND_GATE * threshold joins it, nearest cameras first, up to birth_max_combination
   cameras in all. The hypothesis is triangulated again (DLT over its cameras, one stacked SVD for all
   hypotheses, absent cameras as zero rows) and passes when its point lies in front of all its
   cameras and its mean reprojection error (undistorted pixels) is at most birth_max_reproj_px; when
   the extended hypothesis fails, the seed pair alone may pass.
3. Greedy choice: most hypothesis cameras, then most further cameras that see the point within the
   threshold (so a chance match of a few points loses to a real animal seen by all cameras), then the
   smallest error. An accepted hypothesis starts a target; its points, and the nearest unclaimed point
   of each other camera within the threshold, are used up. Hypotheses that lost a point to an
   accepted one are evaluated again on the points left (next round), within the same budget.
With refractive cameras (CameraArray.refractive) epipolar geometry does not hold: seeds are gated by
the reprojection error of the midpoint of the two refracted rays instead of the Sampson distance, and
hypotheses are triangulated as the least-squares point of their refracted rays (refraction.py).
The C kernel's birth prefilter (kernel/tracker_kernel.c) applies the same seed gate, so the NumPy
birth search only runs when some seed exists (both paths make the same births).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from flytrack_host.geometry.refraction import triangulate_rays
from flytrack_host.tracking.association import PointSet
from flytrack_host.tracking.observation import CameraArray
from flytrack_host.tracking.params import TrackingParams

F64 = NDArray[np.float64]
# Seed gate (Sampson distance of a pair) and extension gate (px from the seed's projection), in units
# of birth_max_reproj_px. The kernel mirrors the seed gate (kernel.py: birth_seed_gate_px).
_SEED_GATE = 2.5
_EXTEND_GATE = 4.0
# Seeds evaluated together (one batch of NumPy calls); rounds repeat on the points left, up to
# birth_max_hypotheses seeds per frame.
_CHUNK = 64


@dataclass(slots=True)
class Birth:
    position: F64  # (3,) triangulated world point
    rows: NDArray[np.intp]  # PointSet rows used (one per camera), hypothesis points first
    n_hypothesis_cameras: int
    reproj_px: float  # mean reprojection error of the hypothesis


@dataclass(slots=True)
class BirthSearch:
    """What one frame's search did (Tracker.stats sums these)."""

    births: list[Birth]
    evaluated: int = 0  # hypotheses (seeds) evaluated
    deferred: int = 0  # seeds left for the next frame by the budget


def triangulate_batch(P: F64, uv_ideal: F64, mask: NDArray[np.bool_] | None = None) -> F64:
    """Linear (DLT) triangulation of M points, each seen in k cameras: P (M, k, 3, 4) projection
    matrices, uv_ideal (M, k, 2) undistorted pixels -> (M, 3). Same algebra as camera.triangulate
    (row-normalised homogeneous system, smallest right singular vector), batched. With mask (M, k),
    cameras where it is False are left out (their rows are zero, which does not change the solution)."""
    u = uv_ideal[..., 0, None]
    v = uv_ideal[..., 1, None]
    rows_u = u * P[..., 2, :] - P[..., 0, :]  # (M, k, 4)
    rows_v = v * P[..., 2, :] - P[..., 1, :]
    A = np.concatenate([rows_u, rows_v], axis=1)  # (M, 2k, 4)
    norm = np.linalg.norm(A, axis=2, keepdims=True)
    if mask is not None:
        m2 = np.concatenate([mask, mask], axis=1)[..., None]
        A = np.where(m2, A / np.where(m2, norm, 1.0), 0.0)
    else:
        A /= norm
    _, _, vt = np.linalg.svd(A)
    Xh = vt[:, -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        return Xh[:, :3] / Xh[:, 3:4]


def seed_pairs(cams: CameraArray, points: PointSet, rows: NDArray[np.intp], gate_px: float) -> tuple[
        NDArray[np.intp], F64]:
    """Pairs (S, 2) of `rows` (two cameras, first row lower) whose Sampson distance is at most gate_px,
    best first, and those distances (S,)."""
    i, j = np.triu_indices(rows.size, 1)
    sl = points.slot[rows]
    keep = sl[i] != sl[j]
    a, b = rows[i[keep]], rows[j[keep]]
    if cams.refractive:
        d2, ok = _pair_error2_refractive(cams, points, a, b)
        a, b, d2 = a[ok], b[ok], d2[ok]
        ok = d2 <= gate_px * gate_px
        a, b, d2 = a[ok], b[ok], d2[ok]
        order = np.argsort(d2, kind="stable")
        return np.stack([a[order], b[order]], axis=1), np.sqrt(d2[order])
    d2 = sampson2(cams, points, a, b)
    ok = d2 <= gate_px * gate_px
    a, b, d2 = a[ok], b[ok], d2[ok]
    ok = in_front(cams, points, a, b)
    a, b, d2 = a[ok], b[ok], d2[ok]
    order = np.argsort(d2, kind="stable")
    return np.stack([a[order], b[order]], axis=1), np.sqrt(d2[order])


def sampson2(cams: CameraArray, points: PointSet, a: NDArray[np.intp], b: NDArray[np.intp]) -> F64:
    """Squared Sampson distance (px^2) of point pairs (a[k], b[k]) from different cameras:
    (x_b' F x_a)^2 / (|(F x_a)_12|^2 + |(F' x_b)_12|^2), undistorted pixels."""
    F = cams.fundamental[points.slot[a], points.slot[b]]  # (S, 3, 3): x_b' F x_a = 0
    ua, va, ub, vb = points.u_ideal[a], points.v_ideal[a], points.u_ideal[b], points.v_ideal[b]
    la = F[:, :, 0] * ua[:, None] + F[:, :, 1] * va[:, None] + F[:, :, 2]  # line F x_a in b
    lb = F[:, 0, :] * ub[:, None] + F[:, 1, :] * vb[:, None] + F[:, 2, :]  # line F' x_b in a
    num = la[:, 0] * ub + la[:, 1] * vb + la[:, 2]
    den = la[:, 0] ** 2 + la[:, 1] ** 2 + lb[:, 0] ** 2 + lb[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        d2 = num * num / den
    return np.where(np.isfinite(d2), d2, np.inf)


def _pair_error2_refractive(
    cams: CameraArray, points: PointSet, a: NDArray[np.intp], b: NDArray[np.intp]
) -> tuple[F64, NDArray[np.bool_]]:
    """Refractive cameras: squared reprojection error (summed over both cameras, undistorted px) of
    the midpoint of the rays of points a[k] and b[k], and whether the rays meet in front of both."""
    oa, ob = _origins(cams, points, a), _origins(cams, points, b)
    da, db = points.rays[a], points.rays[b]
    w = oa - ob
    aa = np.einsum("ij,ij->i", da, da)
    ab = np.einsum("ij,ij->i", da, db)
    bb = np.einsum("ij,ij->i", db, db)
    aw = np.einsum("ij,ij->i", da, w)
    bw = np.einsum("ij,ij->i", db, w)
    den = aa * bb - ab * ab
    s_num, t_num = ab * bw - bb * aw, aa * bw - ab * aw
    ok = (den > 0) & (s_num > 0) & (t_num > 0)
    den = np.where(ok, den, 1.0)
    X = 0.5 * (oa + da * (s_num / den)[:, None] + ob + db * (t_num / den)[:, None])
    pa, fa = cams.project_ideal(points.slot[a], X)
    pb, fb = cams.project_ideal(points.slot[b], X)
    e2 = (pa[:, 0] - points.u_ideal[a]) ** 2 + (pa[:, 1] - points.v_ideal[a]) ** 2
    e2 += (pb[:, 0] - points.u_ideal[b]) ** 2 + (pb[:, 1] - points.v_ideal[b]) ** 2
    ok &= fa & fb & np.isfinite(e2)
    return np.where(ok, e2, np.inf), ok


def _origins(cams: CameraArray, points: PointSet, rows: NDArray[np.intp]) -> F64:
    return cams.centers[points.slot[rows]] if points.origins is None else points.origins[rows]


def triangulate_points(
    cams: CameraArray, points: PointSet, rows: NDArray[np.intp], mask: NDArray[np.bool_] | None = None
) -> F64:
    """Triangulate M points from PointSet rows (M, k) (mask (M, k): rows used): DLT on undistorted
    pixels, or for refractive cameras the least-squares point of the refracted rays weighted by
    1 / distance^2 (so it approximates the angular error)."""
    uv = np.stack([points.u_ideal[rows], points.v_ideal[rows]], axis=-1)
    if not cams.refractive:
        return triangulate_batch(cams.P[points.slot[rows]], uv, mask)
    o, d = _origins(cams, points, rows), points.rays[rows]
    w = np.ones(rows.shape) if mask is None else mask.astype(np.float64)
    X = triangulate_rays(o, d, w)
    c = cams.centers[points.slot[rows]]
    dist2 = np.sum((np.nan_to_num(X)[:, None, :] - c) ** 2, axis=-1)
    return triangulate_rays(o, d, w / np.maximum(dist2, 1e-12))


def in_front(cams: CameraArray, points: PointSet, a: NDArray[np.intp], b: NDArray[np.intp]) -> NDArray[np.bool_]:
    """Whether the rays of points a[k] and b[k] come closest in front of both cameras (the epipolar
    constraint holds along the whole line, half of which images points behind a camera)."""
    ca, cb = cams.centers[points.slot[a]], cams.centers[points.slot[b]]
    da, db = points.rays[a], points.rays[b]
    w = ca - cb
    aa = np.einsum("ij,ij->i", da, da)
    ab = np.einsum("ij,ij->i", da, db)
    bb = np.einsum("ij,ij->i", db, db)
    aw = np.einsum("ij,ij->i", da, w)
    bw = np.einsum("ij,ij->i", db, w)
    # Closest points ca + s da and cb + t db: s, t times the (positive) determinant aa bb - ab^2.
    return (ab * bw - bb * aw > 0) & (aa * bw - ab * aw > 0)


def find_births(
    cams: CameraArray,
    points: PointSet,
    free: NDArray[np.bool_],
    params: TrackingParams,
    existing: F64 | None = None,
) -> list[Birth]:
    """Births from the points where `free` (N,) is True. `existing` (T, 3): positions of current
    targets, for params.birth_min_separation_m."""
    return search_births(cams, points, free, params, existing).births


def search_births(
    cams: CameraArray,
    points: PointSet,
    free: NDArray[np.bool_],
    params: TrackingParams,
    existing: F64 | None = None,
) -> BirthSearch:
    """find_births with the work it did (hypotheses evaluated, seeds deferred by the budget)."""
    out = BirthSearch([])
    rows = np.flatnonzero(free)
    if rows.size < params.birth_min_cameras:
        return out
    sl = points.slot[rows]  # non-decreasing
    if 1 + int(np.count_nonzero(sl[1:] != sl[:-1])) < params.birth_min_cameras:
        return out
    # The seed gate depends on the pair only: scored once, then rounds take the best seeds whose
    # points are still free.
    seeds, _ = seed_pairs(cams, points, rows, _SEED_GATE * params.birth_max_reproj_px)
    budget = params.birth_max_hypotheses
    used = ~free
    while seeds.shape[0]:
        if budget == 0:
            out.deferred = seeds.shape[0]
            break
        take = min(_CHUNK, budget)
        batch, seeds = seeds[:take], seeds[take:]
        budget -= batch.shape[0]
        out.evaluated += batch.shape[0]
        _round(cams, points, used, np.flatnonzero(~used), batch, params, existing, out.births)
        if seeds.shape[0]:
            seeds = seeds[~used[seeds].any(axis=1)]
    return out


def _round(
    cams: CameraArray,
    points: PointSet,
    used: NDArray[np.bool_],
    rows: NDArray[np.intp],
    seeds: NDArray[np.intp],
    params: TrackingParams,
    existing: F64 | None,
    births: list[Birth],
) -> None:
    """Evaluate the seeds over the free points `rows`, accept greedily (marking `used`, appending to
    births). A passing hypothesis that lost a point to an accepted one is skipped: its seed is not
    tried again this frame, but later seeds over its free points are (next round)."""
    thr = params.birth_max_reproj_px
    kmax = max(2, min(params.birth_max_combination, cams.n))
    M = seeds.shape[0]
    C = cams.n
    slot = points.slot
    # Free points as a dense (camera, rank) table, flattened, for per-camera nearest-neighbour look-ups.
    fs = slot[rows]
    starts = np.searchsorted(fs, np.arange(C + 1))
    width = int(np.diff(starts).max())
    cell = fs * width + (np.arange(rows.size) - starts[fs])
    fu, fv = points.u_ideal[rows], points.v_ideal[rows]
    Pm = cams.P
    cams_ix = np.arange(C)

    def nearest(X: F64, exclude: NDArray[np.intp]) -> tuple[F64, NDArray[np.intp]]:
        """For points X (M, 3): per camera the distance (M, C) to the nearest free point and its row
        (inf / -1 where none or X is behind the camera); cameras in exclude (M, k, -1 = none) skipped.
        Written elementwise: tiny matrix products through BLAS cost more in call overhead."""
        if cams.refractive:
            pu, front = cams.project_ideal_all(X)  # (M, C, 2)
            h = np.concatenate([pu, np.ones(front.shape)[..., None]], axis=-1)
        else:
            h = X[:, 0, None, None] * Pm[:, :, 0] + X[:, 1, None, None] * Pm[:, :, 1]
            h += X[:, 2, None, None] * Pm[:, :, 2] + Pm[:, :, 3]  # (M, C, 3)
            front = h[..., 2] > 1e-9
        w = h[..., 2]
        wi = 1.0 / np.where(front, w, 1.0)
        du = (h[..., 0] * wi)[:, fs] - fu  # (M, R)
        dv = (h[..., 1] * wi)[:, fs] - fv
        d = np.sqrt(du * du + dv * dv)
        d[~front[:, fs]] = np.inf
        dense = np.full((X.shape[0], C * width), np.inf)
        dense[:, cell] = d
        dense = dense.reshape(X.shape[0], C, width)
        k = np.argmin(dense, axis=2)  # (M, C)
        dmin = np.take_along_axis(dense, k[..., None], axis=2)[..., 0]
        dmin[(exclude[:, :, None] == cams_ix).any(axis=1)] = np.inf
        near = rows[np.minimum(starts[:C] + k, rows.size - 1)]
        return dmin, np.where(np.isfinite(dmin), near, -1)

    # 1. Seeds triangulated, extended by the nearest free points of the other cameras.
    sa, sb = slot[seeds[:, 0]], slot[seeds[:, 1]]
    X2 = triangulate_points(cams, points, seeds)
    X2 = np.where(np.isfinite(X2), X2, 0.0)
    hyp = np.full((M, kmax), -1, dtype=np.intp)
    hyp[:, :2] = seeds
    if kmax > 2:
        dmin, near = nearest(X2, np.stack([sa, sb], axis=1))
        order = np.argsort(dmin, axis=1, kind="stable")[:, : kmax - 2]
        dsel = np.take_along_axis(dmin, order, axis=1)
        hyp[:, 2:] = np.where(dsel <= _EXTEND_GATE * thr, np.take_along_axis(near, order, axis=1), -1)
    X, err, n_hyp = _fit(cams, points, hyp)
    # The seed pair alone where the extended hypothesis fails.
    if kmax > 2:
        err2 = _errors(cams, points, seeds, X2)
        back = (err > thr) & (err2 <= thr)
        if back.any():
            hyp[back, 2:] = -1
            X[back], err[back], n_hyp[back] = X2[back], err2[back], 2
    ok = (err <= thr) & (n_hyp >= params.birth_min_cameras)
    if not ok.any():
        return
    hyp, X, err, n_hyp = hyp[ok], X[ok], err[ok], n_hyp[ok]
    # 2. Support: further cameras whose nearest free point lies within the threshold.
    dmin, _ = nearest(X, np.where(hyp >= 0, slot[np.maximum(hyp, 0)], -1))
    support = np.count_nonzero(dmin <= thr, axis=1)
    order = np.lexsort((err, -support, -n_hyp))
    # 3. Greedy acceptance (plain Python lists: a few hundred tiny checks).
    min_sep = params.birth_min_separation_m
    hyp_l = hyp.tolist()
    used_l = used.tolist()
    for o in order.tolist():
        tup_l = [r for r in hyp_l[o] if r >= 0]
        if any(used_l[r] for r in tup_l):
            continue
        Xo = X[o]
        if min_sep > 0:
            others = [existing] if existing is not None and existing.size else []
            others += [b.position[None, :] for b in births]
            if others and np.min(np.linalg.norm(np.concatenate(others) - Xo, axis=1)) < min_sep:
                continue
        tup = np.array(tup_l, dtype=np.intp)
        used[tup] = True
        extra = _absorb(cams, points, used, Xo, tup, thr)
        used[extra] = True
        for r in tup_l + extra.tolist():
            used_l[r] = True
        births.append(Birth(Xo.copy(), np.concatenate([tup, extra]), int(tup.size), float(err[o])))


def _fit(cams: CameraArray, points: PointSet, hyp: NDArray[np.intp]) -> tuple[F64, F64, NDArray[np.intp]]:
    """DLT over each hypothesis's points (rows of hyp, -1 = none): points (M, 3), mean reprojection
    errors (M,) (inf where behind a camera or not finite) and camera counts (M,)."""
    mask = hyp >= 0
    r = np.where(mask, hyp, 0)
    X = triangulate_points(cams, points, r, mask)
    return X, _errors(cams, points, hyp, X), mask.sum(axis=1)


def _errors(cams: CameraArray, points: PointSet, hyp: NDArray[np.intp], X: F64) -> F64:
    """Mean reprojection error (M,) of X (M, 3) over the rows of hyp (M, k; -1 = none)."""
    M, k = hyp.shape
    mask = hyp >= 0
    r = np.where(mask, hyp, 0)
    Xf = np.nan_to_num(X)
    proj, front = cams.project_ideal(points.slot[r].ravel(), np.repeat(Xf, k, axis=0))
    uv = np.stack([points.u_ideal[r], points.v_ideal[r]], axis=-1).reshape(-1, 2)
    e = np.linalg.norm(proj - uv, axis=1).reshape(M, k)
    err = np.where(mask, e, 0.0).sum(axis=1) / np.maximum(mask.sum(axis=1), 1)
    good = (front.reshape(M, k) | ~mask).all(axis=1) & np.isfinite(X).all(axis=1) & np.isfinite(err)
    return np.where(good, err, np.inf)


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
