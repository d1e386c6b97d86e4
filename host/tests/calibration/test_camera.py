"""The one camera model: projection, Jacobian, distortion round trip, decomposition, triangulation."""

from __future__ import annotations

import numpy as np
import pytest

from flytrack_host.geometry.camera import Camera, triangulate


def _cam(dist: tuple[float, ...] = (-0.2, 0.05, 1e-3, -2e-3, 0.01)) -> Camera:
    return Camera.look_at("c", (1.2, -0.7, 0.9), (0.0, 0.0, 0.1), 1024, 768, 900.0, dist=dist)


def _pts(n: int = 200) -> np.ndarray:
    return np.random.default_rng(3).uniform(-0.2, 0.2, size=(n, 3)) + np.array([0, 0, 0.1])


def test_project_matches_opencv() -> None:
    import cv2

    cam = _cam()
    X = _pts()
    rvec, _ = cv2.Rodrigues(cam.R)
    ref, _ = cv2.projectPoints(X, rvec, cam.t, cam.K, cam.dist)
    assert np.allclose(cam.project(X), ref.reshape(-1, 2), atol=1e-8)


def test_jacobian_matches_finite_differences() -> None:
    cam = _cam()
    X = _pts(5)[2]
    uv, J = cam.project_jacobian(X)
    assert np.allclose(uv, cam.project(X)[0])
    h = 1e-6
    Jn = np.stack([(cam.project(X + h * e)[0] - cam.project(X - h * e)[0]) / (2 * h) for e in np.eye(3)], axis=1)
    assert np.allclose(J, Jn, rtol=1e-5, atol=1e-4)


def test_undistort_inverts_distort() -> None:
    cam = _cam()
    uv = cam.project(_pts())
    back = cam.distort(cam.undistort(uv))
    assert np.max(np.abs(back - uv)) < 1e-6


def test_behind_camera_is_nan() -> None:
    cam = _cam()
    behind = cam.center + (cam.center - np.array([0.0, 0.0, 0.1]))
    assert np.all(np.isnan(cam.project(behind)))


@pytest.mark.parametrize("scale", [1.0, -2.5, 1e-3])
def test_from_P_recovers_K_R_t(scale: float) -> None:
    cam = _cam(dist=())
    cam.K[0, 1] = 0.7
    got = Camera.from_P("c", scale * cam.P, cam.width, cam.height)
    assert np.allclose(got.K, cam.K, atol=1e-9)
    assert np.allclose(got.R, cam.R, atol=1e-12)
    assert np.allclose(got.t, cam.t, atol=1e-12)
    assert np.isclose(np.linalg.det(got.R), 1.0)


def test_from_P_rejects_singular() -> None:
    with pytest.raises(ValueError, match="singular"):
        Camera.from_P("c", np.zeros((3, 4)), 10, 10)


def test_triangulate_exact() -> None:
    cams = [Camera.look_at(f"c{i}", p, (0, 0, 0), 640, 480, 500.0) for i, p in
            enumerate([(2, 0, 1), (0, 2, 1), (-2, 0, 1)])]
    X = np.array([0.05, -0.03, 0.1])
    got = triangulate(cams, [c.project_undistorted(X)[0] for c in cams])
    assert np.allclose(got, X, atol=1e-9)


def test_undistort_gives_nan_where_the_model_folds_over_not_a_wrong_point() -> None:
    import numpy as np

    from flytrack_host.geometry.camera import Camera

    # Barrel distortion: the model's image of the plane folds back beyond r ~ 1.3 (distorted radius
    # 0.86), so points far outside the image have no preimage; inside, undistort inverts distort.
    cam = Camera.look_at("c", [0, -1, 0], [0, 0, 0], 640, 480, 500, dist=[-0.2, 0.0, 0, 0, 0])
    inside = np.array([[10.0, 10.0], [320.0, 240.0], [630.0, 470.0]])
    back = cam.distort(cam.undistort(inside))
    assert np.allclose(back, inside, atol=1e-6)
    far = np.array([[320.0 + 5000.0, 240.0]])
    assert np.all(np.isnan(cam.undistort(far)))


def test_triangulating_parallel_rays_gives_nan() -> None:
    import numpy as np

    from flytrack_host.geometry.camera import Camera, triangulate

    a = Camera.look_at("a", [0, -1, 0], [0, 0, 0], 640, 480, 500)
    b = Camera.look_at("b", [0.01, -1, 0], [0.01, 0, 0], 640, 480, 500)  # same direction, side by side
    centre = np.array([319.5, 239.5])
    assert np.all(np.isnan(triangulate([a, b], [centre, centre])))
