"""The stacked observation model agrees with the one Camera model, distortion included."""

from __future__ import annotations

import numpy as np

from flytrack_host.geometry.camera import Camera
from flytrack_host.tracking.observation import CameraArray
from flytrack_host.tracking.synthetic import arena_cameras


def _rig() -> dict[int, Camera]:
    cams = arena_cameras(5, seed=3)
    # A camera with skew and strong distortion too, under a non-contiguous index.
    c = cams[4]
    K = c.K.copy()
    K[0, 1] = 0.7
    cams[9] = Camera("skewed", c.width, c.height, K, c.R, c.t, dist=(-0.3, 0.1, 0.004, -0.003, 0.02))
    return cams


def test_project_jacobian_matches_camera_model() -> None:
    cams = _rig()
    arr = CameraArray(cams)
    rng = np.random.default_rng(0)
    X = rng.uniform([0.0, -0.15, 0.0], [1.5, 0.15, 0.3], size=(7, 3))
    uv, J, front = arr.project_jacobian(X)
    assert front.all()
    for s, ci in enumerate(arr.indices):
        np.testing.assert_allclose(uv[s], cams[ci].project(X), rtol=0, atol=1e-9)
        for t in range(X.shape[0]):
            uv1, J1 = cams[ci].project_jacobian(X[t])
            np.testing.assert_allclose(uv[s, t], uv1, atol=1e-9)
            np.testing.assert_allclose(J[s, t], J1, rtol=1e-10, atol=1e-9)


def test_jacobian_is_the_derivative() -> None:
    cams = _rig()
    arr = CameraArray(cams)
    X = np.array([[0.7, 0.05, 0.12]])
    _, J, _ = arr.project_jacobian(X)
    h = 1e-6
    for i in range(3):
        dX = np.zeros(3)
        dX[i] = h
        up, _, _ = arr.project_jacobian(X + dX)
        um, _, _ = arr.project_jacobian(X - dX)
        np.testing.assert_allclose((up - um)[:, 0] / (2 * h), J[:, 0, :, i], rtol=1e-5, atol=1e-3)


def test_behind_camera_is_flagged() -> None:
    cams = _rig()
    arr = CameraArray(cams)
    behind = 2 * cams[0].center - np.array([0.75, 0.0, 0.15])
    _, _, front = arr.project_jacobian(behind[None])
    assert not front[0, 0]


def test_rays_pass_through_the_point() -> None:
    cams = _rig()
    arr = CameraArray(cams)
    X = np.array([0.4, -0.1, 0.2])
    slots = np.arange(arr.n)
    ideal = np.stack([cams[ci].project_undistorted(X)[0] for ci in arr.indices])
    d = arr.ray_directions(slots, ideal[:, 0], ideal[:, 1])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    w = X - arr.centers
    along = np.einsum("ij,ij->i", w, d)
    np.testing.assert_allclose(np.linalg.norm(w - along[:, None] * d, axis=1), 0.0, atol=1e-9)
    assert (along > 0).all()
