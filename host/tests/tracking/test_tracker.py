"""The tracker end to end on synthetic detections: accuracy, bad input, outages."""

from __future__ import annotations

import numpy as np
import pytest

from flytrack_host.protocol import POINT_DTYPE
from flytrack_host.tracking.evaluation import TrackingScores, score_frames
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.synthetic import Scenario, make_scenario
from flytrack_host.tracking.tracker import Tracker
from flytrack_host.tracking.types import FrameBundle, FrameResult

# Every end-to-end test runs on both paths: NumPy, and the C kernel (built by `make cbuild`; the
# c_kernel mark fails the test under make when it is missing, conftest.py).
KERNELS = pytest.mark.parametrize("kernel", ["numpy", pytest.param("c", marks=pytest.mark.c_kernel)])


def _track(sc: Scenario, params: TrackingParams | None = None,
           kernel: str = "auto") -> tuple[Tracker, list[FrameResult], TrackingScores]:
    params = (params or TrackingParams()).model_copy(update={"kernel": kernel})
    tr = Tracker(sc.cameras, params, sc.frame_period_s)
    assert kernel == "auto" or tr.kernel_path == kernel
    results = [tr.process(b) for b in sc.bundles]
    est = [{e.obj_id: e.state[:3] for e in r.estimates} for r in results]
    return tr, results, score_frames(sc.truth, est)


# Measured (C kernel, this code): RMSE 1.051 / 1.212 / 1.018 mm, MOTA 0.9955 / 0.9963 / 0.9961. The
# bounds sit about 20 % above: RMSE x 1.2, and the MOTA's error share (1 - MOTA) x 1.2. A 4x wrong R
# (measurement_noise_px 4) gives RMSE 2.17 / 1.98 / 1.68 mm and fails every case.
@pytest.mark.parametrize(("n_cameras", "n_targets", "seed", "rmse_mm", "mota"),
                         [(5, 4, 1, 1.051, 0.9955), (4, 3, 2, 1.212, 0.9963), (5, 3, 3, 1.018, 0.9961)])
@KERNELS
def test_accuracy_on_synthetic_flights(n_cameras: int, n_targets: int, seed: int, rmse_mm: float, mota: float,
                                       kernel: str) -> None:
    sc = make_scenario(n_cameras=n_cameras, n_targets=n_targets, duration_s=10.0, noise_px=0.5, p_miss=0.05,
                       false_positives_per_camera=0.3, close_pass_m=0.006, seed=seed)
    # The scenario really is hard where it should be: a close pass with merged blobs, false positives.
    assert sc.closest_approach_m <= 0.0061 and sc.n_merged_blobs > 0 and sc.n_false_positives > 500
    tr, _, s = _track(sc, kernel=kernel)
    print(f"\n{n_cameras} cameras, {n_targets} targets: {s.line()}\n  stats {tr.stats}")
    assert s.rmse_mm < 1.2 * rmse_mm
    assert 1.0 - s.mota < 1.2 * (1.0 - mota)
    assert s.duplicates == 0 and s.id_switches == 0
    assert s.idf1 > 0.9
    assert s.merges == 0 and s.duplicates == 0  # no track for two animals, no two tracks on one
    assert s.id_switches <= 1


@KERNELS
def test_nan_and_inf_points_are_skipped_and_counted(kernel: str) -> None:
    sc = make_scenario(n_cameras=5, n_targets=3, duration_s=4.0, corrupt_fraction=0.05, seed=4)
    assert sc.n_corrupted > 100
    tr, _, s = _track(sc, kernel=kernel)
    assert tr.stats["nonfinite_points"] == sc.n_corrupted
    assert tr.stats["points"] + tr.stats["nonfinite_points"] == sc.n_points
    print(f"\nwith {sc.n_corrupted} corrupted points: {s.line()}")
    # Measured RMSE 1.157 mm, MOTA 0.9916: bounds about 20 % above (RMSE, and the MOTA's error share).
    assert s.rmse_mm < 1.39 and 1.0 - s.mota < 1.2 * (1.0 - 0.9916)


