"""Model generation (seed 004 §3): from one frame where a fish is in clear view in the top and a side camera,
find the head centre (centre of the largest circle inside the top silhouette), the tail (highest curvature
of the occluding contour) and the nose (highest curvature near the head, away from the tail); lift head
and nose to 3D with the side view's head-to-tail line (the seed's l_m, l_r constraints); fit the midline
parameters p by eq. 3.3 (SA, then quasi-Newton); estimate the cross-sections a(s), b(s), d(s) with the
iterated EKF from the silhouette widths normal to the projected midline (eq. 3.8).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates
from scipy.optimize import brentq, minimize

from flytrack_host.fish.fit import FitConfig, anneal
from flytrack_host.fish.iekf import iekf_update
from flytrack_host.fish.shape import ShapeModel, default_model, make_state, midline_world
from flytrack_host.fish.silhouette import Blob, Silhouettes
from flytrack_host.fish.views import GridProjection, View, refracts

F64 = NDArray[np.float64]


class ModelError(ValueError):
    """The frame does not give a model (fish not in clear view, a view missing)."""


@dataclass
class ModelResult:
    model: ShapeModel
    X: F64  # (11,) the state in this frame
    head_px: F64
    nose_px: F64
    tail_px: F64
    midline_cost_px: float  # eq. 3.3's mean q* at the solution
    iekf_iterations: int
    blobs: tuple[int, int] = (-1, -1)  # the top and side blobs it was made from


def _contour_curvature(c: F64, k: int) -> F64:
    """Turning angle at each contour point between the chords to the points k before and k after."""
    a = c - np.roll(c, k, axis=0)
    b = np.roll(c, -k, axis=0) - c
    ang = np.arctan2(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0], np.sum(a * b, axis=1))
    return np.abs(ang)


def landmarks(blob: Blob, shape: tuple[int, int]) -> tuple[F64, float, F64, F64]:
    """Head centre (px), head radius (px), nose (px), tail (px) of a top-view silhouette."""
    x, y, w, h = blob.bbox
    m = np.zeros((h + 2, w + 2), np.uint8)
    m[(blob.pixels[:, 1] - y + 1).astype(int), (blob.pixels[:, 0] - x + 1).astype(int)] = 1
    dt = cv2.distanceTransform(m, cv2.DIST_L2, 5)
    c = blob.contour
    if len(c) < 20:
        raise ModelError("silhouette too small for a model")
    # the largest inscribed circle, to sub-pixel: its radius at each candidate centre near the pixel maximum
    # is the distance to the sub-pixel contour; along a fish the radius has a flat top, so the centre is
    # taken as the centroid of the candidates within 0.15 px of the largest radius
    from scipy.spatial import cKDTree

    yy, xx = np.nonzero(dt >= dt.max() - 1.5)
    fine = np.stack([xx + x - 1, yy + y - 1], axis=1).astype(float)
    offs = np.stack(np.meshgrid(np.arange(-0.5, 0.51, 0.25), np.arange(-0.5, 0.51, 0.25)), -1).reshape(-1, 2)
    cand = (fine[:, None] + offs[None]).reshape(-1, 2)
    rho, _ = cKDTree(c).query(cand)
    top = rho >= rho.max() - 0.15
    head = cand[top].mean(axis=0)
    rad = float(rho.max())
    k = max(3, len(c) // 40)
    curv = _contour_curvature(c, k)
    curv = np.convolve(np.concatenate([curv[-2:], curv, curv[:2]]), np.ones(5) / 5, mode="valid")
    tail = c[int(np.argmax(curv))]
    dh = np.linalg.norm(c - head, axis=1)
    away = (c - head) @ (tail - head) < 0
    near = away & (dh < 4.0 * rad)
    if not np.any(near):
        raise ModelError("no nose found: the head is not clear in the top view")
    idx = np.flatnonzero(near)
    nose = c[idx[int(np.argmax(curv[idx]))]]
    return head, rad, nose, tail


def side_line(blob: Blob) -> tuple[float, float]:
    """Least-squares line v = l_m u + l_r through a side silhouette (the seed's head-to-tail line)."""
    u, v = blob.pixels[:, 0], blob.pixels[:, 1]
    A = np.stack([u, np.ones_like(u)], axis=1)
    (lm, lr), *_ = np.linalg.lstsq(A, v, rcond=None)
    return float(lm), float(lr)


def lift(top: View, side: View, uv: F64, line: tuple[float, float], zrange: tuple[float, float]) -> F64:
    """The 3D point on the top camera's line of sight through uv whose side projection is on the line."""
    o, d = top.lines(uv[None])
    o, d = o[0], d[0]

    def g(z: float) -> float:
        lam = (z - o[2]) / d[2]
        q = side.project((o + lam * d)[None])[0]
        return float(q[1] - (line[0] * q[0] + line[1]))

    zs = np.linspace(zrange[0], zrange[1], 41)
    gs = np.array([g(z) for z in zs])
    ok = np.isfinite(gs)
    sign = np.flatnonzero(ok[:-1] & ok[1:] & (np.sign(gs[:-1]) != np.sign(gs[1:])))
    if len(sign) == 0:
        raise ModelError("the side view's line does not meet the top view's line of sight in the tank")
    i = sign[0]
    z = brentq(g, zs[i], zs[i + 1], xtol=1e-7)
    lam = (z - o[2]) / d[2]
    return o + lam * d


def _midline_cost(views_top: View, X_base: F64, P: F64, pix: F64, tail_px: F64, s: F64, w_tail: float) -> F64:
    """Eq. 3.3 for candidate p (B,5): mean over silhouette pixels of the distance to the projected midline,
    plus the tail constraint u_hat(1) = u_t as a penalty."""
    B = P.shape[0]
    X = np.repeat(X_base[None], B, axis=0)
    X[:, 6:11] = P
    m, _ = midline_world(X, s)
    uv = views_top.project(m)  # (B, Ns, 2)
    # nearest midline point of each pixel: squared distances, the root only of the minimum
    dx = pix[None, :, None, 0] - uv[:, None, :, 0]
    dy = pix[None, :, None, 1] - uv[:, None, :, 1]
    d = np.sqrt((dx * dx + dy * dy).min(axis=2))
    tail = np.linalg.norm(uv[:, -1] - tail_px[None], axis=1)
    c = d.mean(axis=1) + w_tail * tail**2
    return np.where(np.isfinite(c), c, 1e9)


def _march(fg: NDArray[np.float32], start: F64, direction: F64, max_px: float) -> float:
    """Distance (px) from start along direction to where fg falls below 0.5 (sub-pixel), NaN if never."""
    t = np.arange(0.0, max_px, 0.25)
    pts = start[None] + t[:, None] * direction[None]
    vals = map_coordinates(fg, [pts[:, 1], pts[:, 0]], order=1, cval=0.0)
    below = np.flatnonzero(vals < 0.5)
    if len(below) == 0 or below[0] == 0:
        return float("nan")
    i = below[0]
    f0, f1 = vals[i - 1], vals[i]
    return float(t[i - 1] + (f0 - 0.5) / max(f0 - f1, 1e-6) * (t[i] - t[i - 1]))


def _widths(view: View, fg: NDArray[np.float32], mid_uv: F64, max_px: float) -> tuple[F64, F64]:
    """Half-width and signed centre offset of the silhouette normal to the projected midline, per point."""
    tang = np.gradient(mid_uv, axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    nrm = np.stack([-tang[:, 1], tang[:, 0]], axis=1)
    half = np.full(len(mid_uv), np.nan)
    off = np.full(len(mid_uv), np.nan)
    for i, (p, n) in enumerate(zip(mid_uv, nrm, strict=True)):
        a = _march(fg, p, n, max_px)
        b = _march(fg, p, -n, max_px)
        half[i] = 0.5 * (a + b)
        off[i] = 0.5 * (a - b)
    return half, off, nrm


def generate_model(top: View, side: View, sil_top: Silhouettes, sil_side: Silhouettes, blob_top: int,
                   blob_side: int, zrange: tuple[float, float] = (0.0, 0.4), length_hint: float | None = None,
                   cfg: FitConfig | None = None, seed: int = 0) -> ModelResult:
    cfg = cfg or FitConfig()
    bt = sil_top.blobs[blob_top]
    bs = sil_side.blobs[blob_side]
    head_px, rad, nose_px, tail_px = landmarks(bt, sil_top.mask.shape)
    line = side_line(bs)
    r = lift(top, side, head_px, line, zrange)
    nose3 = lift(top, side, nose_px, line, zrange)
    h = nose3 - r
    h /= np.linalg.norm(h)
    # scale of the top view at the head, for the starting length
    o, dvec = top.lines(np.stack([head_px, tail_px]))
    lam = (r[2] - o[:, 2]) / dvec[:, 2]
    tail3 = o[1] + lam[1] * dvec[1]
    L0 = float(np.linalg.norm(tail3 - r)) if length_hint is None else length_hint
    nose_frac = float(np.linalg.norm(nose3 - r)) / max(L0, 1e-6)
    if refracts(top):  # many projections near this fish through a refracting camera: tabulate them
        top = GridProjection(top, r - 0.5 * L0 * h, half=0.6 * L0 + 0.01)
    if refracts(side):
        side = GridProjection(side, r - 0.5 * L0 * h, half=0.6 * L0 + 0.01)
    base = default_model(L0)
    # eq. 3.3: midline p by SA then quasi-Newton, head and heading fixed
    X_base = make_state(r, h, [L0, 0, 0, 0, 0])[0]
    pix = bt.pixels
    if len(pix) > 500:
        pix = pix[:: int(np.ceil(len(pix) / 500))]
    s = np.linspace(0.0, 1.0, 40)
    scale = L0 / 50.0  # p in units of 1/50 of the length in the search
    def cost(Z: F64) -> F64:
        return _midline_cost(top, X_base, np.atleast_2d(Z) * scale, pix, tail_px, s, 0.05)
    rng = np.random.default_rng(seed)
    sa_cfg = FitConfig(tau0=1.0, tau_f=1e-3, kc=0.8, n_max=cfg.batch, batch=cfg.batch)
    z0 = np.array([50.0, 0, 0, 0, 0])
    z, c, _ = anneal(cost, z0, sa_cfg, rng, levels=30)
    def cost_grad(q: F64) -> tuple[float, F64]:
        # the forward-difference gradient (scipy's default step) scored in one batch with the value
        h = 1.4901161193847656e-08 * np.maximum(1.0, np.abs(q))
        C = cost(np.vstack([q, q + np.diag(h)]))
        return float(C[0]), (C[1:] - C[0]) / h

    res = minimize(cost_grad, z, jac=True, method="BFGS", options={"maxiter": 200})
    if res.fun < c:
        z, c = res.x, float(res.fun)
    p = z * scale
    # one fish in clear view: its silhouette pixels lie, on average, within about half its widest half-width
    # of the fitted midline (for a fish ~0.4 of the radius); two fish touching, or a fish with another
    # across it, leave many pixels far from any one midline
    if not c < 0.8 * rad + 1.0:
        raise ModelError(f"the top silhouette is not one fish in clear view (mean distance to the midline "
                         f"{c:.1f} px, head radius {rad:.1f} px)")
    X = make_state(r, h, p)[0]
    # eq. 3.8 by the iterated EKF: a from the top view, b and d from the side view, at each station
    st = np.concatenate([-nose_frac * np.array([0.7, 0.4]), base.s[base.s >= 0]])
    st = st[(st > -nose_frac) & (st < 1.0)]
    m, _ = midline_world(X[None], st)
    uv_top = top.project(m[0])
    uv_side = side.project(m[0])
    wa, _, _ = _widths(top, sil_top.fg, uv_top, 4 * rad + 10)
    wb, wd, nrm_side = _widths(side, sil_side.fg, uv_side, 60.0)
    n = len(st)
    proto = ShapeModel(st, np.ones(n), np.ones(n), np.zeros(n), p[0], base.n_u)

    def hfun(Xs: F64) -> F64:
        out = np.empty((Xs.shape[0], 3 * n))
        for i, xv in enumerate(Xs):
            mdl = proto.copy_with(xv[:n], xv[n:2 * n], xv[2 * n:])
            S = mdl.surface(X[None], u=np.array([0.0, np.pi, np.pi / 2, 3 * np.pi / 2]))[0]
            t0, t1 = top.project(S[:, 0]), top.project(S[:, 1])
            s0, s1 = side.project(S[:, 2]), side.project(S[:, 3])
            out[i, :n] = np.linalg.norm(t0 - t1, axis=1) / 2
            out[i, n:2 * n] = np.linalg.norm(s0 - s1, axis=1) / 2
            out[i, 2 * n:] = np.sum(((s0 + s1) / 2 - uv_side) * nrm_side, axis=1)
        return out

    zmeas = np.concatenate([wa, wb, wd])
    ok = np.isfinite(zmeas)
    if ok.sum() < n:
        raise ModelError("too few cross-sections measured: the fish is not in clear view")
    a0 = np.interp(st, base.s, base.a)
    b0 = np.interp(st, base.s, base.b)
    x0 = np.concatenate([a0, b0, np.zeros(n)])
    P0 = np.diag(np.concatenate([(0.5 * a0 + 0.001) ** 2, (0.5 * b0 + 0.001) ** 2, np.full(n, 0.003**2)]))
    R = np.diag(np.concatenate([np.full(n, 1.0), np.full(n, 2.0), np.full(n, 2.0)])[ok])  # e1 = 1, e2 = 2 px^2
    res_k = iekf_update(lambda Xs: hfun(Xs)[:, ok], zmeas[ok], R, x0, P0, max_iter=15, eps=1e-6)
    xa = np.clip(res_k.x, [1e-4] * (2 * n) + [-0.02] * n, None)
    # the nose tip closes the head; the tail keeps its last measured size
    s_all = np.concatenate([[-nose_frac], st, [1.0]])
    a_all = np.concatenate([[0.15 * xa[0]], xa[:n], [xa[n - 1]]])
    b_all = np.concatenate([[0.15 * xa[n]], xa[n:2 * n], [xa[2 * n - 1]]])
    d_all = np.concatenate([[xa[2 * n]], xa[2 * n:], [xa[3 * n - 1]]])
    from flytrack_host.fish.shape import arclength

    length = float(arclength(p[None])[0])
    model = ShapeModel(s_all, a_all, b_all, d_all, length, base.n_u)
    return ModelResult(model, X, head_px, nose_px, tail_px, float(c), res_k.iterations, (blob_top, blob_side))
