"""Bundle adjustment by Levenberg-Marquardt with the Schur complement over the points.

The normal equations of a bundle adjustment are block-sparse: each point's 3x3 block is coupled only
to the cameras that see it. Eliminating the points (the Schur complement) leaves a dense system of
the camera parameters alone (13 a camera with k1 k2: 143 for 11 cameras), which is solved exactly
by Cholesky; each point's step then follows from its own 3x3 system. This is what Ceres
(DENSE_SCHUR) and SBA do. Compared with a trust-region solver over the whole sparse Jacobian with
an iterative linear solver (scipy's trf + LSMR), every step is solved exactly, so the weakly
determined directions (focal length against distance) converge without a tight iterative
tolerance, and the Jacobian is analytic (one vectorised pass, no finite differences).

Rotations are updated on the left, R <- exp([w]x) R, so the Jacobian of a rotation is that of a
small rotation at w = 0 and there is no rotation-vector singularity. Robust losses (huber, soft_l1)
act on each residual component as scipy's do and are applied by iteratively reweighted least squares
(the gradient weighted by the loss's first derivative, the curvature by its second-order weight
rho' + 2 rho'' z, so a step is Newton's in the residuals rather than a fixed-weight one).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

F64 = NDArray[np.float64]
LOSSES = ("linear", "huber", "soft_l1")


def _rho(z: F64, loss: str) -> tuple[F64, F64, F64]:
    """Loss rho(z) of z = (r / f_scale)^2 and its first and second derivatives (scipy's definitions)."""
    if loss == "linear":
        return z, np.ones_like(z), np.zeros_like(z)
    if loss == "huber":
        big = z > 1.0
        sz = np.sqrt(np.where(big, z, 1.0))
        return np.where(big, 2.0 * sz - 1.0, z), np.where(big, 1.0 / sz, 1.0), np.where(big, -0.5 / (sz * sz * sz), 0.0)
    if loss == "soft_l1":
        t = 1.0 + z
        st = np.sqrt(t)
        return 2.0 * (st - 1.0), 1.0 / st, -0.5 / (t * st)
    raise ValueError(f"loss {loss!r} unknown; use one of {LOSSES}")


def distort_observations(x: F64, y: F64, cp: F64, fixed_dist: F64, cam: NDArray[np.intp],
                         nd: int) -> tuple[F64, F64, F64, F64, F64]:
    """OpenCV's distortion (k1 k2 p1 p2 k3) of normalised coordinates x, y (N,) seen by cameras cam (N,):
    the first nd terms are adjusted (cp rows [.., 9: 9 + nd]), the rest fixed_dist's. Returns xd, yd, the
    terms (N, 5), r2 and the radial factor (the last three are what the Jacobian needs again)."""
    d = fixed_dist[cam].copy()
    if nd:
        d[:, :nd] = cp[cam, 9:9 + nd]
    k1, k2, p1, p2, k3 = d.T
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd, d, r2, radial


def project_jacobian(R: F64, cp: F64, aspect: F64, fixed_dist: F64, X: F64, cam: NDArray[np.intp],
                     pt: NDArray[np.intp], nd: int, jac: bool = True) -> tuple[F64, F64 | None, F64 | None]:
    """Projections (N, 2) of X[pt] in cameras cam, and their Jacobians: (N, 2, 9 + nd) with respect to
    the camera's [w (left rotation increment), t, f, cx, cy, distortion terms], (N, 2, 3) with respect
    to the point. cp rows: [unused(3), t(3), f, cx, cy, k1, k2, p1, p2][: 9 + nd]."""
    Rc = R[cam]
    a = np.einsum("nij,nj->ni", Rc, X[pt])  # R X
    Xc = a + cp[cam, 3:6]
    z = Xc[:, 2]
    z = np.where(np.abs(z) < 1e-12, 1e-12, z)
    iz = 1.0 / z
    x, y = Xc[:, 0] * iz, Xc[:, 1] * iz
    xd, yd, d, r2, radial = distort_observations(x, y, cp, fixed_dist, cam, nd)
    k1, k2, p1, p2, k3 = d.T
    f = cp[cam, 6]
    fa = f * aspect[cam]
    uv = np.stack([f * xd + cp[cam, 7], fa * yd + cp[cam, 8]], axis=1)
    if not jac:
        return uv, None, None
    n = len(cam)
    drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
    # d(u, v) / d(x, y)
    A = np.empty((n, 2, 2))
    A[:, 0, 0] = f * (radial + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x)
    A[:, 0, 1] = f * (2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y)
    A[:, 1, 0] = fa * (2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y)
    A[:, 1, 1] = fa * (radial + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x)
    # d(u, v) / d Xc = A [[1/z, 0, -x/z], [0, 1/z, -y/z]]
    G = np.empty((n, 2, 3))
    G[:, :, 0] = A[:, :, 0] * iz[:, None]
    G[:, :, 1] = A[:, :, 1] * iz[:, None]
    G[:, :, 2] = -(A[:, :, 0] * (x * iz)[:, None] + A[:, :, 1] * (y * iz)[:, None])
    m = 9 + nd
    Jc = np.zeros((n, 2, m))
    # d Xc / d w = -[R X]x
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    Jc[:, :, 0] = -G[:, :, 1] * a2[:, None] + G[:, :, 2] * a1[:, None]
    Jc[:, :, 1] = G[:, :, 0] * a2[:, None] - G[:, :, 2] * a0[:, None]
    Jc[:, :, 2] = -G[:, :, 0] * a1[:, None] + G[:, :, 1] * a0[:, None]
    Jc[:, :, 3:6] = G
    Jc[:, 0, 6] = xd
    Jc[:, 1, 6] = aspect[cam] * yd
    Jc[:, 0, 7] = 1.0
    Jc[:, 1, 8] = 1.0
    extra = [(x * r2, y * r2), (x * r2 * r2, y * r2 * r2), (2.0 * x * y, r2 + 2.0 * y * y),
             (r2 + 2.0 * x * x, 2.0 * x * y)]
    for k in range(nd):
        Jc[:, 0, 9 + k] = f * extra[k][0]
        Jc[:, 1, 9 + k] = fa * extra[k][1]
    Jp = np.einsum("nik,nkj->nij", G, Rc)
    return uv, Jc, Jp


def _sum_blocks(index: NDArray[np.intp], blocks: F64, n: int) -> F64:
    """out[i] = sum of blocks[index == i] (faster than np.add.at: one bincount per element)."""
    flat = blocks.reshape(len(index), -1)
    out = np.empty((n, flat.shape[1]))
    for k in range(flat.shape[1]):
        out[:, k] = np.bincount(index, weights=flat[:, k], minlength=n)
    return out.reshape((n,) + blocks.shape[1:])


@dataclass
class SchurResult:
    R: F64  # (C, 3, 3)
    cp: F64  # (C, m) camera rows as project_jacobian takes them
    X: F64  # (P, 3)
    residuals: F64  # (N, 2) predicted - observed
    cost: float
    nfev: int
    iterations: int
    success: bool
    message: str


def levenberg_marquardt(R: F64, cp: F64, aspect: F64, fixed_dist: F64, X: F64, cam: NDArray[np.intp],
                        pt: NDArray[np.intp], uv: F64, nd: int, free: NDArray[np.bool_], loss: str = "linear",
                        f_scale: float = 1.0, max_iter: int = 100, ftol: float = 1e-8,
                        xtol: float = 1e-10) -> SchurResult:
    """Minimises 0.5 f_scale^2 sum rho((r / f_scale)^2) over cameras (rows where `free`) and points.

    free: (C, m) camera parameters to adjust (all points are adjusted). Stops when an accepted step
    lowers the cost by less than ftol x cost, the step is below xtol (relative), or after max_iter
    Jacobians."""
    if loss not in LOSSES:
        raise ValueError(f"loss {loss!r} unknown; use one of {LOSSES}")
    nc, m = cp.shape
    npnt = len(X)
    R, cp, X = R.copy(), cp.copy(), X.copy()
    fs2 = float(f_scale) ** 2
    free_flat = free.ravel()
    fi = np.flatnonzero(free_flat)

    def evaluate(R_: F64, cp_: F64, X_: F64, jac: bool) -> tuple[float, F64, F64 | None, F64 | None]:
        pred, Jc_, Jp_ = project_jacobian(R_, cp_, aspect, fixed_dist, X_, cam, pt, nd, jac)
        r_ = pred - uv
        rho, _, _ = _rho(r_ * r_ / fs2, loss)
        return 0.5 * fs2 * float(np.sum(rho)), r_, Jc_, Jp_

    cost, r, Jc, Jp = evaluate(R, cp, X, True)
    if not np.isfinite(cost):
        bad = int(np.sum(~np.all(np.isfinite(r), axis=1)))
        raise ValueError(f"bundle adjustment: {bad} of {len(r)} residuals are not finite at the start "
                         "(NaN/inf in the observations, the points or the cameras, or a point on a camera's plane)")
    nfev = 1
    lam, nu = 1e-4, 2.0  # damping, and its growth after a rejected step (Nielsen's rule)
    newton = loss == "linear"
    msg, ok, iterations = "max_iter reached", False, 0
    for _ in range(max_iter):
        iterations += 1
        assert Jc is not None and Jp is not None
        z = r * r / fs2
        _, d1, d2 = _rho(z, loss)
        # Per residual component: gradient weight rho'(z); curvature weight rho'(z) (reweighted least
        # squares: robust far from the minimum) until the cost settles, then rho' + 2 rho'' z (the loss's
        # own second derivative in r, kept a little above 0 where the loss is straight: huber's tails),
        # which converges fast near the minimum where reweighting alone creeps.
        w = np.maximum(d1 + 2.0 * d2 * z, 1e-2 * d1) if newton else d1
        wJc = Jc * w[:, :, None]
        wJp = Jp * w[:, :, None]
        gr = (d1 * r)[:, :, None]
        # Blocks of J^T W J and of the gradient J^T rho' r.
        wJcT = wJc.transpose(0, 2, 1)
        U = _sum_blocks(cam, wJcT @ Jc, nc)
        V = _sum_blocks(pt, wJp.transpose(0, 2, 1) @ Jp, npnt)
        Wfull = np.zeros((npnt, nc, m, 3))
        Wfull[pt, cam] = wJcT @ Jp
        gc = _sum_blocks(cam, (Jc.transpose(0, 2, 1) @ gr)[:, :, 0], nc)
        gp = _sum_blocks(pt, (Jp.transpose(0, 2, 1) @ gr)[:, :, 0], npnt)
        dU = np.einsum("cii->ci", U)
        dV = np.einsum("pii->pi", V)
        accepted = False
        while lam < 1e12:
            Ua = U.copy()
            Ua[:, np.arange(m), np.arange(m)] += lam * np.maximum(dU, 1e-12)
            Va = V.copy()
            Va[:, np.arange(3), np.arange(3)] += lam * np.maximum(dV, 1e-12) + 1e-12
            Vinv = np.linalg.inv(Va)
            Z = Wfull @ Vinv[:, None]  # (p, c, m, 3)
            # Schur complement U - W V^-1 W^T: sum over points of (c, m) x (c', m') products, (c, m, c', m').
            S = -np.tensordot(Z, Wfull, axes=([0, 3], [0, 3])).reshape(nc * m, nc * m)
            for c in range(nc):
                S[c * m:(c + 1) * m, c * m:(c + 1) * m] += Ua[c]
            rhs = (-gc + np.tensordot(Z, gp, axes=([0, 3], [0, 1]))).ravel()
            Sf = S[np.ix_(fi, fi)]
            try:
                L = np.linalg.cholesky(Sf)
                dcf = np.linalg.solve(L.T, np.linalg.solve(L, rhs[fi]))
            except np.linalg.LinAlgError:
                lam, nu = lam * nu, nu * 2.0
                continue
            dc = np.zeros(nc * m)
            dc[fi] = dcf
            dc = dc.reshape(nc, m)
            dp = (Vinv @ (-gp - np.tensordot(Wfull, dc, axes=([1, 2], [0, 1])))[:, :, None])[:, :, 0]
            R_new = Rotation.from_rotvec(dc[:, :3]).as_matrix() @ R
            cp_new = cp.copy()
            cp_new[:, 3:] += dc[:, 3:]
            X_new = X + dp
            new_cost, r_new, _, _ = evaluate(R_new, cp_new, X_new, False)
            nfev += 1
            # The reduction the quadratic model predicts: for (H + lam D) d = -g it is
            # 0.5 (lam d^T D d - g^T d).
            g_d = float(np.sum(gc * dc) + np.sum(gp * dp))
            dDd = float(np.sum(np.maximum(dU, 1e-12) * dc**2) + np.sum(np.maximum(dV, 1e-12) * dp**2))
            predicted = 0.5 * (lam * dDd - g_d)
            if np.isfinite(new_cost) and new_cost < cost:
                accepted = True
                gain = (cost - new_cost) / predicted if predicted > 0 else 1.0
                step = float(np.sqrt(np.sum(dc**2) + np.sum(dp**2)))
                size = float(np.sqrt(np.sum(cp[:, 3:] ** 2) + np.sum(X**2)))
                drop = cost - new_cost
                R, cp, X, cost, r = R_new, cp_new, X_new, new_cost, r_new
                lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3), 1e-12)
                nu = 2.0
                break
            lam, nu = lam * nu, nu * 2.0
        if not accepted:
            msg, ok = "no step lowers the cost (converged to the damping limit)", True
            break
        if drop < ftol * cost and newton:
            msg, ok = "ftol: the cost changed by less than ftol", True
            break
        newton = newton or drop < 1e-3 * cost
        if step < xtol * (xtol + size):
            msg, ok = "xtol: the step is below xtol", True
            break
        _, r, Jc, Jp = evaluate(R, cp, X, True)
        nfev += 1
    return SchurResult(R, cp, X, r, cost, nfev, iterations, ok, msg)
