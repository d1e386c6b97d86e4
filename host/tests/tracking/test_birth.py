"""Births: batched triangulation agrees with camera.triangulate; seeds by Sampson distance; hypotheses
extended over the cameras; the per-frame budget defers, never loses, births."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from flytrack_host.geometry.camera import Camera, triangulate
from flytrack_host.geometry.refraction import FlatInterface
from flytrack_host.tracking.birth import find_births, sampson2, search_births, seed_pairs, triangulate_batch
from flytrack_host.tracking.kernel import unavailable_reason
from flytrack_host.tracking.observation import CameraArray
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.synthetic import arena_cameras, make_scenario, point_array
from flytrack_host.tracking.tracker import Tracker
from flytrack_host.tracking.types import FrameBundle
from flytrack_host.util.testing import missing_part


def test_triangulate_batch_matches_camera_triangulate() -> None:
    cams = arena_cameras(5, seed=2)
    arr = CameraArray(cams)
    rng = np.random.default_rng(1)
    X = rng.uniform([0.0, -0.15, 0.0], [1.5, 0.15, 0.3], size=(6, 3))
    for combo in ([0, 1], [1, 3, 4], [0, 1, 2, 3, 4]):
        uv = np.stack([[cams[c].project_undistorted(x)[0] + rng.normal(0, 0.5, 2) for c in combo] for x in X])
        got = triangulate_batch(arr.P[np.array(combo)][None].repeat(len(X), 0), uv)
        for i in range(len(X)):
            want = triangulate([cams[c] for c in combo], list(uv[i]))
            np.testing.assert_allclose(got[i], want, atol=1e-9)


def _frame(cams, X_list, fps_by_cam=None, skip=()) -> FrameBundle:
    dets = {}
    for ci, cam in cams.items():
        uv = [cam.project(x)[0] for k, x in enumerate(X_list) if (ci, k) not in skip]
        if fps_by_cam and ci in fps_by_cam:
            uv += list(fps_by_cam[ci])
        dets[ci] = point_array(cam, np.array(uv).reshape(-1, 2))
    return FrameBundle(trigger_frame=0, timestamp=0.0, detections=dets)


def test_two_targets_born_from_unclaimed_points_and_false_positives_refused() -> None:
    cams = arena_cameras(5, seed=4)
    X = [np.array([0.3, 0.05, 0.1]), np.array([1.1, -0.08, 0.22])]
    fp = {0: [(100.0, 100.0)], 2: [(500.0, 50.0), (20.0, 400.0)]}
    tr = Tracker(cams, TrackingParams(confirm_min_frames=1), 0.01)
    res = tr.process(_frame(cams, X, fp))
    assert sorted(res.born) == [0, 1]
    got = np.array(sorted([e.state[:3] for e in res.estimates], key=lambda s: s[0]))
    np.testing.assert_allclose(got, np.array(X), atol=1e-4)
    # Every camera's true point was used (absorbed beyond the 3-camera hypothesis), no false positive.
    assert all(e.n_cameras == 5 for e in res.estimates)
    used = {(a.camera_index, a.point_index) for a in res.associations}
    assert (0, 2) not in used and (2, 2) not in used and (2, 3) not in used


def test_hypothesis_with_most_cameras_wins_and_threshold_applies() -> None:
    cams = arena_cameras(4, seed=5)
    arr = CameraArray(cams)
    X = np.array([0.8, 0.0, 0.15])
    tr = Tracker(cams, TrackingParams(), 0.01)
    pts = tr._gather(_frame(cams, [X]))
    free = np.ones(pts.n, dtype=bool)
    b = find_births(arr, pts, free, TrackingParams(birth_max_combination=4))
    assert len(b) == 1 and b[0].n_hypothesis_cameras == 4
    # Shift one camera's point by 30 px: it can no longer join, and is not absorbed either.
    bundle = _frame(cams, [X])
    bundle.detections[2]["x_undist"] += 30.0
    pts = tr._gather(bundle)
    b = find_births(arr, pts, np.ones(pts.n, dtype=bool), TrackingParams(birth_max_combination=4))
    assert len(b) == 1 and b[0].n_hypothesis_cameras == 3 and 2 not in pts.slot[b[0].rows]


def test_min_separation_refuses_birth_next_to_existing_target() -> None:
    cams = arena_cameras(4, seed=5)
    arr = CameraArray(cams)
    X = np.array([0.8, 0.0, 0.15])
    tr = Tracker(cams, TrackingParams(), 0.01)
    pts = tr._gather(_frame(cams, [X]))
    free = np.ones(pts.n, dtype=bool)
    p = TrackingParams(birth_min_separation_m=0.02)
    assert find_births(arr, pts, free, p, existing=(X + [0.01, 0, 0])[None]) == []
    assert len(find_births(arr, pts, free, p, existing=(X + [0.05, 0, 0])[None])) == 1


def test_fundamental_matrices_and_sampson_distance() -> None:
    cams = arena_cameras(5, seed=2)
    arr = CameraArray(cams)
    rng = np.random.default_rng(3)
    X = rng.uniform([0.0, -0.15, 0.0], [1.5, 0.15, 0.3], size=(8, 3))
    for a, b in ((0, 1), (1, 3), (4, 2)):
        xa = np.c_[cams[a].project_undistorted(X), np.ones(len(X))]
        xb = np.c_[cams[b].project_undistorted(X), np.ones(len(X))]
        F = arr.fundamental[a, b]
        line = xa @ F.T  # epipolar lines in b
        dist = np.abs((xb * line).sum(axis=1)) / np.hypot(line[:, 0], line[:, 1])
        assert dist.max() < 1e-6
        np.testing.assert_allclose(arr.fundamental[b, a], F.T, rtol=1e-9, atol=1e-12 * np.abs(F).max())
    # Sampson distance of a pair: 0 for exact projections; a point moved by 4 px across its
    # epipolar line gives about 4 px / sqrt(2) (the best 3D point shares the error between the views).
    tr = Tracker(cams, TrackingParams(), 0.01)
    pts = tr._gather(_frame(cams, [X[0]]))
    rows = np.flatnonzero(pts.slot == 0)[0], np.flatnonzero(pts.slot == 1)[0]
    assert sampson2(arr, pts, np.array([rows[0]]), np.array([rows[1]]))[0] < 1e-6  # px^2; points are float32
    F = arr.fundamental[0, 1]
    line = F @ np.array([pts.u_ideal[rows[0]], pts.v_ideal[rows[0]], 1.0])
    normal = line[:2] / np.hypot(line[0], line[1])
    pts.u_ideal[rows[1]] += 4.0 * normal[0]
    pts.v_ideal[rows[1]] += 4.0 * normal[1]
    d = np.sqrt(sampson2(arr, pts, np.array([rows[0]]), np.array([rows[1]]))[0])
    assert 1.5 < d < 4.0


def _newcomers(n_cameras: int, n_targets: int, seed: int, fp: float = 0.3):
    sc = make_scenario(n_cameras=n_cameras, n_targets=n_targets, duration_s=0.1, fps=200.0, enter_exit=False,
                       close_pass_m=None, false_positives_per_camera=fp, p_miss=0.0, seed=seed)
    truth = np.array([sc.truth[0][k] for k in sorted(sc.truth[0])])
    return sc, truth


def test_ten_newcomers_in_eleven_cameras_are_born_in_one_frame() -> None:
    """The stress case of the simulated rig: every animal new at once, each seen by all cameras."""
    sc, truth = _newcomers(11, 10, seed=3)
    tr = Tracker(sc.cameras, TrackingParams(kernel="numpy"), sc.frame_period_s)
    pts = tr._gather(sc.bundles[0])
    s = search_births(tr.cams, pts, np.ones(pts.n, dtype=bool), TrackingParams())
    assert len(s.births) == 10 and 0 < s.evaluated <= TrackingParams().birth_max_hypotheses
    nearest = [int(np.argmin(np.linalg.norm(truth - b.position, axis=1))) for b in s.births]
    assert sorted(nearest) == list(range(10))  # one birth per animal
    for b, k in zip(s.births, nearest, strict=True):
        assert b.n_hypothesis_cameras == 3 and b.reproj_px <= 5.0
        assert np.linalg.norm(truth[k] - b.position) < 0.01  # 3 views at 0.5 px noise
        seen = {int(pts.slot[r]) for r in b.rows}
        assert len(seen) == len(b.rows) >= 8  # one point per camera, most cameras
        # Every point used is the animal's own (within a few px of its true projection).
        for r in b.rows:
            cam = sc.cameras[tr.cams.indices[pts.slot[r]]]
            assert np.hypot(*(cam.project(truth[k])[0] - pts.uv[r])) < 4.0
    # The whole tracker: all ten confirmed after confirm_min_frames frames, on both paths.
    for kernel in ("numpy", "c"):
        if kernel == "c" and (why := unavailable_reason()) is not None:
            missing_part(f"C tracker kernel not built (the NumPy path passed): {why}")
        tr = Tracker(sc.cameras, TrackingParams(kernel=kernel), sc.frame_period_s)
        born = [tr.process(b).born for b in sc.bundles[:4]]
        assert [len(x) for x in born] == [0, 0, 10, 0], kernel
        assert tr.stats["births"] == 10


def test_budget_defers_births_to_later_frames() -> None:
    sc, _ = _newcomers(5, 4, seed=5, fp=0.0)
    p = TrackingParams(birth_max_hypotheses=1, confirm_min_frames=1, kernel="numpy")
    tr = Tracker(sc.cameras, p, sc.frame_period_s)
    per_frame = []
    for b in sc.bundles[:6]:
        before = tr.stats["birth_hypotheses"]
        tr.process(b)
        per_frame.append(tr.stats["birth_hypotheses"] - before)
    assert max(per_frame) <= 1  # never more than the budget
    assert tr.stats["birth_frames_cut"] >= 1  # seeds were left for later frames
    assert tr.stats["births"] == 4 and tr.n_targets == 4  # one a frame, none lost
    est = tr._x[:, :3]
    assert all(np.linalg.norm(est - t, axis=1).min() < 0.003 for t in sc.truth[5].values())


def test_budget_must_be_positive() -> None:
    with pytest.raises(ValidationError):
        TrackingParams(birth_max_hypotheses=0)


def test_reprojection_threshold_refuses_a_pair_the_seed_gate_lets_through() -> None:
    """Two cameras, one camera's point moved 11 px in u and v: the pair still passes the seed gate
    (Sampson distance under 2.5 x the threshold) but its triangulated point reprojects 5.7 px off on
    average (measured), over birth_max_reproj_px (5): no birth. A looser threshold takes it."""
    cams = arena_cameras(2, seed=5)
    arr = CameraArray(cams)
    X = np.array([0.8, 0.0, 0.15])
    bundle = _frame(cams, [X])
    bundle.detections[1]["x_undist"] += 11.0
    bundle.detections[1]["y_undist"] += 11.0
    pts = Tracker(cams, TrackingParams(), 0.01)._gather(bundle)
    free = np.ones(pts.n, dtype=bool)
    loose = find_births(arr, pts, free, TrackingParams(birth_max_reproj_px=6.0))
    assert len(loose) == 1 and 5.0 < loose[0].reproj_px < 6.0, [b.reproj_px for b in loose]
    assert find_births(arr, pts, free, TrackingParams()) == []


# --- Tests that pin what the birth search promises (issue 17: `make mutation` showed they were missing) ---


def test_triangulate_batch_leaves_out_masked_cameras() -> None:
    """A mask (hypotheses padded to a common width) gives camera.triangulate over the kept cameras only,
    with noisy points (exact ones agree under any row weighting, so they would not show a wrong one)."""
    cams = arena_cameras(5, seed=2)
    arr = CameraArray(cams)
    rng = np.random.default_rng(4)
    X = rng.uniform([0.0, -0.15, 0.0], [1.5, 0.15, 0.3], size=(6, 3))
    uv = np.stack([[cams[c].project_undistorted(x)[0] + rng.normal(0, 1.0, 2) for c in range(5)] for x in X])
    mask = np.array([[1, 1, 0, 1, 0], [0, 1, 1, 1, 1], [1, 0, 0, 0, 1], [1, 1, 1, 1, 1], [0, 0, 1, 1, 0],
                     [1, 0, 1, 0, 1]], dtype=bool)
    got = triangulate_batch(arr.P[None].repeat(len(X), 0), uv, mask)
    for i in range(len(X)):
        keep = np.flatnonzero(mask[i])
        want = triangulate([cams[c] for c in keep], list(uv[i, keep]))
        np.testing.assert_allclose(got[i], want, atol=1e-9)
        assert np.linalg.norm(got[i] - X[i]) < 0.01


def _gold_pair_error(cam_a, cam_b, xa: np.ndarray, xb: np.ndarray) -> float:
    """The exact error of a pair: min over 3D points of sqrt(e_a^2 + e_b^2), undistorted px."""
    from scipy.optimize import least_squares

    def res(X: np.ndarray) -> np.ndarray:
        return np.r_[cam_a.project_undistorted(X)[0] - xa, cam_b.project_undistorted(X)[0] - xb]

    X0 = triangulate([cam_a, cam_b], [xa, xb])
    return float(np.linalg.norm(least_squares(res, X0, xtol=1e-14, ftol=1e-14, gtol=1e-14).fun))


def test_sampson_distance_is_the_pair_reprojection_error() -> None:
    """The seed gate's Sampson distance is the first-order reprojection error of the best 3D point for
    a pair: within 2 % of the exact one for points moved a few px in any direction in both images."""
    cams = arena_cameras(5, seed=2)
    arr = CameraArray(cams)
    rng = np.random.default_rng(8)
    tr = Tracker(cams, TrackingParams(), 0.01)
    for a, b in ((0, 1), (1, 3), (4, 2), (3, 0)):
        X = rng.uniform([0.0, -0.15, 0.0], [1.5, 0.15, 0.3])
        pts = tr._gather(_frame({a: cams[a], b: cams[b]}, [X]))
        ra, rb = np.flatnonzero(pts.slot == a)[0], np.flatnonzero(pts.slot == b)[0]
        pts.u_ideal[ra] += rng.uniform(-3, 3)  # a's point anywhere within 3 px
        pts.v_ideal[ra] += rng.uniform(-3, 3)
        line = arr.fundamental[a, b] @ np.array([pts.u_ideal[ra], pts.v_ideal[ra], 1.0])
        n = line[:2] / np.hypot(line[0], line[1])  # b's point 3 px off a's epipolar line, moved along it too
        pts.u_ideal[rb] += 3.0 * n[0] + rng.uniform(-3, 3) * n[1]
        pts.v_ideal[rb] += 3.0 * n[1] - rng.uniform(-3, 3) * n[0]
        xa = np.array([pts.u_ideal[ra], pts.v_ideal[ra]])
        xb = np.array([pts.u_ideal[rb], pts.v_ideal[rb]])
        gold = _gold_pair_error(cams[a], cams[b], xa, xb)
        got = np.sqrt(sampson2(arr, pts, np.array([ra]), np.array([rb]))[0])
        assert gold > 0.2 and abs(got - gold) < 0.02 * gold, (a, b, got, gold)


_WATER = FlatInterface.water_surface(1.333, z=0.3)


def test_births_through_water_use_the_refracted_rays() -> None:
    """Refractive cameras: seeds gated by the reprojection error of the refracted rays' midpoint (about
    0 px for the animals' own pairs, ranked first), births at the true positions from all 5 cameras'
    points, false positives left alone. Read as if there were no water, the births land centimetres off."""
    cams = arena_cameras(5, seed=4, interface=_WATER)
    arr = CameraArray(cams)
    assert arr.refractive
    X = [np.array([0.3, 0.05, 0.1]), np.array([1.1, -0.08, 0.22])]
    fp = {0: [(100.0, 100.0)], 2: [(500.0, 50.0), (20.0, 400.0)]}
    pts = Tracker(cams, TrackingParams(kernel="numpy"), 0.01)._gather(_frame(cams, X, fp))
    free = np.ones(pts.n, dtype=bool)
    owner = np.full(pts.n, -1)  # which animal each point is (-1: a false positive)
    for r in range(pts.n):
        cam = cams[int(arr.indices[pts.slot[r]])]
        for k, x in enumerate(X):
            if np.hypot(*(cam.project(x)[0] - pts.uv[r])) < 1e-3:
                owner[r] = k
    pairs, dist = seed_pairs(arr, pts, np.flatnonzero(free), 2.5 * 5.0)
    assert np.all(np.diff(dist) >= 0) and np.all(pts.slot[pairs[:, 0]] != pts.slot[pairs[:, 1]])
    own = (owner[pairs[:, 0]] >= 0) & (owner[pairs[:, 0]] == owner[pairs[:, 1]])
    assert own.sum() == 20  # 10 camera pairs per animal, all of them seeds
    assert dist[own].max() < 1e-3 and dist[~own].min() > 1.0
    s = search_births(arr, pts, free, TrackingParams())
    assert len(s.births) == 2 and s.evaluated == len(pairs) and s.deferred == 0
    for b in s.births:
        k = int(np.argmin([np.linalg.norm(b.position - x) for x in X]))
        assert np.linalg.norm(b.position - X[k]) < 1e-4
        assert b.n_hypothesis_cameras == 3 and b.reproj_px < 0.01
        assert sorted(pts.slot[b.rows].tolist()) == [0, 1, 2, 3, 4] and (owner[b.rows] == k).all()
    plain = {i: Camera(c.name, c.width, c.height, c.K, c.R, c.t, c.dist) for i, c in cams.items()}
    off = search_births(CameraArray(plain), pts, free, TrackingParams()).births
    assert all(min(np.linalg.norm(b.position - x) for x in X) > 0.02 for b in off)


def test_refractive_pair_refused_when_its_rays_meet_behind_a_camera() -> None:
    """Through water too, a pair whose rays cross behind one camera is no seed, however well it fits."""
    cams = arena_cameras(4, seed=5, interface=_WATER)
    arr = CameraArray(cams)
    X = np.array([0.8, 0.0, 0.15])
    pts = Tracker(cams, TrackingParams(kernel="numpy"), 0.01)._gather(_frame(cams, [X]))
    rows = np.flatnonzero(np.ones(pts.n, dtype=bool))
    pairs, _ = seed_pairs(arr, pts, rows, 12.5)
    assert len(pairs) == 6
    # Turn camera 1's ray around (same line, other way): every pair with camera 1 now meets behind it.
    pts.rays[pts.slot == 1] *= -1.0
    pairs, _ = seed_pairs(arr, pts, rows, 12.5)
    assert len(pairs) == 3 and not (pts.slot[pairs] == 1).any()


def test_a_ghost_pair_meeting_behind_a_camera_costs_no_hypothesis() -> None:
    """Camera 2 has a false positive exactly where a point behind camera 0, on camera 0's ray through
    the animal, would appear: the pair fits the epipolar geometry (Sampson distance ~0) but the rays
    meet behind camera 0. It is no seed, so it spends none of the frame's hypothesis budget."""
    cams = arena_cameras(4, seed=5)
    arr = CameraArray(cams)
    X = np.array([0.8, 0.0, 0.15])
    Y = cams[0].center + 0.3 * (cams[0].center - X)
    ghost = cams[2].project(Y)[0]
    assert 0 < ghost[0] < 640 and 0 < ghost[1] < 480
    dets = {0: point_array(cams[0], cams[0].project(X)), 2: point_array(cams[2], ghost[None])}
    pts = Tracker(cams, TrackingParams(), 0.01)._gather(FrameBundle(0, 0.0, dets))
    assert sampson2(arr, pts, np.array([0]), np.array([1]))[0] < 1e-3
    s = search_births(arr, pts, np.ones(pts.n, dtype=bool), TrackingParams())
    assert s.evaluated == 0 and s.births == []
    # With camera 2's true point as well, the animal is born from the real pair only.
    dets[2] = point_array(cams[2], np.vstack([ghost, cams[2].project(X)[0]]))
    pts = Tracker(cams, TrackingParams(), 0.01)._gather(FrameBundle(0, 0.0, dets))
    s = search_births(arr, pts, np.ones(pts.n, dtype=bool), TrackingParams())
    assert s.evaluated == 1 and len(s.births) == 1 and np.linalg.norm(s.births[0].position - X) < 1e-4
    # The other way round: camera 0's false positive where a point behind camera 1 would appear.
    X = np.array([1.2, -0.1, 0.25])
    ghost = cams[0].project(cams[1].center + 0.3 * (cams[1].center - X))[0]
    assert 0 < ghost[0] < 640 and 0 < ghost[1] < 480
    dets = {0: point_array(cams[0], ghost[None]), 1: point_array(cams[1], cams[1].project(X))}
    pts = Tracker(cams, TrackingParams(), 0.01)._gather(FrameBundle(0, 0.0, dets))
    assert sampson2(arr, pts, np.array([0]), np.array([1]))[0] < 1e-3
    s = search_births(arr, pts, np.ones(pts.n, dtype=bool), TrackingParams())
    assert s.evaluated == 0 and s.births == []


