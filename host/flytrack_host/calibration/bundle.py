"""Bundle adjustment over all cameras and LED points with scipy.optimize.least_squares.

Per camera: rotation vector (3), translation (3), focal length f (fy = f x the initial aspect ratio),
principal point (2), and the distortion terms chosen by `distortion`:
"none", "k1", "k1k2" (default) or "k1k2p1p2" (radial + tangential). Per point: its 3D position.
Two solvers: "schur" (default; schur.py: Levenberg-Marquardt with an analytic Jacobian, the points
eliminated by the Schur complement and the camera system solved exactly) and "trf" (scipy's
least_squares: trust region, LSMR on the sparse Jacobian, estimated by finite differences made cheap
by its sparsity pattern: a residual depends only on its camera's parameters and its point).
Cameras named in `fixed_intrinsics` (e.g. measured with a calibration board) keep K and all five
distortion terms exactly as given: only their pose is refined, and their intrinsic parameters get no
Jacobian column at all.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from flytrack_host.calibration.schur import distort_observations, levenberg_marquardt
from flytrack_host.geometry.camera import Camera

__all__ = ["DISTORTION_MODELS", "BundleResult", "bundle_adjust", "project_params"]

DISTORTION_MODELS = {"none": 0, "k1": 1, "k1k2": 2, "k1k2p1p2": 4}
F64 = NDArray[np.float64]


@dataclass
class BundleResult:
    cameras: list[Camera]
    points: F64
    residuals: F64  # (N, 2) predicted - observed, pixels
    cost: float
    nfev: int
    success: bool
    message: str


def _n_params(distortion: str) -> int:
    return 9 + DISTORTION_MODELS[distortion]


def _pack_camera(cam: Camera, distortion: str) -> F64:
    nd = DISTORTION_MODELS[distortion]
    d = cam.dist
    dist_params = [d[0], d[1], d[2], d[3]][:nd]
    return np.concatenate([Rotation.from_matrix(cam.R).as_rotvec(), cam.t, [cam.K[0, 0], cam.K[0, 2], cam.K[1, 2]],
                           dist_params])


def _unpack_camera(p: F64, template: Camera, distortion: str) -> Camera:
    nd = DISTORTION_MODELS[distortion]
    aspect = template.K[1, 1] / template.K[0, 0]
    K = np.array([[p[6], 0.0, p[7]], [0.0, p[6] * aspect, p[8]], [0.0, 0.0, 1.0]])
    dist = template.dist.copy()  # what the model does not adjust (e.g. k3 from an intrinsics file) stays
    dist[:nd] = p[9:9 + nd]  # OpenCV order k1 k2 p1 p2 k3: the adjusted terms come first
    return Camera(name=template.name, width=template.width, height=template.height, K=K,
                  R=Rotation.from_rotvec(p[:3]).as_matrix(), t=p[3:6], dist=dist)


def project_params(cp: F64, aspect: F64, fixed_dist: F64, X: F64, cam: NDArray[np.intp], nd: int) -> F64:
    """Vectorised projection: camera parameter rows cp (C, n), points X (N, 3) seen by cameras cam (N,)."""
    R = Rotation.from_rotvec(cp[:, :3]).as_matrix()
    Xc = np.einsum("nij,nj->ni", R[cam], X) + cp[cam, 3:6]
    z = Xc[:, 2]
    z = np.where(np.abs(z) < 1e-12, 1e-12, z)
    x, y = Xc[:, 0] / z, Xc[:, 1] / z
    xd, yd = distort_observations(x, y, cp, fixed_dist, cam, nd)[:2]
    f = cp[cam, 6]
    return np.stack([f * xd + cp[cam, 7], f * aspect[cam] * yd + cp[cam, 8]], axis=1)


def bundle_adjust(cameras: list[Camera], points: F64, cam: NDArray[np.intp], pt: NDArray[np.intp], uv: F64,
                  distortion: str = "k1k2", loss: str = "huber", f_scale: float = 1.0, max_nfev: int = 100,
                  fix_intrinsics: bool = False, ftol: float = 1e-4, gauge: tuple[int, int] | None = None,
                  fixed_intrinsics: set[str] | None = None, lsmr_tol: float = 1e-6,
                  solver: str = "schur") -> BundleResult:
    """Refine cameras and points so that projections of points[pt] in cameras[cam] match uv (N, 2).

    fix_intrinsics holds every camera's K and distortion; fixed_intrinsics only those of the cameras named
    (names that are not among `cameras` are ignored). gauge=(a, b) removes the similarity freedom, which
    otherwise slows the sparse solver: camera a's pose and one translation component of camera b are held
    fixed. lsmr_tol: LSMR's atol and btol for each trust-region step (scipy's default 1e-6 is cheap but leaves
    the ill-conditioned directions, e.g. focal length vs distance, under-solved; 1e-10 converges them); used by
    solver="trf" only: the "schur" solver solves each step exactly."""
    if solver not in ("schur", "trf"):
        raise ValueError(f"solver {solver!r} unknown; use 'schur' or 'trf'")
    if distortion not in DISTORTION_MODELS:
        raise ValueError(f"distortion model {distortion!r} unknown; use one of {sorted(DISTORTION_MODELS)}")
    nd = DISTORTION_MODELS[distortion]
    m = _n_params(distortion)
    nc, npnt, nobs = len(cameras), len(points), len(uv)
    cp0 = np.stack([_pack_camera(c, distortion) for c in cameras])
    aspect = np.array([c.K[1, 1] / c.K[0, 0] for c in cameras])
    fixed_dist = np.stack([c.dist for c in cameras])
    if nd:
        fixed_dist[:, :nd] = 0.0
    cam = np.asarray(cam, dtype=np.intp)
    pt = np.asarray(pt, dtype=np.intp)
    free = np.zeros((nc, m), dtype=bool)
    free[:, 6 if fix_intrinsics else m:] = False
    free[:, : (6 if fix_intrinsics else m)] = True
    held = [i for i, c in enumerate(cameras) if fixed_intrinsics and c.name in fixed_intrinsics]
    free[held, 6:] = False
    if gauge is not None:
        # Camera a's pose fixes rotation and translation; the largest component of camera b's translation
        # (in camera a's frame when a is the identity, as the initialisation makes it) fixes the scale.
        free[gauge[0], :6] = False
        free[gauge[1], 3 + int(np.argmax(np.abs(cameras[gauge[1]].t)))] = False
    free_flat = free.ravel()
    col_of = np.cumsum(free_flat) - 1  # column of each free camera parameter
    n_cam_cols = int(free_flat.sum())

    def unpack(x: F64) -> tuple[F64, F64]:
        cp = cp0.copy().ravel()
        cp[free_flat] = x[:n_cam_cols]
        return cp.reshape(nc, m), x[n_cam_cols:].reshape(npnt, 3)

    def fun(x: F64) -> F64:
        cp, X = unpack(x)
        return (project_params(cp, aspect, fixed_dist, X[pt], cam, nd) - uv).ravel()

    if solver == "schur":
        R0 = np.stack([c.R for c in cameras]).astype(np.float64)
        sr = levenberg_marquardt(R0, cp0, aspect, fixed_dist, np.asarray(points, dtype=np.float64), cam, pt,
                                 np.asarray(uv, dtype=np.float64), nd, free, loss=loss, f_scale=f_scale,
                                 max_iter=max_nfev, ftol=ftol)
        cp = sr.cp.copy()
        cp[:, :3] = Rotation.from_matrix(sr.R).as_rotvec()
        out = [_unpack_camera(cp[i], c, distortion) for i, c in enumerate(cameras)]
        for i in held if not fix_intrinsics else range(nc):
            out[i].K, out[i].dist = cameras[i].K.copy(), cameras[i].dist.copy()
        return BundleResult(out, sr.X, sr.residuals, sr.cost, sr.nfev, sr.success, sr.message)

    A = lil_matrix((2 * nobs, n_cam_cols + 3 * npnt), dtype=np.int8)
    rows = np.arange(nobs)
    for k in range(m):
        fc = free[cam, k]
        cols = col_of[cam[fc] * m + k]
        A[2 * rows[fc], cols] = 1
        A[2 * rows[fc] + 1, cols] = 1
    for k in range(3):
        A[2 * rows, n_cam_cols + pt * 3 + k] = 1
        A[2 * rows + 1, n_cam_cols + pt * 3 + k] = 1
    x0 = np.concatenate([cp0.ravel()[free_flat], np.asarray(points, dtype=np.float64).ravel()])
    res = least_squares(fun, x0, jac_sparsity=A.tocsr(), x_scale="jac", loss=loss, f_scale=f_scale,
                        method="trf", tr_solver="lsmr", tr_options={"atol": lsmr_tol, "btol": lsmr_tol},
                        ftol=ftol, xtol=1e-10, gtol=1e-10, max_nfev=max_nfev)
    cp, X = unpack(res.x)
    out = [_unpack_camera(cp[i], c, distortion) for i, c in enumerate(cameras)]
    for i in held if not fix_intrinsics else range(nc):
        # Bit-identical to the input (f * aspect need not round back to fy exactly).
        out[i].K, out[i].dist = cameras[i].K.copy(), cameras[i].dist.copy()
    return BundleResult(out, X, res.fun[: 2 * nobs].reshape(-1, 2), float(res.cost), int(res.nfev), bool(res.success),
                        str(res.message))
