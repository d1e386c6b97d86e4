"""The EKF observation model h(s): every camera's calibration, lens distortion included, stacked.

`Camera.project_jacobian` does one point in one camera; the tracker needs every (camera, target) pair
each frame, so `CameraArray` holds the same model as arrays and evaluates it for all pairs in a few
NumPy calls. Tests check it against `Camera.project_jacobian` and `Camera.project`.

Cameras with a refractive interface (`Camera.interface`, e.g. Braid's `<water>`) see a point through
its refraction point S on the plane (refraction.py): uv = pinhole(S(X)), J = J_pinhole(S) dS/dX, the
"ideal" pixel is the undistorted pinhole projection of S, and a point's ray is a line that starts on
the plane (`ray_lines`). The fundamental matrices do not hold for those cameras (`refractive`).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from flytrack_host.geometry.camera import Camera
from flytrack_host.geometry.refraction import refraction_point, refraction_point_jacobian, trace_rays

F64 = NDArray[np.float64]


class CameraArray:
    """The rig's cameras as stacked arrays, in slot order (slot = position in `indices`)."""

    def __init__(self, cameras: Mapping[int, Camera]) -> None:
        if not cameras:
            raise ValueError("the tracker needs at least one camera")
        self.indices: tuple[int, ...] = tuple(sorted(cameras))
        self.cameras: tuple[Camera, ...] = tuple(cameras[i] for i in self.indices)
        self.slot_of: dict[int, int] = {ci: s for s, ci in enumerate(self.indices)}
        cams = self.cameras
        self.n = len(cams)
        self.R = np.stack([c.R for c in cams])  # (C, 3, 3)
        self.t = np.stack([c.t for c in cams])  # (C, 3)
        self.RT = np.ascontiguousarray(np.swapaxes(self.R, 1, 2))
        # The distortion's K (Camera.Kd: flydra's intrinsic_linear when it differs from P's K): output
        # pixels use it; the distortion acts on q = A q0 + b with (A, b) from K_dist^-1 K.
        K = np.stack([c.Kd for c in cams])
        self.dist_frame = any(c.K_dist is not None for c in cams)
        Adf = np.stack([np.linalg.solve(c.Kd, c.K) for c in cams])
        self._dfA = Adf[:, None, :2, :2]  # (C, 1, 2, 2)
        self._dfAT = np.ascontiguousarray(np.swapaxes(self._dfA, -1, -2))
        self._dfb = Adf[:, None, :2, 2]  # (C, 1, 2)
        # (C, 1) columns broadcast against (C, T) target arrays.
        self.fx = K[:, 0, 0, None].copy()
        self.skew = K[:, 0, 1, None].copy()
        self.cx = K[:, 0, 2, None].copy()
        self.fy = K[:, 1, 1, None].copy()
        self.cy = K[:, 1, 2, None].copy()
        D = np.stack([c.dist for c in cams])
        self.k1, self.k2, self.p1, self.p2, self.k3 = (D[:, i, None].copy() for i in range(5))
        self.centers = np.stack([c.center for c in cams])  # (C, 3)
        self.P = np.stack([c.P for c in cams])  # (C, 3, 4) ideal-pixel projection matrices
        self.width = np.array([c.width for c in cams], dtype=np.float64)
        self.height = np.array([c.height for c in cams], dtype=np.float64)
        # Per-camera constants of project_jacobian, shaped to broadcast against (C, T, ...) arrays, so
        # that a frame spends its NumPy calls on the targets and not on rebuilding these.
        C = self.n
        self._t3 = self.t[:, None, :]  # (C, 1, 3)
        self._R2 = self.R[:, None, :2, :]  # (C, 1, 2, 3) first two rows of R
        self._Rz = self.R[:, None, 2:3, :]  # (C, 1, 1, 3) third row of R
        Kp = np.zeros((C, 1, 2, 2))  # [[fx, skew], [0, fy]]
        Kp[:, 0, 0, 0], Kp[:, 0, 0, 1], Kp[:, 0, 1, 1] = self.fx[:, 0], self.skew[:, 0], self.fy[:, 0]
        self._Kp = Kp
        self._KpT = np.ascontiguousarray(np.swapaxes(Kp, -1, -2))
        self._cxy = np.stack([self.cx, self.cy], axis=-1)  # (C, 1, 2)
        self._k2x2, self._k3x3 = 2.0 * self.k2, 3.0 * self.k3
        pv = np.stack([self.p1, self.p2], axis=-1)  # (C, 1, 2): (p1, p2)
        ps = pv[..., ::-1]  # (p2, p1)
        self._p2v = 2.0 * pv
        self._ps = np.ascontiguousarray(ps)
        self._p2v_col = (2.0 * pv)[..., None]  # (C, 1, 2, 1)
        self._p2s_col = (2.0 * ps)[..., None]
        self._p4s = 4.0 * ps
        # Rays: world direction of undistorted pixel (u, v) is B @ (u, v, 1) with B = R^T K^-1.
        self._ray_B = np.stack([c.R.T @ np.linalg.inv(c.K) for c in cams])  # (C, 3, 3)
        # Fundamental matrices on undistorted pixels, F[a, b] (C, C, 3, 3) with x_b' F[a, b] x_a = 0:
        # the rays B_a x_a, B_b x_b and the baseline c_a - c_b are coplanar, so
        # F[a, b] = B_b' [c_a - c_b]_x B_a (zero for a == b).
        t = self.centers[:, None, :] - self.centers[None, :, :]  # (a, b, 3)
        tx = np.zeros((C, C, 3, 3))
        tx[..., 0, 1], tx[..., 0, 2], tx[..., 1, 2] = -t[..., 2], t[..., 1], -t[..., 0]
        tx[..., 1, 0], tx[..., 2, 0], tx[..., 2, 1] = t[..., 2], -t[..., 1], t[..., 0]
        self.fundamental = np.swapaxes(self._ray_B, 1, 2)[None, :] @ tx @ self._ray_B[:, None]
        # Refraction, per camera (cameras without an interface get a dummy plane and are masked out).
        ifc = [c.interface for c in cams]
        self.refractive = any(i is not None for i in ifc)
        self.has_interface = np.array([i is not None for i in ifc])
        self._ifc_p = np.array([i.point if i is not None else (0.0, 0.0, 0.0) for i in ifc])  # (C, 3)
        self._ifc_n = np.array([i.normal if i is not None else (0.0, 0.0, 1.0) for i in ifc])
        self._ifc_n1 = np.array([i.n_near if i is not None else 1.0 for i in ifc])
        self._ifc_n2 = np.array([i.n_far if i is not None else 1.0 for i in ifc])

    def _iface(self, sl: slice | NDArray[np.intp], extra: int) -> tuple[F64, F64, F64, F64]:
        """Interface parameters of cameras `sl`, with `extra` broadcast axes inserted after the camera."""
        ix = (sl,) + (None,) * extra
        return self._ifc_p[ix], self._ifc_n[ix], self._ifc_n1[ix], self._ifc_n2[ix]

    def seen_at(self, X: F64, jacobian: bool = True) -> tuple[F64, F64 | None]:
        """Targets X (T, 3) -> the points (C, T, 3) each camera's straight rays reach (X, or its
        refraction point beyond an interface) and, with jacobian, dS/dX (C, T, 3, 3)."""
        C, T = self.n, X.shape[0]
        Xs = np.broadcast_to(X, (C, T, 3)).copy()
        dS = np.broadcast_to(np.eye(3), (C, T, 3, 3)).copy() if jacobian else None
        if not self.refractive:
            return Xs, dS
        k = np.flatnonzero(self.has_interface)
        p0, n, n1, n2 = self._iface(k, 1)
        beyond = np.einsum("ctk,ctk->ct", X[None] - p0, np.broadcast_to(n, (k.size, T, 3))) < 0
        Cc = self.centers[k, None, :]
        S = refraction_point(Cc, X[None], (p0, n, n1, n2))
        Xs[k] = np.where(beyond[..., None], S, X[None])
        if dS is not None:
            J = refraction_point_jacobian(Cc, X[None], np.where(beyond[..., None], S, X[None] - n), (p0, n, n1, n2))
            dS[k] = np.where(beyond[..., None, None], J, np.eye(3))
        return Xs, dS

    def _seen_at_rows(self, slots: NDArray[np.intp], X: F64) -> F64:
        """Points X (N, 3) as seen by cameras slots (N,): X or its refraction point."""
        if not self.refractive:
            return X
        p0, n, n1, n2 = self._ifc_p[slots], self._ifc_n[slots], self._ifc_n1[slots], self._ifc_n2[slots]
        beyond = self.has_interface[slots] & (np.einsum("nk,nk->n", X - p0, n) < 0)
        if not beyond.any():
            return X
        S = refraction_point(self.centers[slots], X, (p0, n, n1, n2))
        return np.where(beyond[:, None], S, X)

    def project_jacobian(self, X: F64) -> tuple[F64, F64, NDArray[np.bool_]]:
        """Targets X (T, 3) -> distorted pixels uv (C, T, 2), Jacobians J (C, T, 2, 3) and a mask
        (C, T) of pairs where the target is in front of the camera (elsewhere uv and J are junk)."""
        # Written on (x, y) pairs rather than scalars: the per-frame cost is the count of NumPy calls.
        dS = None
        if self.refractive:
            X, dS = self.seen_at(X)  # (C, T, 3) points on the interfaces, (C, T, 3, 3)
        Xc = X @ self.RT + self._t3  # (C, T, 3)
        z = Xc[..., 2]
        front = z > 1e-9
        zi = 1.0 / np.where(front, z, 1.0)
        q = Xc[..., :2] * zi[..., None]  # normalised (x, y), (C, T, 2)
        q0 = q
        if self.dist_frame:
            q = (q[..., None, :] @ self._dfAT)[..., 0, :] + self._dfb
        qq = q * q
        r2 = qq[..., 0] + qq[..., 1]
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        dradial = self.k1 + r2 * (self._k2x2 + self._k3x3 * r2)  # d radial / d r2
        xy = (q[..., 0] * q[..., 1])[..., None]
        qs = q[..., ::-1]  # (y, x)
        # Tangential part: (2 p1 x y + p2 (r2 + 2 x^2), 2 p2 x y + p1 (r2 + 2 y^2)).
        qd = q * radial[..., None] + self._p2v * xy + self._ps * (r2[..., None] + 2.0 * qq)
        uv = (qd[..., None, :] @ self._KpT)[..., 0, :] + self._cxy
        # Distortion Jacobian d(xd, yd)/d(x, y) = radial I + 2 radial' q q^T + 2 p qs^T + 2 ps q^T
        # + 4 diag(ps * q), with p = (p1, p2), ps = (p2, p1), qs = (y, x).
        Dd = (2.0 * dradial)[..., None, None] * (q[..., :, None] * q[..., None, :])
        Dd += self._p2v_col * qs[..., None, :]
        Dd += self._p2s_col * q[..., None, :]
        Dd.reshape(Dd.shape[:-2] + (4,))[..., ::3] += radial[..., None] + self._p4s * q
        # Chain rule: d(x, y)/dX = (R[:2] - q R[2]) / z, pixels = Kp (xd, yd) + c.
        G = self._R2 - q0[..., :, None] * self._Rz  # (C, T, 2, 3)
        if self.dist_frame:
            G = self._dfA @ G
        J = (self._Kp @ Dd) @ G
        J *= zi[..., None, None]
        if dS is not None:
            J = J @ dS
            front &= np.isfinite(uv).all(axis=-1) & np.isfinite(J).all(axis=(-2, -1))
            uv = np.where(front[..., None], uv, 0.0)
        return uv, J, front

    def ray_lines(self, slots: NDArray[np.intp], u_ideal: F64, v_ideal: F64) -> tuple[F64, F64]:
        """Origins (N, 3) and directions (N, 3) of the lines on which the points seen at undistorted
        pixels (u_ideal, v_ideal) of cameras `slots` lie: camera centre and ray_directions, or beyond a
        refractive interface the refraction point and the refracted (unit) direction."""
        d = self.ray_directions(slots, u_ideal, v_ideal)
        o = self.centers[slots]
        if not self.refractive:
            return o, d
        p0, n, n1, n2 = self._ifc_p[slots], self._ifc_n[slots], self._ifc_n1[slots], self._ifc_n2[slots]
        S, t = trace_rays(o, d, (p0, n, n1, n2))
        hit = self.has_interface[slots] & np.isfinite(S).all(axis=1) & np.isfinite(t).all(axis=1)
        return np.where(hit[:, None], S, o), np.where(hit[:, None], t, d)

    def ray_directions(self, slots: NDArray[np.intp], u_ideal: F64, v_ideal: F64) -> F64:
        """World directions (N, 3), not normalised, of the rays through undistorted pixels
        (u_ideal, v_ideal) of the cameras in `slots`; each ray starts at `centers[slots]`.
        The direction is R^T K^-1 (u, v, 1): the camera-frame ray with unit depth."""
        B = self._ray_B[slots]  # (N, 3, 3)
        return B[:, :, 0] * u_ideal[:, None] + B[:, :, 1] * v_ideal[:, None] + B[:, :, 2]

    def project_ideal(self, slots: NDArray[np.intp], X: F64) -> tuple[F64, NDArray[np.bool_]]:
        """Undistorted pixels (N, 2) of points X (N, 3) in cameras `slots`, and an in-front mask."""
        if self.refractive:
            X = self._seen_at_rows(slots, X)
        h = (self.P[slots, :, :3] @ X[..., None])[..., 0] + self.P[slots, :, 3]
        w = h[:, 2]
        front = w > 1e-9
        w = np.where(front, w, 1.0)
        uv = h[:, :2] / w[:, None]
        if self.refractive:
            front &= np.isfinite(uv).all(axis=1)
        return uv, front

    def project_ideal_all(self, X: F64) -> tuple[F64, NDArray[np.bool_]]:
        """Undistorted pixels (M, C, 2) of points X (M, 3) in every camera, and an in-front mask (M, C)."""
        Xs, _ = self.seen_at(X, jacobian=False)  # (C, M, 3)
        h = (Xs @ np.swapaxes(self.P[:, :, :3], 1, 2)) + self.P[:, None, :, 3]
        w = h[..., 2]
        front = w > 1e-9
        with np.errstate(invalid="ignore"):
            front &= np.isfinite(h).all(axis=-1)
        uv = h[..., :2] / np.where(front, w, 1.0)[..., None]
        return np.swapaxes(uv, 0, 1), front.T
