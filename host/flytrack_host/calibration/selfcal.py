"""Multi-camera self-calibration from one bright point (an LED) waved through the volume.

The default initialisation ("factorization") is the method of Svoboda et al. (as flydra uses it):

1. Pairwise outlier rejection: for every camera pair with enough common frames, RANSAC on the
   fundamental matrix (cv2.findFundamentalMat, pixels); an observation is dropped when most of the pairs
   it takes part in reject it. No intrinsics are needed.
2. Projective factorisation (`factorization.py`, Sturm-Triggs with iterative depths and rank-4 filling
   of the missing views) of the frames seen by 3 or more cameras, then removal of the entries it cannot
   explain and a second factorisation.
3. Euclidean upgrade (`metric_upgrade.py`) through the absolute dual quadric, assuming zero skew, square
   pixels and a principal point near the image centre; every other frame is then triangulated.

The alternative ("pairwise", `--init pairwise`) starts from approximate intrinsics instead: essential
matrix RANSAC per pair, relative pose of the best pair (cv2.recoverPose), then every other camera by RANSAC
PnP (cv2.solvePnPRansac) on the points seen so far, triangulating new points as cameras join.

Either start is refined by bundle adjustment (`bundle.py`) of all cameras (pose, focal length, principal
point, radial and optionally tangential distortion) and all points: first with a robust loss, then
rejection of observations beyond ~4.5 sigma, then again with a Huber loss tuned to the measured noise.

The result is exact up to a similarity (rotation, translation, scale): `align.py` fixes it to the world.
A focal length guess in pixels (lens focal length / pixel pitch, or an intrinsics file; by default the
image's larger side, ~53 deg) is needed by "pairwise"; "factorization" uses it only to normalise pixels
and as a weak prior (the upgrade finds the focal lengths). Lens distortion is ignored until the bundle
adjustment unless an intrinsics file gives it (its pixels are then undistorted first).
The cameras of an intrinsics file (a board calibration) keep its K and distortion exactly: the
factorisation start swaps them in after the upgrade and re-solves those poses by PnP, and the bundle
adjustment holds them (unless refine_intrinsics).
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from flytrack_host.calibration.align import Similarity
from flytrack_host.calibration.bundle import DISTORTION_MODELS, bundle_adjust
from flytrack_host.calibration.observations import Observations
from flytrack_host.calibration.schur import project_jacobian
from flytrack_host.geometry.camera import Camera

__all__ = ["INIT_METHODS", "SelfCalError", "SelfCalResult", "self_calibrate", "initial_cameras",
           "factorization_cameras", "triangulate_frames",
           "check_observations"]

F64 = NDArray[np.float64]
MIN_POINTS_PER_CAMERA = 30
MIN_PAIR_POINTS = 15
INIT_METHODS = ("factorization", "pairwise")


class SelfCalError(ValueError):
    """Self-calibration cannot proceed; the message says what is wrong and what to do."""


@dataclass
class SelfCalResult:
    cameras: dict[str, Camera]
    points: F64  # (P, 3) LED positions (self-calibration frame: arbitrary similarity)
    point_frames: NDArray[np.int64]  # (P,) frame number of each point
    obs: Observations  # the input observations
    inlier: NDArray[np.bool_]  # (N,) which observations the final solution uses
    obs_point: NDArray[np.int64]  # (N,) index into points (or -1)
    residuals: F64  # (N, 2) reprojection residual of each observation (NaN if no point)
    initial_cameras: dict[str, Camera]  # the starting point of the bundle adjustment
    initial_points: F64
    initial_obs_mask: NDArray[np.bool_]  # the observations the bundle adjustment started from
    timings: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    sigma_px: float = float("nan")
    init_method: str = "factorization"  # which initialisation gave the start (see INIT_METHODS)


# ------------------------------------------------------------------------------------------------
# input checks
# ------------------------------------------------------------------------------------------------
def check_observations(obs: Observations, min_points: int = MIN_POINTS_PER_CAMERA) -> None:
    """Raise SelfCalError for input that cannot give a calibration (before any heavy work)."""
    if obs.n_cameras < 2:
        raise SelfCalError(f"only {obs.n_cameras} camera in the points file: self-calibration needs at least 2 "
                           "(3 or more for a reliable result). Add the other cameras' detections.")
    counts = obs.counts()
    empty = [n for n, c in zip(obs.camera_names, counts, strict=True) if c == 0]
    if empty:
        raise SelfCalError(f"camera(s) {', '.join(empty)} have no points. Check that they saw the LED (exposure, "
                           "threshold, aim) and record again, or remove them from the points file.")
    few = [f"{n} ({c})" for n, c in zip(obs.camera_names, counts, strict=True) if c < min_points]
    if few:
        raise SelfCalError(f"too few points in camera(s) {', '.join(few)}: at least {min_points} are needed, "
                           "a few hundred spread over the whole image are better. Wave the LED longer "
                           "through the part of the volume these cameras see.")
    line_like = 0
    for c in range(obs.n_cameras):
        uv = obs.uv[obs.cam == c]
        sv = np.linalg.svd(uv - np.median(uv, axis=0), compute_uv=False)
        line_like += bool(sv[1] < 0.03 * sv[0])
    if line_like == obs.n_cameras:
        raise SelfCalError("the LED positions are collinear (every camera sees them on one line): "
                           "self-calibration needs points that fill a volume. Wave the LED up and down as well "
                           "as across, through the whole tracking volume.")
    _, inv = obs.point_index()
    nviews = np.bincount(inv)
    if int(np.sum(nviews >= 2)) < min_points:
        raise SelfCalError(f"only {int(np.sum(nviews >= 2))} frames show the LED in 2 or more cameras; at least "
                           f"{min_points} are needed. Check that the cameras' frame numbers are synchronised "
                           "and that the LED is in the common field of view.")


def _degeneracy(X: F64) -> str | None:
    """'collinear' or 'planar' when the 3D points do not span a volume, else None."""
    if len(X) < 4:
        return "collinear"
    Xc = X - np.median(X, axis=0)
    s = np.linalg.svd(Xc[np.all(np.isfinite(Xc), axis=1)], compute_uv=False)
    if s[1] < 0.02 * s[0]:
        return "collinear"
    if s[2] < 0.02 * s[0]:
        return "planar"
    return None


# ------------------------------------------------------------------------------------------------
# geometry helpers
# ------------------------------------------------------------------------------------------------
def _normalised(cam: Camera, uv: F64) -> F64:
    ideal = cam.undistort(uv)
    xn, yn = cam._normalize(ideal)  # noqa: SLF001 (our own camera model)
    return np.stack([xn, yn], axis=1)


def triangulate_frames(Ps: list[F64 | None], cam: NDArray[np.intp], pt: NDArray[np.intp], xy: F64,
                       n_points: int) -> F64:
    """Linear triangulation of every point from its normalised observations xy in cameras with known P=[R|t].

    Observations whose camera has no P yet are ignored; points seen by < 2 such cameras get NaN."""
    out = np.full((n_points, 3), np.nan)
    have = np.array([P is not None for P in Ps])
    use = have[cam]
    cam, pt, xy = cam[use], pt[use], xy[use]
    if not len(cam):
        return out
    Pst = np.stack([P if P is not None else np.zeros((3, 4)) for P in Ps])
    rows = np.concatenate([xy[:, 0:1] * Pst[cam, 2] - Pst[cam, 0], xy[:, 1:2] * Pst[cam, 2] - Pst[cam, 1]])
    rows /= np.linalg.norm(rows, axis=1, keepdims=True)
    owner = np.concatenate([pt, pt])
    # Each point's X is the null vector of its stacked rows A: the eigenvector of A^T A (4x4, summed per
    # point) with the smallest eigenvalue, for all points at once.
    outer = (rows[:, :, None] * rows[:, None, :]).reshape(len(rows), 16)
    AtA = np.empty((n_points, 16))
    for k in range(16):
        AtA[:, k] = np.bincount(owner, weights=outer[:, k], minlength=n_points)
    views = np.bincount(pt, minlength=n_points)
    ok = views >= 2
    if not ok.any():
        return out
    _, vecs = np.linalg.eigh(AtA[ok].reshape(-1, 4, 4))
    X = vecs[:, :, 0]
    good = np.abs(X[:, 3]) > 1e-12
    idx = np.flatnonzero(ok)[good]
    out[idx] = X[good, :3] / X[good, 3:4]
    return out


def _reproj_norm(Ps: list[F64 | None], X: F64, cam: NDArray[np.intp], pt: NDArray[np.intp], xy: F64) -> F64:
    """Reprojection error (normalised units) of each observation; NaN where camera or point is unknown."""
    err = np.full(len(cam), np.nan)
    for c, P in enumerate(Ps):
        if P is None:
            continue
        sel = np.flatnonzero(cam == c)
        Xs = X[pt[sel]]
        ok = np.all(np.isfinite(Xs), axis=1)
        sel, Xs = sel[ok], Xs[ok]
        Xc = Xs @ P[:, :3].T + P[:, 3]
        good = Xc[:, 2] > 0
        proj = Xc[:, :2] / np.where(good, Xc[:, 2], 1.0)[:, None]
        e = np.linalg.norm(proj - xy[sel], axis=1)
        e[~good] = np.inf
        err[sel] = e
    return err


# ------------------------------------------------------------------------------------------------
# initialisation
# ------------------------------------------------------------------------------------------------
def _guess_cameras(obs: Observations, focal_px: float | Mapping[str, float] | None,
                   intrinsics: Mapping[str, Camera] | None) -> list[Camera]:
    cams = []
    for name, (w, h) in zip(obs.camera_names, obs.sizes, strict=True):
        if intrinsics is not None and name in intrinsics:
            src = intrinsics[name]
            cams.append(Camera(name=name, width=w, height=h, K=src.K.copy(), R=np.eye(3), t=np.zeros(3),
                               dist=src.dist.copy()))
            continue
        if isinstance(focal_px, Mapping):
            f = float(focal_px.get(name, max(w, h)))
        else:
            f = float(focal_px) if focal_px else float(max(w, h))
        K = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
        cams.append(Camera(name=name, width=w, height=h, K=K, R=np.eye(3), t=np.zeros(3)))
    return cams


def _pairwise_outliers(obs: Observations, inv: NDArray[np.int64], xy: F64, fpx: F64 | None, thresh_px: float,
                       rng_seed: int) -> tuple[NDArray[np.bool_], dict[tuple[int, int], int]]:
    """Epipolar RANSAC per camera pair; returns (observation is an outlier, inliers per pair).

    With focal lengths fpx, xy are normalised coordinates and the essential matrix is fitted; with
    fpx None, xy are pixels and the fundamental matrix is fitted (no intrinsics needed). SelfCalError when no
    pair of cameras could be fitted."""
    n_frames = int(inv.max()) + 1
    C = obs.n_cameras
    lookup = np.full((C, n_frames), -1, dtype=np.int64)
    lookup[obs.cam, inv] = np.arange(len(inv))
    votes_bad = np.zeros(len(inv))
    votes_all = np.zeros(len(inv))
    pair_inliers: dict[tuple[int, int], int] = {}
    cv2.setRNGSeed(rng_seed)
    for i, j in itertools.combinations(range(C), 2):
        both = np.flatnonzero((lookup[i] >= 0) & (lookup[j] >= 0))
        if len(both) < MIN_PAIR_POINTS:
            continue
        oi, oj = lookup[i, both], lookup[j, both]
        if fpx is None:
            E, mask = cv2.findFundamentalMat(xy[oi], xy[oj], cv2.FM_RANSAC, thresh_px, 0.999, 2000)
        else:
            thr = thresh_px / np.sqrt(fpx[i] * fpx[j])
            E, mask = cv2.findEssentialMat(xy[oi], xy[oj], np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=thr,
                                           maxIters=2000)
        if E is None or mask is None:
            continue
        m = mask.ravel().astype(bool)
        pair_inliers[(i, j)] = int(m.sum())
        for o in (oi, oj):
            votes_all[o] += 1
            votes_bad[o] += ~m
    if not pair_inliers:
        raise SelfCalError(f"no pair of cameras shares {MIN_PAIR_POINTS} or more frames with the LED. The "
                           "cameras must overlap: wave the LED where several cameras see it at once.")
    outlier = (votes_all > 0) & (votes_bad > 0.5 * votes_all)
    return outlier, pair_inliers


def initial_cameras(obs: Observations, focal_px: float | Mapping[str, float] | None = None,
                    intrinsics: Mapping[str, Camera] | None = None, ransac_px: float | None = None,
                    seed: int = 0) -> tuple[list[Camera], F64, NDArray[np.bool_], list[str], tuple[int, int]]:
    """Robust initial cameras and points (arbitrary similarity frame).

    Returns cameras, points, which observations are usable, warnings, and the reference pair (gauge)."""
    warns: list[str] = []
    cams = _guess_cameras(obs, focal_px, intrinsics)
    frames, inv = obs.point_index()
    n_pts = len(frames)
    xy = np.empty_like(obs.uv)
    for c, cam in enumerate(cams):
        sel = obs.cam == c
        xy[sel] = _normalised(cam, obs.uv[sel])
    fpx = np.array([c.K[0, 0] for c in cams])
    if ransac_px is None:
        ransac_px = _default_ransac_px(obs)
    outlier, pair_inliers = _pairwise_outliers(obs, inv, xy, fpx, ransac_px, seed)
    good = ~outlier
    (i0, j0), n0 = max(pair_inliers.items(), key=lambda kv: kv[1])
    n_frames = int(inv.max()) + 1
    lookup = np.full((obs.n_cameras, n_frames), -1, dtype=np.int64)
    lookup[obs.cam[good], inv[good]] = np.flatnonzero(good)
    both = np.flatnonzero((lookup[i0] >= 0) & (lookup[j0] >= 0))
    oi, oj = lookup[i0, both], lookup[j0, both]
    thr = ransac_px / np.sqrt(fpx[i0] * fpx[j0])
    E, mask = cv2.findEssentialMat(xy[oi], xy[oj], np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=thr)
    if E is None:
        raise SelfCalError("the relative pose of the two best-overlapping cameras could not be found; the LED "
                           "path may be degenerate (all on a line or in a plane). Wave it through a volume.")
    E = E[:3]
    _, R, t, mask2 = cv2.recoverPose(E, xy[oi], xy[oj], np.eye(3), mask=mask.copy())
    Ps: list[F64 | None] = [None] * obs.n_cameras
    Ps[i0] = np.hstack([np.eye(3), np.zeros((3, 1))])
    Ps[j0] = np.hstack([R, t.reshape(3, 1)])
    cam_idx = obs.cam.astype(np.intp)
    X = triangulate_frames(Ps, cam_idx[good], inv[good], xy[good], n_pts)
    degenerate = _degeneracy(X[np.all(np.isfinite(X), axis=1)])
    if degenerate:
        raise SelfCalError(f"the LED positions are {degenerate}: self-calibration needs points that fill a volume. "
                           "Wave the LED up and down as well as across, through the whole tracking volume.")
    thr_norm = ransac_px / float(np.median(fpx))
    registered = {i0, j0}
    while len(registered) < obs.n_cameras:
        best, best_n = -1, 0
        known = np.all(np.isfinite(X), axis=1)
        for c in range(obs.n_cameras):
            if c in registered:
                continue
            n = int(np.sum(good & (obs.cam == c) & known[inv]))
            if n > best_n:
                best, best_n = c, n
        if best < 0 or best_n < 12:
            missing = [obs.camera_names[c] for c in range(obs.n_cameras) if c not in registered]
            raise SelfCalError(f"camera(s) {', '.join(missing)} share too few LED frames with the other cameras to "
                               "be placed. Wave the LED where these cameras and at least two others see it.")
        sel = np.flatnonzero(good & (obs.cam == best) & known[inv])
        ok, rvec, tvec, inl = cv2.solvePnPRansac(X[inv[sel]], xy[sel], np.eye(3), None, reprojectionError=thr_norm,
                                                 iterationsCount=500, confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
        if not ok or inl is None or len(inl) < 12:
            raise SelfCalError(f"camera {obs.camera_names[best]} could not be placed from the LED points it shares "
                               "with the others (PnP failed). Check its detections and its image size.")
        inl = inl.ravel()
        ok, rvec, tvec = cv2.solvePnP(X[inv[sel[inl]]], xy[sel[inl]], np.eye(3), None, rvec, tvec,
                                      useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        Rm, _ = cv2.Rodrigues(rvec)
        Ps[best] = np.hstack([Rm, tvec.reshape(3, 1)])
        registered.add(best)
        X = triangulate_frames(Ps, cam_idx[good], inv[good], xy[good], n_pts)
        err = _reproj_norm(Ps, X, cam_idx, inv, xy)
        # Drop wildly inconsistent observations now so they do not spoil later PnP steps.
        good &= ~(np.isfinite(err) & (err > 3 * thr_norm))
        X = triangulate_frames(Ps, cam_idx[good], inv[good], xy[good], n_pts)
    for c, cam in enumerate(cams):
        P = Ps[c]
        assert P is not None
        cam.R = P[:, :3].copy()
        cam.t = P[:, 3].copy()
    err = _reproj_norm(Ps, X, cam_idx, inv, xy)
    good &= np.isfinite(err) & (err < 3 * thr_norm)
    if int(np.sum(outlier)) > 0.2 * len(outlier):
        warns.append(f"{int(np.sum(outlier))} of {len(outlier)} detections ({100 * np.mean(outlier):.0f} %) "
                     "disagree with the epipolar geometry: check for reflections or a second bright spot.")
    return cams, X, good, warns, (i0, j0)


def _default_ransac_px(obs: Observations) -> float:
    # Generous: the initial model ignores the (unknown) lens distortion, which can bend epipolar geometry by
    # several pixels at the image edges; the bundle adjustment does the fine rejection.
    return max(4.0, 0.006 * max(max(s) for s in obs.sizes))


def factorization_cameras(obs: Observations, focal_px: float | Mapping[str, float] | None = None,
                          intrinsics: Mapping[str, Camera] | None = None, ransac_px: float | None = None,
                          seed: int = 0, max_points: int = 1000, keep_intrinsics: bool = False,
                          ) -> tuple[list[Camera], F64, NDArray[np.bool_], list[str], tuple[int, int]]:
    """Svoboda-style start: fundamental-matrix RANSAC, projective factorisation, Euclidean upgrade.

    Same return values as `initial_cameras`: cameras, points (all frames), usable observations, warnings,
    and the gauge pair (the first camera is made the identity, the distance to the second 1).
    keep_intrinsics: the cameras of `intrinsics` end with its K and distortion (poses re-solved by PnP)
    instead of the upgrade's K."""
    from flytrack_host.calibration.factorization import FactorizationError, projective_factorization
    from flytrack_host.calibration.metric_upgrade import MetricUpgradeError, metric_upgrade

    warns: list[str] = []
    C = obs.n_cameras
    if C < 3:
        raise SelfCalError(f"the factorisation initialisation needs 3 or more cameras (there are {C}): with 2 the "
                           "focal lengths cannot be found. Use --init pairwise with a focal length guess.")
    cams = _guess_cameras(obs, focal_px, intrinsics)
    frames, inv = obs.point_index()
    n_pts = len(frames)
    px = obs.uv.copy()  # pixels for the projective stage: undistorted when an intrinsics file gives a lens model
    for c, cam in enumerate(cams):
        if cam.has_distortion:
            sel = obs.cam == c
            px[sel] = cam.undistort(obs.uv[sel])
    if ransac_px is None:
        ransac_px = _default_ransac_px(obs)
    outlier, pair_inliers = _pairwise_outliers(obs, inv, px, None, ransac_px, seed)
    good = ~outlier
    lookup = np.full((C, n_pts), -1, dtype=np.int64)
    lookup[obs.cam[good], inv[good]] = np.flatnonzero(good)
    cand = np.flatnonzero(np.sum(lookup >= 0, axis=0) >= 3)  # frames seen by 3+ cameras fix the cameras best
    few = [obs.camera_names[c] for c in range(C) if np.sum(lookup[c, cand] >= 0) < 12]
    if few:
        raise SelfCalError(f"camera(s) {', '.join(few)} share too few LED frames with two other cameras at once to "
                           "be placed. Wave the LED where these cameras and at least two others see it.")
    rng = np.random.default_rng(seed)
    if len(cand) > max_points:
        cand = np.sort(rng.choice(cand, size=max_points, replace=False))
    sub = lookup[:, cand]
    seen = sub >= 0
    uv = np.zeros((C, len(cand), 2))
    uv[seen] = px[sub[seen]]
    try:
        rec = projective_factorization(uv, seen)
        # Entries the rank-4 model cannot explain (outliers the pairwise test let through) go; then again.
        err = np.linalg.norm(rec.project() - uv, axis=2)
        robust = 1.4826 * float(np.median(err[seen]))
        seen &= err < max(ransac_px, 5.0 * robust)
        keep = seen.sum(axis=0) >= 2
        uv, seen, cand = uv[:, keep], seen[:, keep], cand[keep]
        rec = projective_factorization(uv, seen)
    except FactorizationError as exc:
        raise SelfCalError(f"projective factorisation failed: {exc}. Wave the LED longer where 3 or more cameras "
                           "see it at once.") from None
    if rec.singular_ratio < 0.15:
        # The scaled measurement matrix of points on a plane (or a line) has rank 3 (or less), not 4.
        raise SelfCalError("the LED positions are planar (or collinear): self-calibration needs points that fill a "
                           "volume. Wave the LED up and down as well as across, through the whole tracking volume.")
    keep = {c: intrinsics[cam.name] for c, cam in enumerate(cams)
            if keep_intrinsics and intrinsics is not None and cam.name in intrinsics}
    f0 = [c.K[0, 0] for c in cams]
    try:
        mr = metric_upgrade(rec.P, rec.X, obs.sizes, f0, seen)
    except MetricUpgradeError as exc:
        raise SelfCalError(f"Euclidean upgrade failed: {exc}") from None
    if mr.in_front < 0.9:
        raise SelfCalError(f"the Euclidean upgrade puts {100 * (1 - mr.in_front):.0f} % of the LED points behind the "
                           "cameras that see them: the factorisation is unreliable. Try --init pairwise with a "
                           "focal length guess, or give an intrinsics file.")
    for c, cam in enumerate(cams):
        try:
            m = Camera.from_P(cam.name, mr.P[c], cam.width, cam.height)
        except ValueError as exc:
            raise SelfCalError(f"Euclidean upgrade gave no valid camera {cam.name}: {exc}") from None
        f = float(np.sqrt(m.K[0, 0] * m.K[1, 1]))  # the model has zero skew and square pixels
        cx, cy = m.K[0, 2], m.K[1, 2]
        if not (0 <= cx < cam.width and 0 <= cy < cam.height):
            warns.append(f"camera {cam.name}: the upgrade put its principal point outside the image; started from "
                         "the image centre instead.")
            cx, cy = (cam.width - 1) / 2.0, (cam.height - 1) / 2.0
        cam.K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        cam.R, cam.t = m.R, m.t
    # Gauge as the pairwise start has it: the best-overlapping pair, first camera at the origin, unit baseline.
    (i0, j0), _ = max(pair_inliers.items(), key=lambda kv: kv[1])
    cam_idx = obs.cam.astype(np.intp)
    thr_norm = ransac_px / float(np.median([c.K[0, 0] for c in cams]))

    def place(cams: list[Camera], good: NDArray[np.bool_]) -> tuple[list[Camera], F64, NDArray[np.bool_]]:
        """Gauge, triangulate every frame, drop observations the cameras cannot explain, triangulate again."""
        base = float(np.linalg.norm(cams[j0].center - cams[i0].center))
        sim = Similarity(1.0 / base, cams[i0].R.copy(), cams[i0].t / base)
        cams = [sim.apply_camera(c) for c in cams]
        xy = np.empty_like(obs.uv)
        for c, cam in enumerate(cams):
            sel = obs.cam == c
            xy[sel] = _normalised(cam, obs.uv[sel])
        Ps: list[F64 | None] = [np.hstack([c.R, c.t[:, None]]) for c in cams]
        X = triangulate_frames(Ps, cam_idx[good], inv[good], xy[good], n_pts)
        degenerate = _degeneracy(X[np.all(np.isfinite(X), axis=1)])
        if degenerate:
            raise SelfCalError(f"the LED positions are {degenerate}: self-calibration needs points that fill a "
                               "volume. Wave the LED up and down as well as across, through the whole tracking "
                               "volume.")
        err = _reproj_norm(Ps, X, cam_idx, inv, xy)
        good = good & np.isfinite(err) & (err < 3 * thr_norm)
        return cams, triangulate_frames(Ps, cam_idx[good], inv[good], xy[good], n_pts), good

    cams, X, good = place(cams, good)
    if keep:
        # The board's K replaces the upgrade's for these cameras; their poses (found with the upgrade's K) are
        # re-solved by PnP on the triangulated LED points, alternating with triangulation (resection-intersection).
        for _ in range(2):
            for c, board in keep.items():
                cam = cams[c]
                cam.K, cam.dist = board.K.copy(), board.dist.copy()
                sel = np.flatnonzero(good & (obs.cam == c) & np.all(np.isfinite(X[inv]), axis=1))
                if len(sel) < 12:
                    continue
                rvec0, _ = cv2.Rodrigues(cam.R)
                ok, rvec, tvec = cv2.solvePnP(X[inv[sel]], obs.uv[sel], cam.K, cam.dist, rvec0, cam.t.reshape(3, 1),
                                              useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
                if ok:
                    cam.R, cam.t = cv2.Rodrigues(rvec)[0], tvec.ravel()
            cams, X, good = place(cams, good | ~outlier)
    if int(np.sum(outlier)) > 0.2 * len(outlier):
        warns.append(f"{int(np.sum(outlier))} of {len(outlier)} detections ({100 * np.mean(outlier):.0f} %) "
                     "disagree with the epipolar geometry: check for reflections or a second bright spot.")
    return cams, X, good, warns, (i0, j0)


# ------------------------------------------------------------------------------------------------
# the whole pipeline
# ------------------------------------------------------------------------------------------------
def self_calibrate(obs: Observations, focal_px: float | Mapping[str, float] | None = None,
                   intrinsics: Mapping[str, Camera] | None = None, distortion: str = "k1k2",
                   ransac_px: float | None = None, max_nfev: int = 60, seed: int = 0,
                   max_ba_points: int = 1500, final_ftol: float = 1e-8, init: str = "factorization",
                   refine_intrinsics: bool = False, final_lsmr_tol: float = 1e-10,
                   final_ba_points: int | None = None, solver: str = "schur") -> SelfCalResult:
    """Calibrate all cameras of obs (up to a similarity). init: "factorization" (Svoboda: projective
    factorisation + Euclidean upgrade) or "pairwise" (essential matrices + PnP from approximate intrinsics).

    The cameras of `intrinsics` (a board calibration) keep its K and distortion exactly, only their poses
    are refined; refine_intrinsics=True makes them a starting point that the bundle adjustment refines.
    solver: the bundle adjustment's, "schur" (exact Levenberg-Marquardt steps, points eliminated; default)
    or "trf" (scipy's trust region with LSMR; final_lsmr_tol applies to it). final_ftol: the final stage
    runs until the cost changes by less than this (1e-8: exact steps make the last iterations cheap, and
    1e-5 stopped up to 0.1 mm short of the converged camera centres)."""
    if distortion not in DISTORTION_MODELS:
        raise SelfCalError(f"distortion model {distortion!r} unknown; choose one of {', '.join(DISTORTION_MODELS)}.")
    if init not in INIT_METHODS:
        raise SelfCalError(f"initialisation {init!r} unknown; choose one of {', '.join(INIT_METHODS)}.")
    check_observations(obs)
    t0 = time.perf_counter()
    c0 = time.process_time()
    fixed = set() if refine_intrinsics or intrinsics is None else {n for n in obs.camera_names if n in intrinsics}
    if init == "factorization":
        cams, X, good, warns, gauge = factorization_cameras(obs, focal_px, intrinsics, ransac_px, seed,
                                                            keep_intrinsics=bool(fixed))
    else:
        cams, X, good, warns, gauge = initial_cameras(obs, focal_px, intrinsics, ransac_px, seed)
    t1 = time.perf_counter()
    c1 = time.process_time()
    frames, inv = obs.point_index()
    init_cams = {c.name: Camera(c.name, c.width, c.height, c.K.copy(), c.R.copy(), c.t.copy(), c.dist.copy())
                 for c in cams}
    init_X = X.copy()
    init_mask = good.copy()

    usable = good & np.all(np.isfinite(X[inv]), axis=1)
    sigma = float("nan")
    inlier = usable
    X_cur = X
    bres = None
    rng = np.random.default_rng(seed)
    # Stage 1: robust loss from the rough start; later stages: reject and refine with the noise measured.
    for stage, (loss, fs) in enumerate([("soft_l1", 3.0), ("huber", None), ("linear", None)]):
        pts = np.unique(inv[inlier & (_views_per_point(inv, inlier) >= 2)])
        # The final stage uses every frame by default: with a converged solve the centres are limited by the
        # information used (focal length vs depth), and 1500 frames left 4 cameras up to 11 mm off (issue 6).
        cap = max_ba_points if stage < 2 else (final_ba_points if final_ba_points is not None else len(pts))
        if len(pts) > cap:
            # A few hundred well-observed points fix ~10 parameters per camera; more only slow the solver.
            nv = np.bincount(inv[inlier], minlength=len(frames))[pts].astype(float)
            pts = np.sort(rng.choice(pts, size=cap, replace=False, p=nv / nv.sum()))
        sel = inlier & np.isin(inv, pts)
        remap = np.full(len(frames), -1, dtype=np.int64)
        remap[pts] = np.arange(len(pts))
        f_scale = fs if fs is not None else max(0.3, 2.5 * sigma)
        bres = bundle_adjust(cams, X_cur[pts], obs.cam[sel], remap[inv[sel]], obs.uv[sel], distortion=distortion,
                             loss=loss, f_scale=f_scale, max_nfev=max_nfev, gauge=gauge, fixed_intrinsics=fixed,
                             ftol=final_ftol if stage == 2 else 1e-4,
                             # The final stage solves each step's linear system to high accuracy: with scipy's
                             # default (1e-6) LSMR stops early along the weakly determined directions (focal
                             # length vs depth), so the solver creeps there and ftol stops it short (issue 6).
                             lsmr_tol=final_lsmr_tol if stage == 2 else 1e-6, solver=solver)
        cams = bres.cameras
        sigma = float(np.median(np.linalg.norm(bres.residuals, axis=1)) / 1.1774)  # 2D Gaussian: 1.1774 sigma
        # Every frame (also those outside the bundle sample) is triangulated from the current inliers and
        # refined, then every observation (also those rejected before) is measured against the model.
        X_cur = refine_points(cams, obs, inv, inlier, len(frames))
        rn = np.linalg.norm(_pixel_residuals(cams, X_cur, obs, inv), axis=1)
        inlier = np.isfinite(rn) & (rn < max(6.0 * sigma, 1.0))
        inlier &= _views_per_point(inv, inlier) >= 2
    X_cur = refine_points(cams, obs, inv, inlier, len(frames))
    assert bres is not None
    t2 = time.perf_counter()
    c2 = time.process_time()
    all_res = _pixel_residuals(cams, X_cur, obs, inv)
    result = SelfCalResult(
        cameras={c.name: c for c in cams}, points=X_cur, point_frames=frames, obs=obs, inlier=inlier,
        obs_point=inv.copy(), residuals=all_res, initial_cameras=init_cams, initial_points=init_X,
        initial_obs_mask=init_mask, timings={"init_s": t1 - t0, "bundle_s": t2 - t1,
                                                  "init_cpu_s": c1 - c0, "bundle_cpu_s": c2 - c1}, warnings=warns,
        sigma_px=sigma, init_method=init)
    return result


def refine_points(cams: list[Camera], obs: Observations, inv: NDArray[np.int64], use: NDArray[np.bool_],
                  n_points: int, iterations: int = 5) -> F64:
    """Triangulate each frame from its `use` observations (linear), then Gauss-Newton on reprojection error.

    All points are refined at once (vectorised); the 3x3 normal equations of each point are independent."""
    xy = np.empty_like(obs.uv)
    for c, cam in enumerate(cams):
        s = obs.cam == c
        xy[s] = _normalised(cam, obs.uv[s])
    Ps: list[F64 | None] = [np.hstack([c.R, c.t[:, None]]) for c in cams]
    cam_idx = obs.cam.astype(np.intp)
    X = triangulate_frames(Ps, cam_idx[use], inv[use], xy[use], n_points)
    idx = np.flatnonzero(use & np.all(np.isfinite(X[inv]), axis=1))
    if not len(idx):
        return X
    c_i, p_i, uv = cam_idx[idx], inv[idx], obs.uv[idx]

    def proj(Xp: F64) -> F64:
        out = np.empty((len(idx), 2))
        for c, cam in enumerate(cams):
            s = c_i == c
            out[s] = cam.project(Xp[p_i[s]])
        return out

    h = 1e-6 * max(1.0, float(np.nanmax(np.abs(X))))
    # Pinhole + OpenCV distortion cameras without skew, refraction or a separate distortion frame (all
    # that self-calibration produces): one vectorised pass with the analytic Jacobian.
    plain = all(c.interface is None and c.K_dist is None and c.K[0, 1] == 0.0 for c in cams)
    if plain:
        Rs = np.stack([c.R for c in cams])
        cps = np.zeros((len(cams), 9))
        cps[:, 3:6] = [c.t for c in cams]
        cps[:, 6:9] = [[c.K[0, 0], c.K[0, 2], c.K[1, 2]] for c in cams]
        aspect = np.array([c.K[1, 1] / c.K[0, 0] for c in cams])
        dists = np.stack([c.dist for c in cams])
    for _ in range(iterations):
        if plain:
            pred, _, J = project_jacobian(Rs, cps, aspect, dists, X, c_i, p_i, 0)
            assert J is not None
            z = np.einsum("nj,nj->n", Rs[c_i, 2], X[p_i]) + cps[c_i, 5]
            pred[z <= 0] = np.nan  # behind the camera, as Camera.project
            r = pred - uv
        else:
            r = proj(X) - uv
            J = np.empty((len(idx), 2, 3))
            for k in range(3):
                Xk = X.copy()
                Xk[:, k] += h
                J[:, :, k] = (proj(Xk) - uv - r) / h
        ok = np.all(np.isfinite(J), axis=(1, 2)) & np.all(np.isfinite(r), axis=1)
        JtJ = np.zeros((n_points, 3, 3))
        Jtr = np.zeros((n_points, 3))
        np.add.at(JtJ, p_i[ok], np.einsum("nki,nkj->nij", J[ok], J[ok]))
        np.add.at(Jtr, p_i[ok], np.einsum("nki,nk->ni", J[ok], r[ok]))
        has = np.abs(np.linalg.det(JtJ)) > 1e-30
        step = np.zeros_like(X)
        step[has] = np.linalg.solve(JtJ[has], Jtr[has][:, :, None])[:, :, 0]
        X = X - step
    return X


def robust_points(cams: list[Camera], obs: Observations, rounds: int = 3) -> tuple[F64, NDArray[np.bool_], F64]:
    """Points of a fixed calibration with outlier views dropped: (points, inlier mask, residuals)."""
    _, inv = obs.point_index()
    n = int(inv.max()) + 1
    use = np.ones(len(inv), dtype=bool)
    for _ in range(rounds):
        X = refine_points(cams, obs, inv, use, n)
        rn = np.linalg.norm(_pixel_residuals(cams, X, obs, inv), axis=1)
        good = rn[use & np.isfinite(rn)]
        sigma = float(np.median(good) / 1.1774) if len(good) else 1.0
        use = np.isfinite(rn) & (rn < max(6.0 * sigma, 1.0))
        use &= _views_per_point(inv, use) >= 2
    X = refine_points(cams, obs, inv, use, n)
    return X, use, _pixel_residuals(cams, X, obs, inv)


def _views_per_point(inv: NDArray[np.int64], mask: NDArray[np.bool_]) -> NDArray[np.int64]:
    counts = np.bincount(inv[mask], minlength=int(inv.max()) + 1)
    return counts[inv]


def _pixel_residuals(cams: list[Camera], X: F64, obs: Observations, inv: NDArray[np.int64]) -> F64:
    res = np.full((len(inv), 2), np.nan)
    for c, cam in enumerate(cams):
        sel = np.flatnonzero(obs.cam == c)
        Xs = X[inv[sel]]
        ok = np.all(np.isfinite(Xs), axis=1)
        res[sel[ok]] = cam.project(Xs[ok]) - obs.uv[sel[ok]]
    return res
