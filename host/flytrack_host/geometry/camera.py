"""The one camera model of FlyTrack: pinhole + OpenCV-style lens distortion.

The tracker (observation model), the calibration (bundle adjustment), the simulator (rendering) and the
edge extractor's undistortion all use this model, so a point means the same thing everywhere.

Conventions: a world point Xw maps to camera coordinates Xc = R @ Xw + t; the camera looks along +z;
pixel (0, 0) is the centre of the top-left pixel, as in OpenCV.
Distortion coefficients are in OpenCV order (k1, k2, p1, p2, k3).
With `K_dist` set (flydra's `intrinsic_linear` / XML `non_linear_parameters` fc, cc, alpha_c) the lens
distortion is applied about that K instead of K: ideal pixel p = K (x/z, y/z) (so P = K [R|t] still holds),
q = K_dist^-1 p, distorted pixel = K_dist D(q). This is flydra's model exactly (its helper's undistort is
the inverse of it); with K_dist None it is OpenCV's, K_dist = K.
With `interface` set (a `refraction.FlatInterface`: Braid's `<water>`, a tank wall) points beyond the
plane are seen through it: they project as their refraction point on the plane does (refraction.py).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from flytrack_host.geometry.refraction import (
    FlatInterface,
    refraction_point,
    refraction_point_jacobian,
    trace_rays,
    triangulate_rays,
)

F64 = NDArray[np.float64]



def face_the_scene(cameras: list[Camera]) -> tuple[list[Camera], list[str]]:
    """Cameras of one rig turned to face where their optical axes meet. A projection matrix fixes a
    camera's side only up to the world's handedness: MultiCamSelfCal (flydra, Braid) often gives a
    mirrored world, in which every real point lies behind every camera by the usual rule (det R = +1),
    so `project` would return NaN for all of them. flydra and Braid never test the side. A camera whose
    axis-meeting point lies behind it gets R, t negated (an improper R): the same projection of every
    point, with the scene in front. Returns the cameras and the names of those turned."""
    if len(cameras) < 2:
        return cameras, []
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in cameras:
        d = c.R[2] / np.linalg.norm(c.R[2])  # the optical axis, in world coordinates
        proj = np.eye(3) - np.outer(d, d)
        A += proj
        b += proj @ c.center
    if np.linalg.cond(A) > 1e8:  # parallel axes meet nowhere: nothing to decide by
        return cameras, []
    X = np.linalg.solve(A, b)
    turned = [c.name for c in cameras if float((c.R @ X + c.t)[2]) < 0.0]
    if not turned:
        return cameras, []
    out = [dataclasses.replace(c, R=-c.R, t=-c.t) if c.name in turned else c for c in cameras]
    return out, turned


def mirrored_world_note(turned: list[str]) -> str:
    """What face_the_scene did, for the loaders' warnings."""
    return (f"camera(s) {', '.join(turned)}: the scene (where the optical axes meet) lies behind them by the "
            "usual rule: the calibration's world is mirrored (as MultiCamSelfCal can give); taken as facing it "
            "(the same projection of every point, as flydra and Braid use it)")

def _distort_normalized(x: F64, y: F64, d: F64) -> tuple[F64, F64]:
    k1, k2, p1, p2, k3 = d
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def distort_normalized(x: F64, y: F64, d: F64) -> tuple[F64, F64]:
    """OpenCV's distortion (k1 k2 p1 p2 k3) of normalised image coordinates (x, y) = (X/Z, Y/Z)."""
    return _distort_normalized(x, y, np.asarray(d, dtype=np.float64))


