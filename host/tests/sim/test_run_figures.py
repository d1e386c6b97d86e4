"""The demo's own figures computed from a recording: frame numbering check, latency per bundle,
camera lateness."""

import h5py
import numpy as np
import pytest

from flytrack_host.recording.schema import DATA2D, FLAG_TRACKED
from flytrack_host.sim.run import _frame_numbering, _lateness


def _recording(path, shift_cam1_from: int):
    rows = []
    for cf in range(10):
        for cam in (0, 1):
            r = np.zeros(1, DATA2D)
            r["camera_index"] = cam
            r["camera_frame"] = cf
            r["trigger_frame"] = cf + (1 if cam == 1 and cf >= shift_cam1_from else 0)
            r["flags"] = FLAG_TRACKED
            r["edge_recv_ns"] = int((100.0 + cf * 0.01 + 0.001) * 1e9)
            r["edge_done_ns"] = int((100.0 + cf * 0.01 + 0.0011) * 1e9)
            r["cam_received_timestamp"] = 100.0 + cf * 0.01 + 0.0015
            rows.append(r)
    with h5py.File(path, "w") as f:
        f["data2d_distorted"] = np.concatenate(rows)
        f.attrs["format"] = '"flytrack-recording"'  # what the reader checks (attributes are JSON)
    return path


def test_misnumbered_frames_are_counted_and_bundles_use_their_true_frames(tmp_path):
    handoff = 100.0 + np.arange(10) * 0.01
    written = np.stack([handoff, handoff], axis=1)  # (frames, cameras)
    written[7, 0] += 0.0002  # camera 0's frame 7 reached its edge a little later
    rec = _recording(tmp_path / "r.h5", shift_cam1_from=6)
    out = _frame_numbering(str(rec), written)
    assert out["camera_frames"] == 20
    assert out["misnumbered"] == 4  # camera 1, frames 6..9
    # Host frame 7 was built from camera 0's frame 7 and camera 1's frame 6: the latest is camera 0's.
    assert out["bundle_handoff"][7] == pytest.approx(handoff[7] + 0.0002)
    assert out["bundle_handoff"][10] == pytest.approx(handoff[9])
    assert out["parts_p50_ms"]["edge_read"] == pytest.approx(1.0, abs=1e-3)
    assert out["parts_p50_ms"]["extraction"] == pytest.approx(0.1, abs=1e-3)
    assert out["parts_p50_ms"]["udp_to_host"] == pytest.approx(0.4, abs=1e-3)


def test_no_recording_gives_empty_figures():
    out = _frame_numbering(None, np.zeros((3, 2)))
    assert out["misnumbered"] == 0 and out["bundle_handoff"] == {}


def test_lateness_against_a_perfect_clock():
    t = 5.0 + np.arange(100) / 100.0
    t[50:60] += 0.020  # ten frames 20 ms late
    s = _lateness(t, 100.0)
    assert s["max_ms"] == pytest.approx(20.0, abs=1e-6)
    assert s["p50_ms"] == pytest.approx(0.0, abs=1e-6)