@KERNELS
def test_infinite_orientation_is_counted_not_fatal(kernel: str) -> None:
    sc = make_scenario(n_cameras=4, n_targets=1, duration_s=0.5, close_pass_m=None, seed=6)
    sc.bundles[10].detections[0]["orientation"] = np.inf
    sc.bundles[11].detections[1]["eccentricity"] = -np.inf
    tr, _, s = _track(sc, kernel=kernel)
    assert tr.stats["nonfinite_orientation"] >= 2
    assert s.mota > 0.9


@KERNELS
def test_one_camera_out_for_a_while_then_back(kernel: str) -> None:
    sc = make_scenario(n_cameras=5, n_targets=2, duration_s=4.0, close_pass_m=None, p_miss=0.0,
                       false_positives_per_camera=0.0, camera_outages=((2, 100, 299),), seed=8)
    tr, results, s = _track(sc, kernel=kernel)
    ids_before = {e.obj_id for e in results[99].estimates}
    ids_after = {e.obj_id for e in results[350].estimates}
    assert ids_before == ids_after and len(ids_before) == 2
    assert all(e.n_cameras <= 4 for r in results[100:300] for e in r.estimates)
    assert all(a.camera_index != 2 for r in results[100:300] for a in r.associations)
    assert all(e.n_cameras == 5 for r in results[302:] for e in r.estimates)
    assert s.id_switches == 0 and s.rmse_mm < 1.34  # measured 1.120 mm


@KERNELS
def test_all_cameras_out_targets_coast_then_reacquire(kernel: str) -> None:
    outage = tuple((ci, 150, 154) for ci in range(4))
    sc = make_scenario(n_cameras=4, n_targets=2, duration_s=3.0, close_pass_m=None, p_miss=0.0,
                       false_positives_per_camera=0.0, camera_outages=outage, seed=9)
    tr, results, s = _track(sc, kernel=kernel)
    ids = {e.obj_id for e in results[149].estimates}
    assert len(ids) == 2
    for f in range(150, 155):  # coasting: reported from the prediction, no camera, growing covariance
        r = results[f]
        assert {e.obj_id for e in r.estimates} == ids and not r.associations
        assert all(e.n_cameras == 0 for e in r.estimates)
    std = lambda r: max(np.sqrt(e.covariance[0, 0]) for e in r.estimates)  # noqa: E731
    assert std(results[154]) > 2 * std(results[149])
    assert {e.obj_id for e in results[156].estimates} == ids  # reacquired, same identities
    assert all(e.n_cameras == 4 for e in results[156].estimates)
    assert s.id_switches == 0 and tr.stats["births"] == 2


@KERNELS
def test_long_silence_kills_targets_and_they_are_reborn(kernel: str) -> None:
    sc = make_scenario(n_cameras=4, n_targets=1, duration_s=1.0, close_pass_m=None, p_miss=0.0,
                       false_positives_per_camera=0.0, seed=10)
    tr = Tracker(sc.cameras, TrackingParams(kernel=kernel), sc.frame_period_s)
    for b in sc.bundles[:50]:
        tr.process(b)
    # 40 empty frames: the position std passes death_position_std_m.
    died = []
    for f in range(50, 90):
        died += tr.process(FrameBundle(f, f / 100, {})).died
    assert died == [0] and tr.n_targets == 0 and tr.stats["deaths"] == 1
    born = []
    for b in sc.bundles[90:]:
        born += tr.process(b).born
    assert born == [1]


@KERNELS
def test_skipped_trigger_frames_use_the_right_dt(kernel: str) -> None:
    sc = make_scenario(n_cameras=4, n_targets=2, duration_s=3.0, close_pass_m=None, seed=12)
    kept = [b for b in sc.bundles if b.trigger_frame % 3 != 1]  # a third of the frames never arrive
    sub = Scenario(sc.cameras, sc.frame_period_s, kept, [sc.truth[b.trigger_frame] for b in kept],
                   [sc.truth_axis[b.trigger_frame] for b in kept])
    tr, _, s = _track(sub, kernel=kernel)
    assert tr.stats["skipped_frames"] == len(sc.bundles) - len(kept) - (0 if sc.bundles[-1] in kept else 1)
    assert s.rmse_mm < 1.64 and s.id_switches == 0  # measured 1.365 mm


