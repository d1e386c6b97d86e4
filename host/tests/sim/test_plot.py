import numpy as np

from flytrack_host.sim.flight import simulate_flight
from flytrack_host.sim.plot import plot_tracks
from flytrack_host.tracking.evaluation import FrameTracks


def test_figure_is_written(tmp_path):
    gt = simulate_flight(2, 1.0, 50.0, seed=0)
    hyps = [FrameTracks(k, np.array([3, 4]), gt.pos[k] + 0.001) for k in range(0, gt.n_frames) if k != 20]
    out = plot_tracks(gt, hyps, tmp_path / "tracks.png", title="test")
    assert out.stat().st_size > 10_000
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