@dataclass
class Camera:
    name: str
    width: int
    height: int
    K: F64
    R: F64
    t: F64
    dist: F64 = field(default_factory=lambda: np.zeros(5))
    interface: FlatInterface | None = None
    K_dist: F64 | None = None

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        self.t = np.asarray(self.t, dtype=np.float64).reshape(3)
        d = np.zeros(5)
        given = np.asarray(self.dist, dtype=np.float64).ravel()
        if given.size > 5:
            raise ValueError(f"camera {self.name}: at most 5 distortion coefficients (k1 k2 p1 p2 k3)")
        d[: given.size] = given
        self.dist = d
        if self.K_dist is not None:
            Kd = np.asarray(self.K_dist, dtype=np.float64).reshape(3, 3)
            if not (np.all(np.isfinite(Kd)) and Kd[0, 0] > 0 and Kd[1, 1] > 0 and Kd[2, 2] == 1.0
                    and Kd[1, 0] == 0 and Kd[2, 0] == 0 and Kd[2, 1] == 0):
                raise ValueError(f"camera {self.name}: K_dist must be an upper-triangular intrinsic matrix "
                                 "with positive focal lengths and K_dist[2, 2] = 1")
            # The same K as the pinhole's (to rounding) is no separate distortion frame.
            self.K_dist = None if np.allclose(Kd, self.K, rtol=1e-13, atol=0) else Kd
        if not (np.all(np.isfinite(self.K)) and np.all(np.isfinite(self.R)) and np.all(np.isfinite(self.t))):
            raise ValueError(f"camera {self.name}: calibration contains NaN or infinity")
        if self.interface is not None and not float(self.interface.height(self.center)) > 0:
            raise ValueError(f"camera {self.name}: its centre must lie on the near (normal) side of its "
                             "refractive interface")

    # --- geometry -------------------------------------------------------------------------------
    @property
    def center(self) -> F64:
        """Camera centre in world coordinates."""
        return -self.R.T @ self.t

    @property
    def P(self) -> F64:
        """3x4 projection matrix for undistorted (ideal pinhole) pixel coordinates."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0.0))

    def to_camera(self, Xw: ArrayLike) -> F64:
        """Camera coordinates of the point each world point is seen at: itself, or its refraction
        point on the interface when it lies beyond it."""
        return self.seen_at(Xw) @ self.R.T + self.t

    def seen_at(self, Xw: ArrayLike) -> F64:
        """World points (N,3) -> the points (N,3) the camera's straight rays reach: the points
        themselves, or for points beyond the refractive interface their refraction points on it."""
        X = np.atleast_2d(np.asarray(Xw, dtype=np.float64))
        if self.interface is None:
            return X
        beyond = self.interface.beyond(X)
        if not beyond.any():
            return X
        S = refraction_point(self.center, X, self.interface)
        return np.where(beyond[:, None], S, X)

    @property
    def Kd(self) -> F64:
        """The K about which the distortion is applied (K_dist, or K)."""
        return self.K if self.K_dist is None else self.K_dist

    def _to_dist_frame(self, xn: F64, yn: F64) -> tuple[F64, F64]:
        """Pinhole normalised coordinates -> the coordinates the distortion acts on (K_dist^-1 K x)."""
        if self.K_dist is None:
            return xn, yn
        return self._normalize(self._pix(xn, yn), self.K_dist)

    def _pix(self, xn: F64, yn: F64, K: F64 | None = None) -> F64:
        K = self.K if K is None else K
        u = K[0, 0] * xn + K[0, 1] * yn + K[0, 2]
        v = K[1, 1] * yn + K[1, 2]
        return np.stack([u, v], axis=-1)

    def project(self, Xw: ArrayLike) -> F64:
        """World points (N,3) -> distorted pixel coordinates (N,2). Points behind the camera give NaN."""
        Xc = self.to_camera(Xw)
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = np.where(z > 0, Xc[:, 0] / z, np.nan)
            yn = np.where(z > 0, Xc[:, 1] / z, np.nan)
        xn, yn = self._to_dist_frame(xn, yn)
        xd, yd = _distort_normalized(xn, yn, self.dist)
        return self._pix(xd, yd, self.Kd)

    def project_undistorted(self, Xw: ArrayLike) -> F64:
        Xc = self.to_camera(Xw)
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = np.where(z > 0, Xc[:, 0] / z, np.nan)
            yn = np.where(z > 0, Xc[:, 1] / z, np.nan)
        return self._pix(xn, yn)

    def project_jacobian(self, Xw: ArrayLike) -> tuple[F64, F64]:
        """One world point (3,) -> (distorted pixel (2,), d pixel / d Xw (2,3)), analytically."""
        X = np.asarray(Xw, dtype=np.float64).reshape(3)
        dS = None
        if self.interface is not None and bool(self.interface.beyond(X)):
            S = refraction_point(self.center, X, self.interface)
            dS = refraction_point_jacobian(self.center, X, S, self.interface)
            X = S
        Xc = self.R @ X + self.t
        z = Xc[2]
        x0, y0 = Xc[0] / z, Xc[1] / z
        # The distortion acts on q = A (x0, y0) + b, A = (K_dist^-1 K)[:2, :2].
        A = np.linalg.solve(self.Kd, self.K)[:2, :2] if self.K_dist is not None else np.eye(2)
        x, y = self._to_dist_frame(np.array([x0]), np.array([y0]))
        x, y = float(x[0]), float(y[0])
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial_dr2 = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        # d(xd, yd) / d(x, y)
        dxd_dx = radial + x * dradial_dr2 * 2.0 * x + 2.0 * p1 * y + p2 * 6.0 * x
        dxd_dy = x * dradial_dr2 * 2.0 * y + 2.0 * p1 * x + p2 * 2.0 * y
        dyd_dx = y * dradial_dr2 * 2.0 * x + p1 * 2.0 * x + 2.0 * p2 * y
        dyd_dy = radial + y * dradial_dr2 * 2.0 * y + p1 * 6.0 * y + 2.0 * p2 * x
        Dd = np.array([[dxd_dx, dxd_dy], [dyd_dx, dyd_dy]])
        # d(x, y) / d Xc
        Dn = np.array([[1.0 / z, 0.0, -x0 / z], [0.0, 1.0 / z, -y0 / z]])
        Kd = self.Kd
        Kp = Kd[:2, :2]
        J = Kp @ Dd @ A @ Dn @ self.R
        if dS is not None:
            J = J @ dS
        uv = np.array([Kp[0, 0] * xd + Kp[0, 1] * yd + Kd[0, 2], Kp[1, 1] * yd + Kd[1, 2]])
        return uv, J

    def distort(self, uv_ideal: ArrayLike) -> F64:
        """Ideal (undistorted) pixel coordinates (N,2) -> distorted pixel coordinates (N,2)."""
        uv = np.atleast_2d(np.asarray(uv_ideal, dtype=np.float64))
        xn, yn = self._normalize(uv, self.Kd)
        xd, yd = _distort_normalized(xn, yn, self.dist)
        return self._pix(xd, yd, self.Kd)

    def undistort(self, uv: ArrayLike, iterations: int = 20) -> F64:
        """Distorted pixel coordinates (N,2) -> ideal pinhole pixel coordinates (N,2).

        Fixed-point iteration as in OpenCV's undistortPoints, then Newton steps to reach 1e-12 in the
        normalised plane (so undistort(distort(p)) == p to well under 1e-6 px). Where the iteration
        does not converge (far outside the field the distortion model was fitted on, where it folds
        over) the point is NaN rather than a wrong position."""
        uv = np.atleast_2d(np.asarray(uv, dtype=np.float64))
        Kd = self.Kd
        xd, yd = self._normalize(uv, Kd)
        if not self.has_distortion:
            return self._pix(xd, yd, Kd)
        k1, k2, p1, p2, k3 = self.dist
        x, y = xd.copy(), yd.copy()
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
            x = (xd - dx) / radial
            y = (yd - dy) / radial
        for _ in range(3):  # Newton polish
            fx, fy = _distort_normalized(x, y, self.dist)
            ex, ey = fx - xd, fy - yd
            h = 1e-7
            fxx, fyx = _distort_normalized(x + h, y, self.dist)
            fxy, fyy = _distort_normalized(x, y + h, self.dist)
            a, b = (fxx - fx) / h, (fxy - fx) / h
            c, d = (fyx - fy) / h, (fyy - fy) / h
            det = a * d - b * c
            with np.errstate(divide="ignore", invalid="ignore"):
                x = x - (d * ex - b * ey) / det
                y = y - (-c * ex + a * ey) / det
        fx, fy = _distort_normalized(x, y, self.dist)
        with np.errstate(invalid="ignore"):
            bad = ~(np.hypot(fx - xd, fy - yd) < 1e-6)  # ~1e-3 px at f = 1000 px; NaN counts as bad
        x[bad] = np.nan
        y[bad] = np.nan
        return self._pix(x, y, Kd)

    def _normalize(self, uv: F64, K: F64 | None = None) -> tuple[F64, F64]:
        K = self.K if K is None else K
        yn = (uv[:, 1] - K[1, 2]) / K[1, 1]
        xn = (uv[:, 0] - K[0, 2] - K[0, 1] * yn) / K[0, 0]
        return xn, yn

    def rays(self, uv: ArrayLike) -> tuple[F64, F64]:
        """Distorted pixels (N,2) -> (camera centre (3,), unit ray directions in world (N,3))."""
        uv_ideal = self.undistort(uv)
        xn, yn = self._normalize(uv_ideal)
        d_cam = np.stack([xn, yn, np.ones_like(xn)], axis=-1)
        d_world = d_cam @ self.R  # R.T @ d for each row
        d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
        return self.center, d_world

    def refracted_rays(self, uv: ArrayLike) -> tuple[F64, F64]:
        """Distorted pixels (N,2) -> (origins (N,3), unit directions (N,3)) of the lines on which the
        seen points lie: the camera's rays, or beyond the interface their refracted continuations."""
        c, d = self.rays(uv)
        return self._refract_rays(c, d)

    def ideal_rays(self, uv_ideal: ArrayLike) -> tuple[F64, F64]:
        """As refracted_rays, from undistorted pixels."""
        uv = np.atleast_2d(np.asarray(uv_ideal, dtype=np.float64))
        xn, yn = self._normalize(uv)
        d = np.stack([xn, yn, np.ones_like(xn)], axis=-1) @ self.R
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return self._refract_rays(self.center, d)

    def _refract_rays(self, c: F64, d: F64) -> tuple[F64, F64]:
        origins = np.broadcast_to(c, d.shape).copy()
        if self.interface is None:
            return origins, d
        S, t = trace_rays(c, d, self.interface)
        hit = np.isfinite(S).all(axis=1) & np.isfinite(t).all(axis=1)
        origins[hit], d = S[hit], np.where(hit[:, None], t, d)
        return origins, d

    def in_view(self, Xw: ArrayLike, margin: float = 0.0) -> NDArray[np.bool_]:
        """Which world points are in front of the camera and project inside the image."""
        Xc = self.to_camera(Xw)
        uv = self.project(Xw)
        with np.errstate(invalid="ignore"):
            return (
                (Xc[:, 2] > 0)
                & (uv[:, 0] >= -0.5 + margin)
                & (uv[:, 0] <= self.width - 0.5 - margin)
                & (uv[:, 1] >= -0.5 + margin)
                & (uv[:, 1] <= self.height - 0.5 - margin)
            )

    @classmethod
    def from_P(
        cls,
        name: str,
        P: ArrayLike,
        width: int,
        height: int,
        dist: ArrayLike = (0.0, 0.0, 0.0, 0.0, 0.0),
        interface: FlatInterface | None = None,
        K_dist: ArrayLike | None = None,
    ) -> Camera:
        """Decompose a 3x4 projection matrix (any scale and sign) into K, R, t (RQ decomposition).

        The result has K[2,2] == 1, positive focal lengths and a proper rotation (det R = +1), and
        projects every finite point exactly as P does (up to rounding)."""
        Pm = np.asarray(P, dtype=np.float64).reshape(3, 4)
        if not np.all(np.isfinite(Pm)):
            raise ValueError(f"camera {name}: projection matrix contains NaN or infinity")
        M = Pm[:, :3]
        det = np.linalg.det(M)
        if abs(det) < 1e-12 * max(1.0, float(np.abs(M).max()) ** 3):
            raise ValueError(f"camera {name}: projection matrix is singular (its left 3x3 block has rank < 3)")
        if det < 0:  # the overall sign of P is free; pick the one that gives det(R) = +1
            Pm = -Pm
            M = Pm[:, :3]
        # RQ via QR of the row-reversed transpose.
        flip = np.eye(3)[::-1]
        q, r = np.linalg.qr((flip @ M).T)
        K = flip @ r.T @ flip
        R = flip @ q.T
        # Make the diagonal of K positive; each sign change is applied to K's column and R's row.
        S = np.diag(np.sign(np.diag(K)))
        K = K @ S
        R = S @ R
        t = np.linalg.solve(K, Pm[:, 3])  # with the unscaled K, so the overall scale of P cancels
        K = K / K[2, 2]
        return cls(name=name, width=width, height=height, K=K, R=R, t=t, dist=np.asarray(dist, dtype=float),
                   interface=interface, K_dist=None if K_dist is None else np.asarray(K_dist, dtype=float))

    @classmethod
    def look_at(
        cls,
        name: str,
        position: ArrayLike,
        target: ArrayLike,
        width: int,
        height: int,
        focal_px: float,
        up: ArrayLike = (0.0, 0.0, 1.0),
        dist: ArrayLike = (0.0, 0.0, 0.0, 0.0, 0.0),
        interface: FlatInterface | None = None,
    ) -> Camera:
        """A camera at `position` looking at `target` (handy for synthetic rigs and tests)."""
        c = np.asarray(position, dtype=np.float64)
        z = np.asarray(target, dtype=np.float64) - c
        z /= np.linalg.norm(z)
        upv = np.asarray(up, dtype=np.float64)
        if abs(np.dot(upv, z)) > 0.99:
            upv = np.array([0.0, 1.0, 0.0])
        x = np.cross(z, upv)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        t = -R @ c
        K = np.array([[focal_px, 0.0, (width - 1) / 2.0], [0.0, focal_px, (height - 1) / 2.0], [0, 0, 1.0]])
        return cls(name=name, width=width, height=height, K=K, R=R, t=t, dist=np.asarray(dist, dtype=float),
                   interface=interface)


