"""Births: batched triangulation agrees with camera.triangulate; hypotheses over camera combinations."""

from __future__ import annotations

import numpy as np

from flytrack_host.camera import triangulate
from flytrack_host.tracking.birth import find_births, triangulate_batch
from flytrack_host.tracking.observation import CameraArray
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.synthetic import arena_cameras, point_array
from flytrack_host.tracking.tracker import Tracker
from flytrack_host.tracking.types import FrameBundle


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
