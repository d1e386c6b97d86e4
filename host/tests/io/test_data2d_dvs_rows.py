"""Re-tracking from a recording gives the tracker the event cameras' points (FLAG_DVS rows) with the
covariance the live run weighed them by (the dvs_point_covariance table, SPEC 1.6), and leaves them
out, saying how many, when a recording has no covariance for them: as plain frame points they could
start targets."""

from __future__ import annotations

import numpy as np
import pytest

from flytrack_host.io.data2d import dvs_rows_left_out, iter_bundles, n_frames
from flytrack_host.recording.rows import dvs_covariance_rows
from flytrack_host.recording.schema import DATA2D, FLAG_DVS


def _rows() -> np.ndarray:
    rows = np.zeros(6, DATA2D)
    rows["trigger_frame"] = [0, 0, 1, 1, 1, 2]
    rows["camera_index"] = [0, 5, 0, 5, 5, 5]
    rows["frame_pt_idx"] = [0, 0, 0, 0, 1, 0]
    rows["x_dist"], rows["y_dist"] = 10.0, 20.0
    rows["x_dist"][4] = 30.0
    rows["flags"] = [0, FLAG_DVS, 0, FLAG_DVS, FLAG_DVS, FLAG_DVS]
    return rows


def test_dvs_rows_without_covariance_are_left_out_and_counted() -> None:
    rows = _rows()
    bundles = list(iter_bundles(rows, 100.0))
    assert [b.trigger_frame for b in bundles] == [0, 1]  # frame 2 had event-camera rows only
    assert all(set(b.detections) == {0} and not b.point_cov for b in bundles)
    assert n_frames(rows) == 2
    assert dvs_rows_left_out(rows, None) == 4
    rows["flags"] = 0
    assert [sorted(b.detections) for b in iter_bundles(rows, 100.0)] == [[0, 5], [0, 5], [5]]


def test_dvs_rows_join_with_their_recorded_covariance() -> None:
    rows = _rows()
    cov = np.concatenate([dvs_covariance_rows(5, 0, np.array([[1.0, 2.0, 0.5]])),
                          dvs_covariance_rows(5, 1, np.array([[3.0, 4.0, -1.0], [5.0, 6.0, 0.0]]))])
    bundles = list(iter_bundles(rows, 100.0, dvs_cov=cov))
    assert [b.trigger_frame for b in bundles] == [0, 1]  # frame 2's point has no covariance
    assert n_frames(rows, cov) == 2 and dvs_rows_left_out(rows, cov) == 1
    b0, b1 = bundles
    assert sorted(b0.detections) == [0, 5] and sorted(b0.point_cov) == [5]
    assert b0.point_cov[5].tolist() == [[1.0, 2.0, 0.5]]
    # each point keeps its own covariance, matched by frame_pt_idx
    assert b1.detections[5]["x_dist"].tolist() == [10.0, 30.0]
    assert b1.point_cov[5].tolist() == [[3.0, 4.0, -1.0], [5.0, 6.0, 0.0]]
    assert 0 not in b1.point_cov  # frame cameras' points are not weighed by a covariance


def test_covariance_rows_are_numbered_as_the_points() -> None:
    r = dvs_covariance_rows(3, 42, np.array([[1.0, 2.0, 0.1], [3.0, 4.0, 0.2]]))
    assert r["frame_pt_idx"].tolist() == [0, 1] and set(r["trigger_frame"]) == {42}
    assert r["cov_xy"].tolist() == pytest.approx([0.1, 0.2])