def test_seed_gate_spares_the_budget_for_pairs_that_cannot_pass() -> None:
    """A pair whose Sampson distance exceeds 2.5 x birth_max_reproj_px cannot reach a mean error under
    the threshold: it is no seed (not evaluated). At 2 x the threshold it is evaluated (and refused)."""
    cams = arena_cameras(2, seed=5)
    arr = CameraArray(cams)
    X = np.array([0.8, 0.0, 0.15])
    tr = Tracker(cams, TrackingParams(), 0.01)
    for off_px, evaluated in ((10.0, 1), (15.0, 0)):
        pts = tr._gather(_frame(cams, [X]))
        line = arr.fundamental[0, 1] @ np.array([pts.u_ideal[0], pts.v_ideal[0], 1.0])
        n = line[:2] / np.hypot(line[0], line[1])
        # Camera 1's point moved across the epipolar line until the pair's Sampson distance is off_px.
        d0 = np.sqrt(sampson2(arr, pts, np.array([0]), np.array([1]))[0])
        step = 0.0
        for _ in range(40):  # the distance grows linearly with the move: a few secant steps
            pts.u_ideal[1] += n[0] * (off_px - d0)
            pts.v_ideal[1] += n[1] * (off_px - d0)
            step += off_px - d0
            d0 = np.sqrt(sampson2(arr, pts, np.array([0]), np.array([1]))[0])
            if abs(d0 - off_px) < 1e-3:
                break
        assert abs(d0 - off_px) < 1e-3
        s = search_births(arr, pts, np.ones(pts.n, dtype=bool), TrackingParams())
        assert s.evaluated == evaluated and s.births == [], (off_px, s)


