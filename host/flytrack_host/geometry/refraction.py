"""Refraction at a flat interface (water surface, aquarium wall): the one model FlyTrack uses.

A camera in one medium (index n_near, usually air) sees points in another (n_far, water 1.333) through
a plane given by a point and a unit normal that points INTO the camera's medium. A ray from the camera
centre C to the interface point S is straight; from S to the point X it is bent by Snell's law
(n_near sin(theta_near) = n_far sin(theta_far)). Points on the camera's side of the plane are seen
directly. This is Braid's `<water>` (plane z = 0, normal +z, cameras above) and the fish rig's tank
walls (a vertical plane per side camera; the thin glass is neglected).

API (all functions broadcast over leading dimensions; points are (..., 3) arrays):
  FlatInterface(point, normal, n_far, n_near=1.0), FlatInterface.water_surface(n=1.333)
  refraction_point(C, X, iface)            -> S, the point on the plane where the ray C..X bends
  refraction_point_jacobian(C, X, S, iface) -> dS/dX (..., 3, 3) by the implicit function theorem
  refract(d, iface)                         -> direction after the interface (NaN on total reflection)
  trace_rays(C, d, iface)                   -> (origin on the plane, refracted direction) of air rays
  triangulate_rays(origins, dirs, weights)  -> least-squares point nearest to a set of 3D lines
Camera (camera.py) uses these when its `interface` is set: project, project_jacobian, refracted_rays,
and camera.triangulate; the tracker's CameraArray (tracking/observation.py) does the same for all
(camera, target) pairs.

How S is found: by Fermat's principle S minimises n_near |S - C| + n_far |X - S|; S lies on the line
between the feet of C and X on the plane, at distance r from C's foot, where
f(r) = n_near r / sqrt(r^2 + hc^2) - n_far (d - r) / sqrt((d - r)^2 + hx^2) = 0 (hc, hx: heights of C
and X from the plane, d: distance between the feet). f rises monotonically from f(0) <= 0 to f(d) >= 0,
so Newton's method safeguarded by bisection converges from any start (to 1e-13 of d here).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]
WATER_INDEX = 1.333  # Braid's and flydra's default for <water>
# The index of air flydra and Braid use for the camera side of <water> (flydra-mvg AIR_REFRACTION): with
# 1.0 instead, a point 3 cm under the surface projects up to 5 mpx off their pixels and triangulates
# from them 10 um off.
AIR_INDEX = 1.0003


@dataclass(frozen=True)
class FlatInterface:
    """A plane through `point` with unit `normal` pointing into the camera's medium (index n_near);
    beyond it is the medium of index n_far."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    n_far: float
    n_near: float = 1.0

    def __post_init__(self) -> None:
        p = np.asarray(self.point, dtype=np.float64).reshape(3)
        n = np.asarray(self.normal, dtype=np.float64).reshape(3)
        norm = float(np.linalg.norm(n))
        if not (np.all(np.isfinite(p)) and np.isfinite(norm) and norm > 0):
            raise ValueError("a refractive interface needs a finite point and a non-zero normal")
        if not (np.isfinite(self.n_far) and np.isfinite(self.n_near) and self.n_far > 0 and self.n_near > 0):
            raise ValueError(f"refractive indices must be positive, got {self.n_near} and {self.n_far}")
        object.__setattr__(self, "point", tuple(float(v) for v in p))
        object.__setattr__(self, "normal", tuple(float(v) for v in n / norm))
        object.__setattr__(self, "n_far", float(self.n_far))
        object.__setattr__(self, "n_near", float(self.n_near))

    @classmethod
    def water_surface(cls, n_water: float = WATER_INDEX, z: float = 0.0) -> FlatInterface:
        """Braid's `<water>`: the surface z = 0 (or z), cameras in air above (index AIR_INDEX, as flydra
        and Braid take it), points in water below."""
        return cls(point=(0.0, 0.0, float(z)), normal=(0.0, 0.0, 1.0), n_far=float(n_water), n_near=AIR_INDEX)

    @property
    def is_braid_water(self) -> bool:
        """Whether this is exactly what a flydra/Braid XML `<water>` element describes."""
        return self.point[2] == 0.0 and self.normal == (0.0, 0.0, 1.0) and self.n_near == AIR_INDEX

    def p(self) -> F64:
        return np.asarray(self.point)

    def n(self) -> F64:
        return np.asarray(self.normal)

    def height(self, X: ArrayLike) -> F64:
        """Signed distance of points from the plane, positive on the camera's side."""
        return (np.asarray(X, dtype=np.float64) - self.p()) @ self.n()

    def beyond(self, X: ArrayLike) -> NDArray[np.bool_]:
        """Which points lie in the far medium (their rays are refracted)."""
        return self.height(X) < 0.0