def triangulate(cameras: Sequence[Camera], uv_ideal: Sequence[ArrayLike]) -> F64:
    """Linear (DLT) triangulation of one point from undistorted pixels in two or more cameras.
    NaN when the rays are (nearly) parallel, i.e. the point is at infinity."""
    if len(cameras) < 2 or len(cameras) != len(uv_ideal):
        raise ValueError("triangulation needs the same number (>= 2) of cameras and points")
    if any(c.interface is not None for c in cameras):
        return triangulate_refractive(cameras, uv_ideal)
    rows = []
    for cam, p in zip(cameras, uv_ideal, strict=True):
        u, v = np.asarray(p, dtype=np.float64).reshape(2)
        P = cam.P
        rows.append(u * P[2] - P[0])
        rows.append(v * P[2] - P[1])
    A = np.asarray(rows)
    # Scale rows for conditioning; the solution is the right singular vector of least value.
    A /= np.linalg.norm(A, axis=1, keepdims=True)
    _, _, vt = np.linalg.svd(A)
    X = vt[-1]
    if not abs(X[3]) > 1e-12 * np.linalg.norm(X[:3]):
        return np.full(3, np.nan)  # rays (nearly) parallel: the point is at infinity
    return X[:3] / X[3]


def triangulate_refractive(cameras: Sequence[Camera], uv_ideal: Sequence[ArrayLike], iterations: int = 8) -> F64:
    """Triangulation through refractive interfaces: the (refracted) rays' least-squares point, weighted
    by 1 / distance^2 so it approximates the angular error, then Gauss-Newton on the undistorted-pixel
    reprojection error. Works for cameras without an interface too (their rays are straight)."""
    rays = [c.ideal_rays(p) for c, p in zip(cameras, uv_ideal, strict=True)]
    o = np.concatenate([r[0] for r in rays])
    d = np.concatenate([r[1] for r in rays])
    X = triangulate_rays(o, d)
    if not np.all(np.isfinite(X)):
        return np.full(3, np.nan)
    centers = np.stack([c.center for c in cameras])
    w = 1.0 / np.maximum(np.sum((X - centers) ** 2, axis=1), 1e-12)
    X = triangulate_rays(o, d, w)
    obs = np.concatenate([np.asarray(p, dtype=np.float64).reshape(1, 2) for p in uv_ideal])
    for _ in range(iterations):
        r = np.concatenate([c.project_undistorted(X) for c in cameras]) - obs
        if not np.all(np.isfinite(r)):
            break
        h = 1e-7 * max(1.0, float(np.abs(X).max()))
        J = np.stack([(np.concatenate([c.project_undistorted(X + h * e) for c in cameras]) - obs - r).ravel() / h
                      for e in np.eye(3)], axis=1)
        step = np.linalg.lstsq(J, -r.ravel(), rcond=None)[0]
        X = X + step
        if np.linalg.norm(step) < 1e-12 * max(1.0, float(np.linalg.norm(X))):
            break
    return X