def test_a_stray_point_beyond_the_extension_gate_does_not_spoil_the_hypothesis() -> None:
    """Five cameras, the fifth's point 22 px (over 4 x the threshold) off: it joins no hypothesis, so the
    four good cameras make it (an outlier joining would fail the fit and leave only the seed pair)."""
    cams = arena_cameras(5, seed=5)
    arr = CameraArray(cams)
    X = np.array([0.8, 0.0, 0.15])
    bundle = _frame(cams, [X])
    bundle.detections[4] = point_array(cams[4], cams[4].project(X) + 22.0 / np.sqrt(2))
    pts = Tracker(cams, TrackingParams(), 0.01)._gather(bundle)
    b = find_births(arr, pts, np.ones(pts.n, dtype=bool), TrackingParams(birth_max_combination=5))
    assert len(b) == 1 and b[0].n_hypothesis_cameras == 4 and sorted(pts.slot[b[0].rows]) == [0, 1, 2, 3]
    assert np.linalg.norm(b[0].position - X) < 1e-4


def test_combination_size_two_triangulates_pairs_and_absorbs_the_rest() -> None:
    sc, truth = _newcomers(5, 4, seed=5, fp=0.0)
    tr = Tracker(sc.cameras, TrackingParams(kernel="numpy"), sc.frame_period_s)
    pts = tr._gather(sc.bundles[0])
    s = search_births(tr.cams, pts, np.ones(pts.n, dtype=bool), TrackingParams(birth_max_combination=2))
    assert len(s.births) == 4
    assert all(b.n_hypothesis_cameras == 2 and len(b.rows) == 5 for b in s.births)
    assert all(np.linalg.norm(truth - b.position, axis=1).min() < 0.01 for b in s.births)