def _stack_params(iface: FlatInterface | tuple[F64, F64, F64, F64]) -> tuple[F64, F64, F64, F64]:
    """(point, normal, n_near, n_far) as arrays; a tuple of arrays passes through (CameraArray uses
    per-camera parameters shaped to broadcast)."""
    if isinstance(iface, FlatInterface):
        return iface.p(), iface.n(), np.asarray(iface.n_near), np.asarray(iface.n_far)
    return iface


def refraction_point(C: ArrayLike, X: ArrayLike, iface: FlatInterface | tuple, iterations: int = 60) -> F64:
    """The point S (..., 3) on the plane where the ray from camera centre C (..., 3) to X (..., 3) bends.
    X must lie beyond the plane and C on the camera side; elsewhere S is NaN."""
    p0, n, n1, n2 = _stack_params(iface)
    C = np.asarray(C, dtype=np.float64)
    X = np.asarray(X, dtype=np.float64)
    hc = np.sum((C - p0) * n, axis=-1)
    hx = -np.sum((X - p0) * n, axis=-1)
    Cf = C - hc[..., None] * n
    Xf = X + hx[..., None] * n
    w = Xf - Cf
    d = np.sqrt(np.sum(w * w, axis=-1))
    ok = (hc > 0) & (hx > 0)
    e = w / np.where(d > 0, d, 1.0)[..., None]
    n1 = np.broadcast_to(n1, d.shape)
    n2 = np.broadcast_to(n2, d.shape)
    hc2 = np.where(ok, hc, 1.0) ** 2
    hx2 = np.where(ok, hx, 1.0) ** 2
    # Safeguarded Newton on f(r) (module docstring); start from the straight line's crossing.
    lo = np.zeros_like(d)
    hi = d.copy()
    with np.errstate(invalid="ignore", divide="ignore"):
        r = d * np.where(ok, hc / (hc + hx), 0.5)
    tol = 1e-13 * np.maximum(d, 1e-300)
    for _ in range(iterations):
        a = np.sqrt(r * r + hc2)
        q = d - r
        b = np.sqrt(q * q + hx2)
        f = n1 * r / a - n2 * q / b
        df = n1 * hc2 / a**3 + n2 * hx2 / b**3
        lo = np.where(f < 0, r, lo)
        hi = np.where(f > 0, r, hi)
        step = f / df
        rn = r - step
        out = ~((rn > lo) & (rn < hi))
        rn = np.where(out, 0.5 * (lo + hi), rn)
        done = np.abs(rn - r) <= tol
        r = rn
        if np.all(done | ~ok):
            break
    S = Cf + r[..., None] * e
    return np.where(ok[..., None], S, np.nan)


