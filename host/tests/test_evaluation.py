"""flytrack_host.tracking.evaluation: the one tracking scorer (simulated rig, tracking tests, tracker bench)."""

import numpy as np
import pytest

from flytrack_host.tracking.evaluation import FrameTracks, score_frames, score_tracks


def _gt(F=20):
    t = np.arange(F)[:, None]
    a = np.concatenate([t * 0.01, np.zeros((F, 1)), np.full((F, 1), 0.1)], axis=1)
    b = a + np.array([0.0, 0.2, 0.0])
    return np.stack([a, b], axis=1)  # (F, 2, 3), 20 cm apart


def test_perfect_tracks_with_known_offset():
    gt = _gt()
    off = np.array([0.001, 0.0, 0.0])  # 1 mm error on every estimate
    hyps = [FrameTracks(k, np.array([7, 8]), gt[k] + off) for k in range(20)]
    s = score_tracks(gt, hyps)
    assert s.rmse_mm == pytest.approx(1.0)
    assert s.mota == 1.0 and s.idf1 == 1.0
    assert s.id_switches == 0 and s.merges == 0 and s.misses == 0 and s.false_positives == 0
    assert s.duplicates == 0
    assert s.tracks_found == 2 and s.gt_objects == 2 and s.gt_detections == 40


def test_misses_false_positives_and_a_switch():
    gt = _gt()
    hyps = []
    for k in range(20):
        if k < 10:
            hyps.append(FrameTracks(k, np.array([1, 2]), gt[k]))
        elif k < 15:  # object 1 missed, a false positive far away
            hyps.append(FrameTracks(k, np.array([1, 9]), np.array([gt[k, 0], [5.0, 5.0, 5.0]])))
        else:  # ids swapped: two switches at frame 15
            hyps.append(FrameTracks(k, np.array([2, 1]), gt[k]))
    s = score_tracks(gt, hyps)
    assert s.misses == 5 and s.false_positives == 5
    assert s.id_switches == 2
    assert s.mota == pytest.approx(1 - (5 + 5 + 2) / 40)
    assert s.id_switches_free_flight == 2
    close = np.zeros((20, 2), bool)
    close[14, :] = True
    s2 = score_tracks(gt, hyps, close=close, close_window=3)
    assert s2.id_switches_free_flight == 0


def test_merge_is_one_track_standing_for_two_animals():
    F = 10
    a = np.tile([0.0, 0.0, 0.1], (F, 1))
    b = a + [0.005, 0.0, 0.0]  # 5 mm apart
    gt = np.stack([a, b], axis=1)
    hyps = [FrameTracks(k, np.array([1]), (a[k] + b[k]) / 2) for k in range(F)]
    s = score_tracks(gt, hyps, match_threshold_m=0.02)
    assert s.merges == 1 and s.merge_frames == F
    assert s.misses == F


def test_duplicate_is_a_second_track_on_an_animal_with_its_own():
    gt = _gt()
    hyps = [FrameTracks(k, np.array([1, 2]), gt[k]) for k in range(20)]
    for k in range(5, 8):  # a second track 1 mm from animal 0 for three frames
        hyps[k] = FrameTracks(k, np.array([1, 2, 3]), np.vstack([gt[k], gt[k, 0] + [0.001, 0, 0]]))
    s = score_tracks(gt, hyps)
    assert s.duplicates == 1 and s.duplicate_frames == 3 and s.false_positives == 3
    assert s.merges == 0 and s.misses == 0


def test_unscored_animals_are_dont_care():
    gt = _gt()
    scored = np.ones((20, 2), bool)
    scored[:, 1] = False  # e.g. seen by fewer than two cameras
    hyps = [FrameTracks(k, np.array([1, 2]), gt[k]) for k in range(20)]
    s = score_tracks(gt, hyps, scored=scored)
    assert s.false_positives == 0 and s.mota == 1.0 and s.gt_objects == 1


def test_frames_without_estimates_are_misses():
    gt = _gt()
    s = score_tracks(gt, [FrameTracks(0, np.array([1, 2]), gt[0])])
    assert s.misses == 38 and s.mota == pytest.approx(2 / 40)


def test_bad_shapes():
    with pytest.raises(ValueError):
        score_tracks(np.zeros((3, 2)), [])
    with pytest.raises(ValueError):
        score_tracks(np.zeros((3, 2, 3)), [], scored=np.ones((2, 2), bool))


def test_score_frames_takes_per_frame_dicts_with_animals_coming_and_going():
    gt = _gt()
    # Animal 0 throughout; animal 1 only in frames 5..14 (entered, then left the arena).
    truth = [{0: gt[k, 0], **({1: gt[k, 1]} if 5 <= k < 15 else {})} for k in range(20)]
    est = [{10: gt[k, 0] + [0.002, 0, 0], **({11: gt[k, 1]} if 6 <= k < 16 else {})} for k in range(20)]
    s = score_frames(truth, est)
    assert s.gt_detections == 30 and s.gt_objects == 2
    assert s.misses == 1 and s.false_positives == 1  # born a frame late; lingers a frame after it left
    assert s.mota == pytest.approx(1 - 2 / 30) and s.id_switches == 0 and s.merges == 0
    assert s.rmse_mm == pytest.approx(np.sqrt(20 * 4.0 / 29))  # 2 mm on animal 0, exact on animal 1
    with pytest.raises(ValueError, match="same frames"):
        score_frames(truth, est[:-1])


def test_score_frames_counts_a_merge_and_splits_switches_by_closeness():
    F = 30
    a = np.column_stack([np.linspace(0, 0.3, F), np.zeros(F), np.full(F, 0.1)])
    b = a + [0.0, 0.015, 0.0]  # 15 mm apart: a close encounter all along
    truth = [{0: a[k], 1: b[k]} for k in range(F)]
    # One track for both for frames 10..19 (the other track lost), then two tracks with swapped ids.
    est = [{1: a[k], 2: b[k]} if k < 10 else {1: (a[k] + b[k]) / 2} if k < 20 else {2: a[k], 1: b[k]}
           for k in range(F)]
    s = score_frames(truth, est, match_threshold_m=0.01, close_distance_m=0.02)
    assert s.merges == 1 and s.merge_frames == 10
    assert s.id_switches == 2 and s.id_switches_free_flight == 0  # both within the close encounter
    s = score_frames(truth, est, match_threshold_m=0.01, close_distance_m=0.01)  # 15 mm is not close now
    assert s.id_switches == 2 and s.id_switches_free_flight == 2