def test_budget_counts_what_was_evaluated_and_what_is_left() -> None:
    """With a budget of one hypothesis, the seeds deferred are exactly those still possible (all their
    points free after the birth), not those that lost a point to it."""
    sc, _ = _newcomers(5, 4, seed=5, fp=0.0)
    tr = Tracker(sc.cameras, TrackingParams(kernel="numpy"), sc.frame_period_s)
    pts = tr._gather(sc.bundles[0])
    free = np.ones(pts.n, dtype=bool)
    s = search_births(tr.cams, pts, free, TrackingParams(birth_max_hypotheses=1))
    assert s.evaluated == 1 and len(s.births) == 1
    left = free.copy()
    left[s.births[0].rows] = False
    still, _ = seed_pairs(tr.cams, pts, np.flatnonzero(left), 2.5 * TrackingParams().birth_max_reproj_px)
    assert s.deferred == len(still) > 0


def test_seeds_beyond_the_first_batch_are_evaluated_on_the_points_left() -> None:
    """Eleven cameras, two exactly seen animals (110 seed pairs at ~0 px, ranked first) and a third seen
    with 1.5 px errors, whose seeds rank behind them all: it is born from the seeds evaluated once the
    first two used their points, and the hypotheses evaluated are counted over all of them."""
    cams = arena_cameras(11, seed=3)
    X = [np.array([0.3, 0.05, 0.1]), np.array([1.1, -0.08, 0.22]), np.array([0.7, 0.1, 0.15])]
    bundle = _frame(cams, X)
    rng = np.random.default_rng(2)
    for ci in cams:
        d = bundle.detections[ci]
        ang = rng.uniform(0, 2 * np.pi)
        d["x_undist"][2] += 1.5 * np.cos(ang)
        d["y_undist"][2] += 1.5 * np.sin(ang)
    pts = Tracker(cams, TrackingParams(kernel="numpy"), 0.01)._gather(bundle)
    arr = CameraArray(cams)
    s = search_births(arr, pts, np.ones(pts.n, dtype=bool), TrackingParams(birth_max_hypotheses=70))
    assert len(s.births) == 3 and s.evaluated == 70
    assert all(b.n_hypothesis_cameras == 3 for b in s.births)
    for x in X:
        assert min(np.linalg.norm(b.position - x) for b in s.births) < 0.01  # 3 views, 1.5 px: 5.5 mm