@KERNELS
def test_stale_and_repeated_bundles_are_ignored(kernel: str) -> None:
    sc = make_scenario(n_cameras=4, n_targets=1, duration_s=0.3, close_pass_m=None, seed=13)
    tr, _, _ = _track(sc, kernel=kernel)
    state = tr._x.copy()
    r = tr.process(sc.bundles[5])  # from the past
    assert tr.stats["stale_bundles"] == 1 and not r.associations and len(r.estimates) == 1
    np.testing.assert_array_equal(tr._x, state)


@KERNELS
def test_unknown_camera_and_bad_dtype(kernel: str) -> None:
    sc = make_scenario(n_cameras=4, n_targets=1, duration_s=0.2, close_pass_m=None, seed=14)
    tr = Tracker(sc.cameras, TrackingParams(kernel=kernel), sc.frame_period_s)
    b = sc.bundles[0]
    b.detections[77] = np.zeros(3, POINT_DTYPE)
    tr.process(b)
    assert tr.stats["unknown_camera_points"] == 3
    with pytest.raises(TypeError, match="structured array"):
        tr.process(FrameBundle(1, 0.01, {0: np.zeros((3, 2))}))
    with pytest.raises(TypeError, match="x_undist"):
        tr.process(FrameBundle(2, 0.02, {0: np.zeros(2, [("x_dist", "<f4")])}))


def test_constructor_checks() -> None:
    sc = make_scenario(n_cameras=2, n_targets=1, duration_s=0.1, close_pass_m=None, seed=15)
    for bad in (0.0, -0.01, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="frame_period_s"):
            Tracker(sc.cameras, TrackingParams(), bad)
    with pytest.raises(ValueError, match="camera"):
        Tracker({}, TrackingParams(), 0.01)


@KERNELS
def test_flydra_association_with_merge_prevention_does_not_merge(kernel: str) -> None:
    """flydra's independent per-target choice (exclusive_points = false): the merge-prevention rule
    fires during the close pass and the two trajectories stay apart."""
    sc = make_scenario(n_cameras=5, n_targets=4, duration_s=10.0, close_pass_m=0.006, seed=1)
    tr, _, s = _track(sc, TrackingParams(exclusive_points=False), kernel)
    print(f"\nflydra association: {s.line()}, merges prevented {tr.stats['merges_prevented']}")
    assert tr.stats["merges_prevented"] > 0
    assert s.merges == 0 and s.duplicates == 0 and s.id_switches <= 1 and s.rmse_mm < 1.41  # measured 1.175


@pytest.mark.c_kernel  # the C path only, for time; test_kernel.py holds the NumPy path to the same results
def test_support_rules_end_lingering_and_duplicate_tracks(kernel: str = "c") -> None:
    """11 cameras x 10 targets (the bench's hardest size, 400 frames from frame 600): targets leave
    mid-air while false positives keep arriving (9 leave in these frames). Measured with the support
    rules: no duplicate, 32 false positives (about 3.5 frames per exit). Without them (all three off):
    417 false positives, a track that lost its animal coasts on chance false positives, wanders onto
    another animal and stays as its duplicate (3 episodes, 248 frames)."""
    sc = make_scenario(n_cameras=11, n_targets=10, duration_s=10.0, close_pass_m=0.006, seed=1)
    exits = sum(1 for i in sc.truth[600] if i not in sc.truth[-1])
    assert exits == 9  # the scenario has what the rules are for
    _, results, s = _track(sc, kernel=kernel)
    est = [{e.obj_id: e.state[:3] for e in r.estimates} for r in results]
    late = score_frames(sc.truth[600:], est[600:])
    print(f"\nwith the rules: {late.line()}")
    assert late.duplicates == 0 and late.false_positives <= 38, late.line()
    off = TrackingParams(death_weak_frames=0, report_max_coast_frames=0, duplicate_distance_m=0.0)
    _, results, s_off = _track(sc, off, kernel=kernel)
    est = [{e.obj_id: e.state[:3] for e in r.estimates} for r in results]
    late_off = score_frames(sc.truth[600:], est[600:])
    print(f"without: {late_off.line()}")
    assert late_off.duplicates >= 1 and late_off.false_positives > 5 * late.false_positives, late_off.line()
    assert s.mota > s_off.mota + 0.03
