"""NNSF association: gates, nearest neighbour, one point per camera, clashes and merge prevention."""

from __future__ import annotations

import numpy as np

from flytrack_host.tracking.association import associate, inv3, ray_mahalanobis
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


# --- What association promises beyond the cases above (issue 17: `make mutation` found these untested) ---


def _associate(targets: np.ndarray, pix: dict[int, list[tuple[float, float]]], params: TrackingParams,
               cov: np.ndarray | None = None, area: float | list[float] = 30.0, target_area: float = 30.0,
               cams=CAMS, front: np.ndarray | None = None):  # noqa: ANN001
    """Associate points given in absolute distorted pixels per camera (area: one value or one per point)."""
    tr = Tracker(cams, params, 0.01)
    dets = {}
    for ci, uvs in pix.items():
        arr = point_array(cams[ci], np.array(uvs, dtype=float).reshape(-1, 2))
        arr["area"] = area
        dets[ci] = arr
    pts = tr._gather(FrameBundle(0, 0.0, dets))
    uv, _, fr = tr.cams.project_jacobian(targets)
    T = targets.shape[0]
    if cov is None:
        cov = np.broadcast_to(np.eye(3) * 0.003**2, (T, 3, 3)).copy()
    res = associate(pts, tr.cams.n, uv, fr if front is None else front, targets, cov, np.full(T, target_area),
                    tr.cams.centers, params)
    return res, pts


def _proj(X: np.ndarray, cams=CAMS) -> dict[int, np.ndarray]:  # noqa: ANN001
    return {ci: cam.project(X)[0] for ci, cam in cams.items()}


def test_inv3_inverts_stacks_of_any_shape() -> None:
    rng = np.random.default_rng(5)
    for shape in ((7,), (2, 4)):
        A = rng.normal(size=shape + (3, 3)) + 2.0 * np.eye(3)
        np.testing.assert_allclose(inv3(A), np.linalg.inv(A), rtol=1e-9, atol=1e-12)
    sing = np.diag([1.0, 1.0, 0.0])[None]
    assert not np.isfinite(inv3(sing)).all()


def test_a_singular_covariance_refuses_its_target_and_leaves_the_others_as_they_were() -> None:
    """np.linalg.inv refuses the whole stack when one covariance is singular; the fallback must still
    give every other target its points and distances, and the singular one none."""
    X = np.array([[0.7, 0.0, 0.15], [0.3, 0.1, 0.05]])
    pa, pb = _proj(X[0]), _proj(X[1])
    pix = {ci: [tuple(pa[ci] + (1.5, -1.0)), tuple(pb[ci] + (0.5, 0.8))] for ci in CAMS}
    cov = np.stack([np.diag([2.0, 1.0, 3.0]) * 1e-5, np.diag([1e-5, 1e-5, 0.0])])
    res, _ = _associate(X, pix, TrackingParams(), cov=cov)
    alone, _ = _associate(X[:1], pix, TrackingParams(), cov=cov[:1])
    assert (res.assign[:, 1] == -1).all() and np.isinf(res.cost[:, 1]).all()
    np.testing.assert_array_equal(res.assign[:, 0], alone.assign[:, 0])
    assert (alone.assign[:, 0] >= 0).all()
    np.testing.assert_allclose(res.cost[:, 0], alone.cost[:, 0], rtol=1e-9)


def _ray_distance_brute(m: np.ndarray, cov: np.ndarray, o: np.ndarray, d: np.ndarray) -> float:
    from scipy.optimize import minimize_scalar

    A = np.linalg.inv(cov)
    f = lambda s: float((o + s * d - m) @ A @ (o + s * d - m))  # noqa: E731
    s0 = float(np.dot(m - o, d) / np.dot(d, d))
    return float(np.sqrt(minimize_scalar(f, bracket=(s0 - 1.0, s0 + 1.0), tol=1e-12).fun))