def refraction_point_jacobian(C: ArrayLike, X: ArrayLike, S: ArrayLike, iface: FlatInterface | tuple) -> F64:
    """dS/dX (..., 3, 3) at the solution S of refraction_point. S is stationary for the optical path
    L = n_near |S - C| + n_far |X - S| along the plane: g = E^T grad_S L = 0 with E the plane's basis.
    Implicitly dS/dX = E (E^T H E)^-1 E^T n_far M2 / l2, with H = n_near M1 / l1 + n_far M2 / l2 and
    M = I - u u^T the projector across each leg (u unit leg direction, l its length)."""
    p0, n, n1, n2 = _stack_params(iface)
    C = np.asarray(C, dtype=np.float64)
    X = np.asarray(X, dtype=np.float64)
    S = np.asarray(S, dtype=np.float64)
    v1 = S - C
    v2 = X - S
    l1 = np.sqrt(np.sum(v1 * v1, axis=-1))[..., None, None]
    l2 = np.sqrt(np.sum(v2 * v2, axis=-1))[..., None, None]
    u1 = v1 / l1[..., 0]
    u2 = v2 / l2[..., 0]
    eye = np.eye(3)
    M1 = eye - u1[..., :, None] * u1[..., None, :]
    M2 = eye - u2[..., :, None] * u2[..., None, :]
    n1 = np.asarray(n1)[..., None, None]
    n2 = np.asarray(n2)[..., None, None]
    B = n2 * M2 / l2
    H = n1 * M1 / l1 + B
    # Projector onto the plane P = I - n n^T: (E^T H E)^-1 E^T in plane terms is the pseudo-inverse of
    # P H P on the plane; adding n n^T makes it invertible without choosing a basis E.
    nn = n[..., :, None] * n[..., None, :]
    Pp = eye - nn
    A = Pp @ H @ Pp + nn
    return Pp @ np.linalg.solve(A, Pp @ B)


def refract(d: ArrayLike, iface: FlatInterface | tuple) -> F64:
    """Direction (..., 3), unit, of rays with direction d (..., 3) crossing from the near to the far
    medium (Snell's law in vector form). NaN for rays that do not head into the plane or are totally
    reflected (only possible from the denser medium)."""
    _, n, n1, n2 = _stack_params(iface)
    d = np.asarray(d, dtype=np.float64)
    i = d / np.sqrt(np.sum(d * d, axis=-1))[..., None]
    cosi = -np.sum(i * n, axis=-1)
    eta = np.asarray(n1 / n2)
    k = 1.0 - eta**2 * (1.0 - cosi**2)
    with np.errstate(invalid="ignore"):
        t = eta[..., None] * i + (eta * cosi - np.sqrt(k))[..., None] * n
    bad = ~((cosi > 0) & (k >= 0))
    return np.where(bad[..., None], np.nan, t)


def trace_rays(C: ArrayLike, d: ArrayLike, iface: FlatInterface | tuple) -> tuple[F64, F64]:
    """Rays from C (..., 3) with directions d (..., 3) in the near medium -> (their crossing points S
    on the plane, refracted unit directions). NaN for rays that never reach the plane."""
    p0, n, _, _ = _stack_params(iface)
    C = np.asarray(C, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    den = np.sum(d * n, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.sum((p0 - C) * n, axis=-1) / den
    ok = (den < 0) & (lam > 0)
    S = C + np.where(ok, lam, np.nan)[..., None] * d
    return S, refract(d, iface)


def triangulate_rays(origins: ArrayLike, dirs: ArrayLike, weights: ArrayLike | None = None) -> F64:
    """The point (..., 3) nearest, in summed squared (weighted) distance, to the lines origins[..., k, :]
    + s dirs[..., k, :] (k along the second-to-last axis). NaN if the lines are (nearly) parallel.
    Zero weights leave a line out (the batched birth search pads with them); so does a line with a
    non-finite origin or direction (a point with no preimage through the lens)."""
    o = np.asarray(origins, dtype=np.float64)
    t = np.asarray(dirs, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = t / np.sqrt(np.sum(t * t, axis=-1))[..., None]
    w = np.ones(t.shape[:-1]) if weights is None else np.asarray(weights, dtype=np.float64)
    w = np.where(np.isfinite(o).all(axis=-1) & np.isfinite(t).all(axis=-1), w, 0.0)
    o = np.where(w[..., None] > 0, o, 0.0)
    t = np.where(w[..., None] > 0, t, 0.0)
    M = np.eye(3) - t[..., :, None] * t[..., None, :]  # (..., k, 3, 3)
    M = M * w[..., None, None]
    A = M.sum(axis=-3)
    b = (M @ o[..., None])[..., 0].sum(axis=-2)
    cond = np.linalg.cond(A)
    with np.errstate(invalid="ignore"):
        X = np.linalg.solve(np.where((cond < 1e10)[..., None, None], A, np.eye(3)), b[..., None])[..., 0]
    return np.where((cond < 1e10)[..., None], X, np.nan)
