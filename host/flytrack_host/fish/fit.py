"""Pose and shape of one fish from the occluding contours (seed 004 §4.2, eq. 4.2).

Each contour pixel back-projects to a 3D line L = (l_v, l_m) in Plucker coordinates; its distance to a
surface point S is ||S x l_v - l_m||. The cost of a candidate state is the sum over cameras and contour
lines of the distance to the nearest point of the model surface, plus K_q (Delta l)^2 for a midline
length different from the model's. It is minimised by simulated annealing (Table 2's schedule, proposals
scored in batches) and then polished by a quasi-Newton search (scipy L-BFGS-B).

Speed: the cost is batched over candidate states; the point-line distances come from two matrix
products, ||S - p||^2 - ((S - p).v)^2 with p the foot of the line, and the nearest surface point is refined
by parabolic interpolation over the ellipse angle u and over s (exact for a straight generator), so the
cost is smooth enough for the quasi-Newton step. Lengths are in millimetres inside the cost, relative to
the predicted head position, to keep the numbers well scaled.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares, minimize

from flytrack_host.fish.kernel import line_distances_c
from flytrack_host.fish.shape import ShapeModel, angles_from_heading, arclength, heading_from_angles
from flytrack_host.fish.views import View

F64 = NDArray[np.float64]
MM = 1000.0
# the optimiser's variables z: r (mm), yaw and pitch (units of ANG rad), p (mm)
ANG = 0.02
N_Z = 10


@dataclass
class FitConfig:
    """Table 2 of seed 004 where it applies; the tracking budget (levels, batch) is ours."""

    kq: float = 10.0  # K_q, weight of the length penalty (per mm^2)
    tau0: float = 1.0  # starting temperature
    tau_f: float = 1e-6  # freezing temperature
    kc: float = 0.9  # cooling coefficient
    n_max: int = 400  # maximum unsuccessful evaluations at one temperature
    sigma_w: float = 1.0  # variance of the SA proposals (in the scaled variables z)
    batch: int = 16  # proposals scored per NumPy pass
    max_levels: int = 6  # temperature levels per frame when tracking (the full schedule has 131)
    qn_maxiter: int = 15
    polish: str = "lsq"
    max_lines: int = 200  # contour lines per blob and camera (evenly subsampled)
    outside_weight: float = 1.0  # our addition to eq. 4.2: model points seen outside the silhouettes
    prior_weight: float = 0.2  # weak pull to the prediction; only matters for a fish hidden in a view
    prior_sigma: tuple[float, ...] = (3.0, 3.0, 3.0, 5.0, 5.0, 5.0, 5.0, 8.0, 8.0, 8.0)  # in z units
    rng_seed: int = 0


def z_from_state(X: F64, r0: F64) -> F64:
    X = np.atleast_2d(X)
    yaw, pitch = angles_from_heading(X[:, 3:6])
    return np.concatenate([(X[:, 0:3] - r0) * MM, yaw[:, None] / ANG, pitch[:, None] / ANG, X[:, 6:11] * MM], axis=1)


def state_from_z(Z: F64, r0: F64) -> F64:
    Z = np.atleast_2d(Z)
    h = heading_from_angles(Z[:, 3] * ANG, Z[:, 4] * ANG)
    return np.concatenate([Z[:, 0:3] / MM + r0, h, Z[:, 5:10] / MM], axis=1)


@dataclass
class LineSet:
    """Back-projected contour lines of one blob in one camera, relative to r0 and in mm: feet p (N,3)
    (the line's point nearest r0) and unit directions v (N,3). Plucker moment l_m = p x v."""

    p: F64
    v: F64
    camera: int = 0

    @property
    def moment(self) -> F64:
        return np.cross(self.p, self.v)


def contour_lines(view: View, contour: F64, r0: F64, max_lines: int, camera: int = 0) -> LineSet:
    if len(contour) > max_lines:
        idx = np.linspace(0, len(contour), max_lines, endpoint=False).astype(int)
        contour = contour[idx]
    o, v = view.lines(contour)
    ok = np.all(np.isfinite(v), axis=1)
    o = (o[ok] - r0) * MM
    v = v[ok]
    p = o - v * np.sum(o * v, axis=1, keepdims=True)
    return LineSet(p, v, camera)


def _parabolic_min(y: F64, axis: int, cyclic: bool) -> F64:
    """Minimum over `axis` refined by a parabola through the least sample and its two neighbours (cyclic:
    around the ellipse; else the ends are not refined). The C kernel applies the same rule."""
    k = np.argmin(y, axis=axis)
    n = y.shape[axis]
    ke = np.expand_dims(k, axis)
    y0 = np.take_along_axis(y, ke, axis)
    if cyclic:
        ym = np.take_along_axis(y, (ke - 1) % n, axis)
        yp = np.take_along_axis(y, (ke + 1) % n, axis)
        inner = np.ones_like(y0, dtype=bool)
    else:
        ym = np.take_along_axis(y, np.clip(ke - 1, 0, n - 1), axis)
        yp = np.take_along_axis(y, np.clip(ke + 1, 0, n - 1), axis)
        inner = (ke > 0) & (ke < n - 1)
    den = ym + yp - 2.0 * y0
    dif = ym - yp
    ok = inner & (den > np.abs(dif) + 1e-12)
    v = np.where(ok, y0 - dif * dif / (8.0 * np.where(ok, den, 1.0)), y0)
    return np.squeeze(np.maximum(v, 0.0), axis=axis)


def line_distances(S: F64, lines: LineSet, use_c: bool = True) -> F64:
    """Distance (mm) of each line to the surface, min over the surface: S (B, Ns, Nu, 3) in mm -> (B, N).
    The C kernel when built (same rule, skips far stations), else NumPy."""
    if use_c:
        D = line_distances_c(S, lines.p, lines.v)
        if D is not None:
            return D
    return line_distances_numpy(S, lines)


def line_distances_numpy(S: F64, lines: LineSet) -> F64:
    p, v = lines.p, lines.v
    SS = np.einsum("bsuk,bsuk->bsu", S, S)[..., None]
    Sp = S @ p.T
    Sv = S @ v.T
    pp = np.einsum("nk,nk->n", p, p)
    d2 = SS - 2.0 * Sp + pp - Sv * Sv  # |S - p|^2 - ((S - p).v)^2 with p.v = 0
    e = _parabolic_min(d2, axis=2, cyclic=True)  # (B, Ns, N)
    e = _parabolic_min(e, axis=1, cyclic=False)  # (B, N)
    return np.sqrt(e)


@dataclass
class OutsideMap:
    """How far outside the silhouettes each pixel of one camera is (px): 0 inside the half-coverage edge,
    rising to 0.5 at the fully clear pixel next to it, then the distance to the silhouette. Eq. 4.2 alone
    lets a model pierce the contour lines (a line through the body is at distance 0), which leaves the
    length and the bend along the lines of sight loose; this term closes that."""

    view: View
    field: NDArray[np.float32]
    mm_per_px: float
    r0: F64
    origin: tuple[int, int] = (0, 0)  # image position of field[0, 0] (the field covers a window)
    beyond: float = 40.0  # value outside the window (px)

    @classmethod
    def build(cls, view: View, fg: NDArray[np.float32], mask: NDArray[np.uint8], mm_per_px: float, r0: F64,
              window: tuple[int, int, int, int] | None = None) -> OutsideMap:
        """`window` (x0, y0, x1, y1) limits the work to the pixels near the fish."""
        import cv2

        x0, y0, x1, y1 = window if window is not None else (0, 0, mask.shape[1], mask.shape[0])
        m = mask[y0:y1, x0:x1]
        dt = cv2.distanceTransform((m == 0).astype(np.uint8), cv2.DIST_L2, 3)
        f = np.clip(0.5 - fg[y0:y1, x0:x1], 0.0, 0.5) + np.maximum(dt - 1.0, 0.0)
        return cls(view, f.astype(np.float32), mm_per_px, r0, (x0, y0), float(max(x1 - x0, y1 - y0)) / 2)

    def values(self, S_mm: F64) -> F64:
        """S (B, Ns, Nu, 3) in mm about r0 -> outside distance (mm) of each point (B, Ns*Nu)."""
        import cv2

        B = S_mm.shape[0]
        uv = self.view.project(S_mm.reshape(-1, 3) / MM + self.r0) - np.asarray(self.origin, float)
        uv = np.where(np.isnan(uv), -1e4, uv).astype(np.float32)  # off the map (as np.nan_to_num, cheaper)
        vals = cv2.remap(self.field, uv[None, :, 0], uv[None, :, 1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=self.beyond)
        return vals.reshape(B, -1).astype(np.float64) * self.mm_per_px

    def __call__(self, S_mm: F64) -> F64:
        return self.values(S_mm).sum(axis=1)


@dataclass
class FishCost:
    """Eq. 4.2 for one fish: lines of its blobs in each camera; `others[i]` the distance (mm) of line set
    i to the surfaces of the other fish sharing that blob (an occlusion), so those lines are explained
    by whichever fish is nearer."""

    model: ShapeModel
    r0: F64
    line_sets: list[LineSet]
    others: list[F64 | None]
    length_mm: float
    kq: float = 10.0
    z_prior: F64 | None = None
    prior_sigma: F64 | None = None
    prior_weight: float = 0.0
    outside: list[OutsideMap] = field(default_factory=list)
    outside_weight: float = 1.0
    evaluations: int = field(default=0)

    def residuals(self, Z: F64) -> F64:
        """The terms of the cost as a residual vector per state (B, M), for the least-squares polish:
        line distances (mm), outside distances (mm), sqrt(K_q) Delta l, the prior's whitened offsets."""
        Z = np.atleast_2d(Z)
        self.evaluations += Z.shape[0]
        X = np.concatenate([Z[:, 0:3], heading_from_angles(Z[:, 3] * ANG, Z[:, 4] * ANG), Z[:, 5:10]], axis=1)
        S = self.model.surface(X)
        parts = []
        for ls, oth in zip(self.line_sets, self.others, strict=True):
            if len(ls.p) == 0:
                continue
            D = line_distances(S, ls)
            if oth is not None:
                D = np.minimum(D, oth[None, :])
            parts.append(D)
        for om in self.outside:
            parts.append(np.sqrt(self.outside_weight) * om.values(S))
        dl = arclength(Z[:, 5:10]) - self.length_mm
        parts.append(np.sqrt(self.kq) * dl[:, None])
        if self.prior_weight > 0 and self.z_prior is not None and self.prior_sigma is not None:
            parts.append(np.sqrt(self.prior_weight) * (Z - self.z_prior) / self.prior_sigma)
        return np.concatenate(parts, axis=1)

    def __call__(self, Z: F64) -> F64:
        """Eq. 4.2 (sum of line distances + K_q Delta l^2) plus the outside and prior terms."""
        Z = np.atleast_2d(Z)
        self.evaluations += Z.shape[0]
        # the state in mm about r0, as the lines are
        X = np.concatenate([Z[:, 0:3], heading_from_angles(Z[:, 3] * ANG, Z[:, 4] * ANG), Z[:, 5:10]], axis=1)
        S = self.model.surface(X)
        c = np.zeros(Z.shape[0])
        for ls, oth in zip(self.line_sets, self.others, strict=True):
            if len(ls.p) == 0:
                continue
            D = line_distances(S, ls)
            if oth is not None:
                D = np.minimum(D, oth[None, :])
            c += D.sum(axis=1)
        for om in self.outside:
            c += self.outside_weight * om(S)
        dl = arclength(Z[:, 5:10]) - self.length_mm
        c += self.kq * dl * dl
        if self.prior_weight > 0 and self.z_prior is not None and self.prior_sigma is not None:
            c += self.prior_weight * np.sum(((Z - self.z_prior) / self.prior_sigma) ** 2, axis=1)
        return c


def model_in_mm(model: ShapeModel) -> ShapeModel:
    return ShapeModel(model.s, model.a * MM, model.b * MM, model.d * MM, model.length * MM, model.n_u)


def anneal(cost: Callable[[F64], F64], z0: F64, cfg: FitConfig, rng: np.random.Generator,
           levels: int | None = None) -> tuple[F64, float, int]:
    """Simulated annealing (seed 004 §2.2): Gaussian proposals (variance sigma_w), Metropolis acceptance at
    temperature tau, tau <- K_c tau, a level ends after n_max unsuccessful evaluations; stops at tau_f or
    after `levels` levels. Proposals are drawn and scored `batch` at a time, then accepted in order.
    Returns the best state seen, its cost and the number of evaluations."""
    z = np.asarray(z0, float).copy()
    c = float(cost(z[None])[0])
    best_z, best_c = z.copy(), c
    tau = cfg.tau0
    n_eval = 1
    level = 0
    sd = np.sqrt(cfg.sigma_w)
    max_levels = levels if levels is not None else 10**9
    while tau > cfg.tau_f and level < max_levels:
        fails = 0
        while fails < cfg.n_max:
            Zc = z + rng.normal(0.0, sd, (cfg.batch, z.size))
            C = cost(Zc)
            n_eval += cfg.batch
            accepted = False
            for i in range(cfg.batch):
                dc = C[i] - c
                if dc <= 0 or rng.random() <= np.exp(-dc / tau):
                    z, c = Zc[i], float(C[i])
                    accepted = True
                    if c < best_c:
                        best_z, best_c = z.copy(), c
                else:
                    fails += 1
            if levels is not None and (accepted or fails >= cfg.batch):
                break  # tracking budget: one batch per level
        tau *= cfg.kc
        level += 1
    return best_z, best_c, n_eval


def quasi_newton(cost: Callable[[F64], F64], z0: F64, maxiter: int = 15, h: float = 1e-3) -> tuple[F64, float, int]:
    """L-BFGS-B with the gradient by forward differences scored in one batch."""
    n = z0.size
    E = np.eye(n) * h
    count = [0]

    def fg(z: F64) -> tuple[float, F64]:
        Zs = np.vstack([z, z + E])
        C = cost(Zs)
        count[0] += Zs.shape[0]
        return float(C[0]), (C[1:] - C[0]) / h

    res = minimize(fg, z0, jac=True, method="L-BFGS-B", options={"maxiter": maxiter, "gtol": 1e-4})
    return res.x, float(res.fun), count[0]


def least_squares_polish(cost: FishCost, z0: F64, maxiter: int = 15, h: float = 1e-3,
                         f_scale: float = 0.3) -> tuple[F64, int]:
    """Trust-region Gauss-Newton on the cost's residuals with a soft-L1 loss (an L1 sum of distances far
    from the fit, like eq. 4.2, quadratic near it); the Jacobian by forward differences in one batch."""
    n = z0.size
    E = np.eye(n) * h
    cache: dict[bytes, F64] = {}
    count = [0]

    def both(z: F64) -> tuple[F64, F64]:
        R = cost.residuals(np.vstack([z, z + E]))
        count[0] += n + 1
        return R[0], ((R[1:] - R[0]) / h).T

    def fun(z: F64) -> F64:
        key = z.tobytes()
        if key not in cache:
            r, J = both(z)
            cache.clear()
            cache[key] = J
            cache[key + b"r"] = r
        return cache[key + b"r"]

    def jac(z: F64) -> F64:
        key = z.tobytes()
        if key not in cache:
            fun(z)
        return cache[key]

    res = least_squares(fun, z0, jac=jac, method="trf", loss="soft_l1", f_scale=f_scale, max_nfev=maxiter,
                        x_scale=1.0)
    return res.x, count[0]


def fit_fish(cost: FishCost, z0: F64, cfg: FitConfig, rng: np.random.Generator, sa_levels: int | None = None,
             qn: bool = True) -> tuple[F64, float, int]:
    """SA then a local polish from z0 (cfg.polish: "lsq" Gauss-Newton on the residuals, "bfgs" scipy's
    L-BFGS-B quasi-Newton on the cost itself); returns (z, cost, evaluations)."""
    z, c, n = anneal(cost, z0, cfg, rng, levels=cfg.max_levels if sa_levels is None else sa_levels)
    if qn:
        if cfg.polish == "bfgs":
            z2, c2, n2 = quasi_newton(cost, z, cfg.qn_maxiter)
        else:
            z2, n2 = least_squares_polish(cost, z, cfg.qn_maxiter)
            c2 = float(cost(z2[None])[0])
            n2 += 1
        n += n2
        if c2 <= c:
            z, c = z2, c2
    return z, c, n


def make_cost(model_mm: ShapeModel, r0: F64, line_sets: list[LineSet], others: list[F64 | None],
              cfg: FitConfig, z_prior: F64 | None = None, length_mm: float | None = None,
              outside: list[OutsideMap] | None = None) -> FishCost:
    return FishCost(model_mm, r0, line_sets, others, model_mm.length if length_mm is None else length_mm, cfg.kq,
                    z_prior, np.asarray(cfg.prior_sigma, float), cfg.prior_weight if z_prior is not None else 0.0,
                    outside or [], cfg.outside_weight)


def surface_mm(model_mm: ShapeModel, X: F64, r0: F64) -> F64:
    """The surface of states X (B,11, metres) in mm about r0, as FishCost sees it."""
    Xm = np.atleast_2d(X).copy()
    Xm[:, 0:3] = (Xm[:, 0:3] - r0) * MM
    Xm[:, 6:11] *= MM
    return model_mm.surface(Xm)