def test_cost_is_the_mahalanobis_distance_from_the_prediction_to_the_chosen_ray() -> None:
    """res.cost is the distance the NNSF minimises, under the target's covariance, also below 1."""
    X = np.array([[0.7, 0.0, 0.15]])
    cov = np.array([[[4.0, 1.0, 0.5], [1.0, 2.0, 0.3], [0.5, 0.3, 3.0]]]) * 1e-6
    p = _proj(X[0])
    res, pts = _associate(X, {0: [tuple(p[0] + (0.2, 0.1))], 1: [tuple(p[1] + (3.0, -2.0))],
                              2: [tuple(p[2] + (6.0, 4.0))]}, TrackingParams(), cov=cov)
    costs = []
    for c in range(3):
        r = res.assign[c, 0]
        assert r >= 0
        o = CAMS[c].center
        want = _ray_distance_brute(X[0], cov[0], o, pts.rays[r])
        np.testing.assert_allclose(res.cost[c, 0], want, rtol=1e-6)
        costs.append(want)
    assert costs[0] < 1.0 < costs[2]
    assert res.assign[3, 0] == -1 and np.isinf(res.cost[3, 0])


def test_mahalanobis_and_front_gates() -> None:
    X = np.array([[0.7, 0.0, 0.15]])
    p = _proj(X[0])
    pix = {ci: [tuple(p[ci] + (3.0, 0.0))] for ci in CAMS}
    loose, _ = _associate(X, pix, TrackingParams())
    assert (loose.assign[:, 0] >= 0).all()
    # A covariance of 0.1 mm puts the 3 px rays dozens of sigmas away: refused by max_mahalanobis.
    tight, _ = _associate(X, pix, TrackingParams(), cov=np.eye(3)[None] * 1e-8)
    assert (tight.assign[:, 0] == -1).all()
    assert (tight.conflicts_resolved, tight.merges_prevented) == (0, 0)
    # A target behind camera 2 (front False) gets nothing from it, whatever its projection.
    front = np.ones((len(CAMS), 1), dtype=bool)
    front[2, 0] = False
    res, _ = _associate(X, pix, TrackingParams(), front=front)
    assert res.assign[2, 0] == -1 and (np.delete(res.assign[:, 0], 2) >= 0).all()


def test_min_area_gate_needs_an_area_above_it() -> None:
    """min_area_px (seed 000 eq. 3.11): a point must have an area above it, also a fractional one."""
    X = np.array([[0.7, 0.0, 0.15]])
    p = _proj(X[0])
    pix = {0: [tuple(p[0] + (1.0, 0.0)), tuple(p[0] + (1.5, 0.0))]}
    res, pts = _associate(X, pix, TrackingParams(min_area_px=3.0), area=[3.0, 3.5], target_area=3.2)
    assert pts.index[res.assign[0, 0]] == 1  # area 3.0 is not above 3.0: the farther one is used
    res, _ = _associate(X, {0: pix[0][:1]}, TrackingParams(min_area_px=0.8), area=0.5, target_area=0.5)
    assert res.assign[0, 0] == -1
    res, _ = _associate(X, {0: pix[0][:1]}, TrackingParams(min_area_px=0.4), area=0.5, target_area=0.5)
    assert res.assign[0, 0] == 0
    # The area test adds to the other gates, never replaces them: a point 40 px away stays out.
    res, _ = _associate(X, {0: [tuple(p[0] + (40.0, 0.0))]}, TrackingParams(min_area_px=0.4), area=0.5,
                        target_area=0.5, cov=np.eye(3)[None] * 0.05**2)
    assert res.assign[0, 0] == -1


def test_image_and_area_gates_alone() -> None:
    """With a loose (5 cm) covariance only the image gate (20 px) and the area ratio (10x either way)
    decide: 18 px is in, 25 px out; an area 0.15 of the target's is in, 0.09 out."""
    X = np.array([[0.7, 0.0, 0.15]])
    p = _proj(X[0])
    cov = np.eye(3)[None] * 0.05**2
    res, _ = _associate(X, {0: [tuple(p[0] + (18.0, 0.0))], 1: [tuple(p[1] + (0.0, 25.0))]}, TrackingParams(),
                        cov=cov)
    assert res.assign[0, 0] >= 0 and res.assign[1, 0] == -1
    for area, used in ((4.5, True), (2.7, False)):
        res, _ = _associate(X, {0: [tuple(p[0] + (1.0, 0.0))]}, TrackingParams(), cov=cov, area=area)
        assert (res.assign[0, 0] >= 0) == used, area


