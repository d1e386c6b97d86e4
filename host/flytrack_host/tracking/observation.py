"""The EKF observation model h(s): every camera's calibration, lens distortion included, stacked.

`Camera.project_jacobian` does one point in one camera; the tracker needs every (camera, target) pair
each frame, so `CameraArray` holds the same model as arrays and evaluates it for all pairs in a few
NumPy calls. Tests check it against `Camera.project_jacobian` and `Camera.project`.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from flytrack_host.camera import Camera

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
        K = np.stack([c.K for c in cams])
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

    def project_jacobian(self, X: F64) -> tuple[F64, F64, NDArray[np.bool_]]:
        """Targets X (T, 3) -> distorted pixels uv (C, T, 2), Jacobians J (C, T, 2, 3) and a mask
        (C, T) of pairs where the target is in front of the camera (elsewhere uv and J are junk)."""
        Xc = X @ self.RT + self.t[:, None, :]  # (C, T, 3)
        z = Xc[..., 2]
        front = z > 1e-9
        zi = 1.0 / np.where(front, z, 1.0)
        x = Xc[..., 0] * zi
        y = Xc[..., 1] * zi
        k1, k2, k3, p1, p2 = self.k1, self.k2, self.k3, self.p1, self.p2
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
        xy = x * y
        xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy
        # Jacobian of the distortion, d(xd, yd) / d(x, y).
        a = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
        b = 2.0 * xy * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        c = 2.0 * xy * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        d = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
        # M = Kp @ Dd with Kp = [[fx, skew], [0, fy]].
        m00 = self.fx * a + self.skew * c
        m01 = self.fx * b + self.skew * d
        m10 = self.fy * c
        m11 = self.fy * d
        # A = M @ d(x, y)/d(Xc) with d(x, y)/d(Xc) = [[1/z, 0, -x/z], [0, 1/z, -y/z]].
        A = np.empty(z.shape + (2, 3))
        A[..., 0, 0] = m00 * zi
        A[..., 0, 1] = m01 * zi
        A[..., 0, 2] = -(m00 * x + m01 * y) * zi
        A[..., 1, 0] = m10 * zi
        A[..., 1, 1] = m11 * zi
        A[..., 1, 2] = -(m10 * x + m11 * y) * zi
        J = A @ self.R[:, None, :, :]  # chain rule through Xc = R X + t
        uv = np.empty(z.shape + (2,))
        uv[..., 0] = self.fx * xd + self.skew * yd + self.cx
        uv[..., 1] = self.fy * yd + self.cy
        return uv, J, front

    def ray_directions(self, slots: NDArray[np.intp], u_ideal: F64, v_ideal: F64) -> F64:
        """World directions (N, 3), not normalised, of the rays through undistorted pixels
        (u_ideal, v_ideal) of the cameras in `slots`; each ray starts at `centers[slots]`."""
        fx, fy = self.fx[slots, 0], self.fy[slots, 0]
        yn = (v_ideal - self.cy[slots, 0]) / fy
        xn = (u_ideal - self.cx[slots, 0] - self.skew[slots, 0] * yn) / fx
        d_cam = np.stack([xn, yn, np.ones_like(xn)], axis=-1)
        return (self.RT[slots] @ d_cam[..., None])[..., 0]

    def project_ideal(self, slots: NDArray[np.intp], X: F64) -> tuple[F64, NDArray[np.bool_]]:
        """Undistorted pixels (N, 2) of points X (N, 3) in cameras `slots`, and an in-front mask."""
        h = (self.P[slots, :, :3] @ X[..., None])[..., 0] + self.P[slots, :, 3]
        w = h[:, 2]
        front = w > 1e-9
        w = np.where(front, w, 1.0)
        return h[:, :2] / w[:, None], front