def test_an_outlier_that_spoils_the_extended_fit_falls_back_to_the_seed_pair() -> None:
    """Three cameras, the third's point 18 px off (within the extension gate): the three-camera fit
    fails the threshold, so the exact seed pair alone is born, without the outlier point."""
    cams = arena_cameras(3, seed=5)
    arr = CameraArray(cams)
    X = np.array([0.8, 0.0, 0.15])
    bundle = _frame(cams, [X])
    bundle.detections[2] = point_array(cams[2], cams[2].project(X) + 18.0 / np.sqrt(2))
    pts = Tracker(cams, TrackingParams(), 0.01)._gather(bundle)
    b = find_births(arr, pts, np.ones(pts.n, dtype=bool), TrackingParams())
    assert len(b) == 1 and b[0].n_hypothesis_cameras == 2 and sorted(pts.slot[b[0].rows]) == [0, 1]
    assert np.linalg.norm(b[0].position - X) < 1e-4 and b[0].reproj_px < 0.01


def test_a_real_animal_seen_by_more_cameras_beats_a_chance_pair_with_a_smaller_error() -> None:
    """Camera 1 has a false positive exactly where camera 0's ray through the animal passes a point
    nearer camera 0: that chance pair fits to ~0 px, better than any pair of the animal (1 px noise).
    Ranked by the further cameras that see it, the animal wins; the chance pair is not born."""
    cams = arena_cameras(5, seed=5)
    arr = CameraArray(cams)
    X = np.array([0.8, 0.0, 0.15])
    Z = X + 0.25 * (cams[0].center - X)
    rng = np.random.default_rng(1)
    dets = {}
    for ci, cam in cams.items():
        uv = [cam.project(X)[0] + (rng.normal(0, 1.0, 2) if ci else 0.0)]
        if ci == 1:
            uv.append(cam.project(Z)[0])
        dets[ci] = point_array(cam, np.array(uv))
    pts = Tracker(cams, TrackingParams(), 0.01)._gather(FrameBundle(0, 0.0, dets))
    for comb in (2, 3):
        b = find_births(arr, pts, np.ones(pts.n, dtype=bool), TrackingParams(birth_max_combination=comb))
        assert len(b) == 1 and np.linalg.norm(b[0].position - X) < 0.02  # Z is 30 cm away
        assert sorted(pts.slot[b[0].rows]) == [0, 1, 2, 3, 4] and (pts.index[b[0].rows] == 0).all()