def test_clashes_are_counted_per_camera_and_a_loser_without_a_point_goes_without() -> None:
    """Camera 0: one point between A and B, nearer B: B takes it, A gets none there (cost inf).
    Camera 1: a point far from both, then one between them nearer A: A takes the second. Camera 2: A
    and B each have their own point, no clash: untouched, not counted."""
    X = np.array([[0.7, 0.0, 0.15], [0.7, 0.015, 0.15]])
    pa, pb = _proj(X[0]), _proj(X[1])
    pix = {0: [tuple(pa[0] + 0.6 * (pb[0] - pa[0]))],
           1: [(20.0, 20.0), tuple(pa[1] + 0.4 * (pb[1] - pa[1]))],
           2: [tuple(pa[2] + (0.5, 0.0)), tuple(pb[2] + (0.5, 0.0))]}
    res, pts = _associate(X, pix, TrackingParams())
    assert res.conflicts_resolved == 2
    assert res.assign[0, 1] == 0 and res.assign[0, 0] == -1 and np.isinf(res.cost[0, 0])
    assert np.isfinite(res.cost[0, 1])
    assert res.assign[1, 1] == -1 and pts.slot[res.assign[1, 0]] == 1 and pts.index[res.assign[1, 0]] == 1
    assert [int(pts.index[res.assign[2, t]]) for t in (0, 1)] == [0, 1]
    assert (res.assign[3:] == -1).all()


def test_merge_prevention_keeps_the_nearest_whatever_its_order_and_counts_every_stripped_target() -> None:
    params = TrackingParams(exclusive_points=False)
    # One shared point, camera 0 only (PointSet row 0), nearer to the second target.
    X = np.array([[0.7, 0.0, 0.15], [0.7, 0.004, 0.15]])
    pa, pb = _proj(X[0]), _proj(X[1])
    res, _ = _associate(X, {0: [tuple(pa[0] + 0.7 * (pb[0] - pa[0]))]}, params)
    assert res.merges_prevented == 1
    assert res.assign[0, 1] == 0 and res.assign[0, 0] == -1 and np.isinf(res.cost[0, 0])
    # A lone target first, then three sharing the same point in every camera: two are stripped, the
    # nearest (the middle one) keeps them.
    X = np.array([[0.2, 0.1, 0.05], [0.7, -0.003, 0.15], [0.7, 0.0, 0.15], [0.7, 0.004, 0.15]])
    lone, mid = _proj(X[0]), _proj(X[2])
    pix = {ci: [tuple(lone[ci] + (0.3, 0.2)), tuple(mid[ci] + (0.2, -0.1))] for ci in CAMS}
    res, _ = _associate(X, pix, params)
    assert res.merges_prevented == 2
    assert (res.assign[:, 0] >= 0).all() and (res.assign[:, 2] >= 0).all()
    assert (res.assign[:, [1, 3]] == -1).all()


def test_no_candidate_or_no_point_counts_nothing() -> None:
    X = np.array([[0.7, 0.0, 0.15], [0.7, 0.015, 0.15]])
    for params in (TrackingParams(), TrackingParams(exclusive_points=False)):
        res, _ = _associate(X, {}, params)
        assert (res.conflicts_resolved, res.merges_prevented) == (0, 0) and (res.assign == -1).all()
        assert res.cost.shape == (len(CAMS), 2) and np.isinf(res.cost).all()
        res, _ = _associate(X, {0: [(5.0, 5.0)]}, params)  # far from both: gated out
        assert (res.conflicts_resolved, res.merges_prevented) == (0, 0) and (res.assign == -1).all()


def test_rays_start_on_the_water_surface_for_refractive_cameras() -> None:
    """Under water the camera ray bends at the surface: the distance is taken to the refracted line
    (PointSet.origins), so exact points of the target are at ~0, not off by the refraction."""
    from flytrack_host.geometry.refraction import FlatInterface
    from flytrack_host.tracking.synthetic import arena_cameras

    cams = arena_cameras(4, seed=7, interface=FlatInterface.water_surface(1.333, z=0.3))
    X = np.array([[0.7, 0.0, 0.15]])
    p = _proj(X[0], cams)
    res, _ = _associate(X, {ci: [tuple(p[ci])] for ci in cams}, TrackingParams(), cams=cams)
    assert (res.assign[:, 0] >= 0).all() and res.cost[:, 0].max() < 0.05
