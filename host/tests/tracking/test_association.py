"""NNSF association: gates, nearest neighbour, one point per camera, clashes and merge prevention."""

from __future__ import annotations

import numpy as np

from flytrack_host.tracking.association import associate, ray_mahalanobis
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.synthetic import arena_cameras, point_array
from flytrack_host.tracking.tracker import Tracker
from flytrack_host.tracking.types import FrameBundle

CAMS = arena_cameras(4, seed=7)


def _run(targets: np.ndarray, offsets_px: dict[int, list[tuple[float, float]]], params: TrackingParams,
         area: float = 30.0, target_area: float = 30.0, std_m: float = 0.003):
    """Associate points placed at given pixel offsets from target 0's projection in each camera."""
    tr = Tracker(CAMS, params, 0.01)
    base = {ci: cam.project(targets[0])[0] for ci, cam in CAMS.items()}
    dets = {ci: point_array(CAMS[ci], np.array([base[ci] + o for o in offs]).reshape(-1, 2), area=area)
            for ci, offs in offsets_px.items()}
    pts = tr._gather(FrameBundle(0, 0.0, dets))
    uv, _, front = tr.cams.project_jacobian(targets)
    T = targets.shape[0]
    cov = np.broadcast_to(np.eye(3) * std_m**2, (T, 3, 3)).copy()
    res = associate(pts, tr.cams.n, uv, front, targets, cov, np.full(T, target_area), tr.cams.centers, params)
    return res, pts


def test_nearest_point_per_camera_and_gates() -> None:
    X = np.array([[0.7, 0.0, 0.15]])
    res, pts = _run(X, {0: [(8.0, 0.0), (2.0, 1.0)], 1: [(25.0, 0.0)], 2: [(0.5, 0.5)]}, TrackingParams())
    assert pts.index[res.assign[0, 0]] == 1  # the 2 px point, not the 8 px one
    assert res.assign[1, 0] == -1  # outside the 20 px image gate
    assert pts.index[res.assign[2, 0]] == 0
    assert res.assign[3, 0] == -1  # camera with no points
    assert np.all(np.diff(res.cost[[0, 2], 0]) < 0)  # the nearer ray has the smaller distance


def test_area_gate() -> None:
    X = np.array([[0.7, 0.0, 0.15]])
    res, _ = _run(X, {0: [(1.0, 0.0)]}, TrackingParams(), area=30.0 * 11, target_area=30.0)
    assert res.assign[0, 0] == -1
    res, _ = _run(X, {0: [(1.0, 0.0)]}, TrackingParams(), area=30.0 * 9, target_area=30.0)
    assert res.assign[0, 0] == 0


def test_mahalanobis_to_ray_matches_brute_force() -> None:
    rng = np.random.default_rng(3)
    A = rng.normal(size=(3, 3))
    cov = A @ A.T + 0.1 * np.eye(3)
    m = rng.normal(size=3)
    o = rng.normal(size=3) * 3
    d = rng.normal(size=3)
    s = np.linspace(-50, 50, 400001)
    pts = o + s[:, None] * d
    inv = np.linalg.inv(cov)
    brute = np.sqrt(np.min(np.einsum("ni,ij,nj->n", pts - m, inv, pts - m)))
    got = ray_mahalanobis(m[None], cov[None], o[None], d[None])[0, 0]
    np.testing.assert_allclose(got, brute, rtol=1e-6)


def test_clash_over_one_point_is_settled_globally() -> None:
    # Targets A, B about 7 px apart in camera 0. Point 0 lies between them (nearest for both), point 1
    # lies beyond A. Each target alone would take point 0; globally A takes point 1 and B point 0.
    X = np.array([[0.7, 0.0, 0.15], [0.7, 0.015, 0.15]])
    uv = CAMS[0].project(X)
    D = uv[1] - uv[0]
    res, pts = _run(X, {0: [tuple(0.45 * D), tuple(-0.6 * D)]}, TrackingParams())
    assert res.conflicts_resolved == 1
    got = {t: int(pts.index[res.assign[0, t]]) for t in range(2)}
    assert got == {0: 1, 1: 0}
    # flydra's independent choice: both take point 0, their point sets are identical, so the merge
    # rule leaves it to the target predicted closer to it (A, 0.45 D against 0.55 D).
    res, pts = _run(X, {0: [tuple(0.45 * D), tuple(-0.6 * D)]}, TrackingParams(exclusive_points=False))
    assert res.conflicts_resolved == 0 and res.merges_prevented == 1
    assert res.assign[0, 0] == 0 and res.assign[0, 1] == -1


def test_merge_prevention_keeps_only_the_closer_target() -> None:
    # flydra's way (no exclusive points): two targets see the very same single point in each camera.
    X = np.array([[0.7, 0.0, 0.15], [0.7, 0.003, 0.15]])
    params = TrackingParams(exclusive_points=False)
    offs = {ci: [(0.3, -0.2)] for ci in CAMS}
    res, _ = _run(X, offs, params)
    assert res.merges_prevented == 1
    assert (res.assign[:, 0] >= 0).all() and (res.assign[:, 1] == -1).all()
    # Without the clash (target 1 far away) nobody is stripped.
    X2 = np.array([[0.7, 0.0, 0.15], [0.2, 0.1, 0.05]])
    res, _ = _run(X2, offs, params)
    assert res.merges_prevented == 0 and (res.assign[:, 0] >= 0).all()
