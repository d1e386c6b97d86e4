"""DVS slices become per-trigger-frame 2D observations: the right slice for each frame, moved to the
frame's time with the cluster's velocity, the sensor clock tied to trigger frames by the clock model."""

from __future__ import annotations

import numpy as np
import pytest

from flytrack_host.dvs.clusters.observations import DvsObservations
from flytrack_host.intake.receiver import DvsSlice
from flytrack_host.protocol import DvsClusters
from flytrack_host.protocol.udp import CLUSTER_DTYPE

FPS = 100.0
T0_US = 7_000_123  # the sensor's time of trigger frame 0 (unknown to the host)
HOST0 = 1000.0  # host time of trigger frame 0


def _slice(t_end_us: int, x: float, vx: float, delay_s: float, seq: int) -> DvsSlice:
    c = np.zeros(1, CLUSTER_DTYPE)
    c["id"], c["x"], c["y"], c["vx"], c["vy"], c["size"], c["mass"] = 3, x, 50.0, vx, 0.0, 2.0, 12.0
    msg = DvsClusters(camera_index=5, seq=seq, t_start_us=t_end_us - 1000, t_end_us=t_end_us, clusters=c)
    recv = HOST0 + (t_end_us - T0_US) / 1e6 + delay_s
    return DvsSlice(5, msg, recv)


def frame_of_host_time(t: float) -> float:
    return (t - HOST0) * FPS


def test_slices_map_to_trigger_frames_through_the_clock_model():
    obs = DvsObservations({5: None}, FPS)
    rng = np.random.default_rng(0)
    vx = 400.0  # px/s: 4 px per frame
    for k in range(1, 300):  # 1 ms slices; delivery delay 0.3-3 ms, the freshest ones 0.3 ms
        t_end = T0_US + k * 1000
        x = 10.0 + vx * (t_end - T0_US) / 1e6
        obs.add(_slice(t_end, x, vx, float(rng.uniform(0.0003, 0.003)), k), frame_of_host_time)
    st = obs.stats()[5]
    assert st["slices"] == 299 and st["clusters"] == 299
    assert abs(st["t0_us"] - T0_US) < 500, st["t0_us"] - T0_US  # within half a slice
    for tf in (5, 17, 29):
        got = obs.frame(5, tf)
        assert got is not None
        fr, cov = got
        assert fr.dvs and fr.trigger_frame == tf and cov.shape == (1, 3)
        truth = 10.0 + vx * tf / FPS
        assert abs(float(fr.points["x_undist"][0]) - truth) < 0.3, (fr.points["x_undist"][0], truth)
        assert float(fr.points["y_undist"][0]) == pytest.approx(50.0)
    # A frame past the last slice by more than the allowed age gets nothing (no stale points).
    assert obs.frame(5, 40) is None
    assert obs.stats()[5]["no_slice"] == 1


def test_no_clock_no_observations_and_unknown_cameras_ignored():
    obs = DvsObservations({5: None}, FPS)
    obs.add(_slice(T0_US + 1000, 1.0, 0.0, 0.001, 1), None)
    assert obs.frame(5, 0) is None  # the sensor clock is not tied to trigger frames yet
    obs.add(DvsSlice(9, _slice(T0_US, 1.0, 0.0, 0.001, 2).msg, 0.0), frame_of_host_time)
    assert 9 not in obs.stats()
    with pytest.raises(ValueError):
        DvsObservations({5: None}, 0.0)


def _stamped(t_end_us: int, frame: float, x: float, vx: float, var: tuple[float, float, float], seq: int) -> DvsSlice:
    c = np.zeros(1, CLUSTER_DTYPE)
    c["id"], c["x"], c["y"], c["vx"], c["vy"], c["size"], c["mass"] = 3, x, 50.0, vx, 0.0, 2.0, 12.0
    c["var_x"], c["var_y"], c["cov_xy"] = var
    msg = DvsClusters(camera_index=5, seq=seq, t_start_us=t_end_us - 5000, t_end_us=t_end_us,
                      trigger_frame=frame, frame_period_us=10_000.0, syncs=int(frame) + 1, flags=1, clusters=c)
    return DvsSlice(5, msg, 0.0)


def test_edge_stamp_wins_over_the_clock_model_and_covariance_grows_with_the_move():
    """Slices stamped with their trigger frame (SYNCED) map by the stamp, whatever the host's clock
    model says (here it is 3 ms off); a point moved over dt gets (velocity_std dt)^2 more variance."""
    obs = DvsObservations({5: None}, FPS, velocity_std_px_s=50.0)
    vx = 400.0

    def wrong_clock(t: float) -> float:
        return frame_of_host_time(t) + 0.3

    for k in range(0, 40):  # slices cut at every sync (frame k) and halfway (k + 0.5)
        for half in (0.0, 0.5):
            f = k + half
            obs.add(_stamped(T0_US + int(f * 10_000), f, 10.0 + vx * f / FPS, vx, (0.3, 0.2, 0.05), 2 * k),
                    wrong_clock)
    st = obs.stats()[5]
    assert st["synced_slices"] == 80 and st["t0_us"] is None
    fr, cov = obs.frame(5, 17)
    assert float(fr.points["x_dist"][0]) == pytest.approx(10.0 + vx * 17 / FPS, abs=1e-3)
    assert cov[0] == pytest.approx([0.3, 0.2, 0.05], abs=1e-6)  # stated at the frame: no move, no growth
    obs2 = DvsObservations({5: None}, FPS, velocity_std_px_s=50.0)
    obs2.add(_stamped(T0_US, 16.5, 100.0, vx, (0.3, 0.2, 0.05), 1), None)  # half a frame before frame 17
    fr2, cov2 = obs2.frame(5, 17)
    assert float(fr2.points["x_dist"][0]) == pytest.approx(100.0 + vx * 0.005, abs=1e-3)
    assert cov2[0, 0] == pytest.approx(0.3 + (50.0 * 0.005) ** 2, rel=1e-5)
    assert cov2[0, 2] == pytest.approx(0.05, rel=1e-6)
    assert obs2.frame(5, 19) is None  # older than max_age_frames (2)
