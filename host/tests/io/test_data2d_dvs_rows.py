"""Re-tracking from a recording leaves event cameras' rows out: the tracker weighs them by their
covariance (SPEC 1.6), which data2d does not keep, and as frame points they could start targets."""

from __future__ import annotations

import numpy as np

from flytrack_host.io.data2d import iter_bundles, n_frames
from flytrack_host.recording.schema import DATA2D, FLAG_DVS


def test_dvs_rows_are_not_re_tracked() -> None:
    rows = np.zeros(5, DATA2D)
    rows["trigger_frame"] = [0, 0, 1, 1, 2]
    rows["camera_index"] = [0, 5, 0, 5, 5]
    rows["x_dist"], rows["y_dist"] = 10.0, 20.0
    rows["flags"] = [0, FLAG_DVS, 0, FLAG_DVS, FLAG_DVS]
    bundles = list(iter_bundles(rows, 100.0))
    assert [b.trigger_frame for b in bundles] == [0, 1]  # frame 2 had event-camera rows only
    assert all(set(b.detections) == {0} for b in bundles)
    assert n_frames(rows) == 2
    rows["flags"] = 0
    assert [sorted(b.detections) for b in iter_bundles(rows, 100.0)] == [[0, 5], [0, 5], [5]]
