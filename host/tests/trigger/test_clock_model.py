from __future__ import annotations

import math

import numpy as np
import pytest

from flytrack_host.trigger.clock_model import ClockModel


def _feed(m: ClockModel, dev_times, gain=1.00002, offset=1.7e9, rtt=0.002, noise=20e-6, seed=1):
    rng = np.random.default_rng(seed)
    for d in dev_times:
        h = gain * d + offset + rng.normal(0, noise)
        m.add_sample(h - rtt / 2, h + rtt / 2, d)


def test_recovers_gain_offset_and_residual() -> None:
    m = ClockModel(frame_period_s=0.01)
    _feed(m, np.arange(200) * 0.05)
    assert m.fitted and m.n_samples >= 40
    assert m.gain == pytest.approx(1.00002, abs=2e-5)
    assert m.device_to_host(5.0) == pytest.approx(1.00002 * 5.0 + 1.7e9, abs=50e-6)
    assert 5e-6 < m.residual_s < 60e-6
    t = m.frame_to_host_time(1234.5)
    assert m.host_time_to_frame(t) == pytest.approx(1234.5, abs=1e-4)  # 1 us at 100 fps
    assert m.host_to_device(m.device_to_host(3.3)) == pytest.approx(3.3, abs=1e-6)


def test_long_round_trips_and_outliers_are_ignored() -> None:
    m = ClockModel(frame_period_s=0.01, max_rtt_s=0.01)
    assert not m.add_sample(0.0, 0.5, 0.0)  # round trip too long
    assert m.rejected_rtt == 1
    assert not m.add_sample(math.nan, 1.0, 0.0)
    rng = np.random.default_rng(3)
    for i in range(100):
        d = i * 0.05
        h = d + 100.0
        if i % 10 == 5:
            h += 0.004  # a delayed reply that still passed the rtt bound
        rtt = 0.002 + rng.uniform(0, 0.006)
        m.add_sample(h - rtt / 2, h + rtt / 2, d)
    assert m.residual_s < 1e-4
    assert m.device_to_host(2.0) == pytest.approx(102.0, abs=1e-4)


def test_restarted_device_starts_a_new_window() -> None:
    m = ClockModel(frame_period_s=0.01)
    _feed(m, np.arange(50) * 0.05)
    _feed(m, np.arange(20) * 0.05, offset=1.7e9 + 10.0)  # device time went back to 0
    assert m.restarts >= 1
    assert m.device_to_host(0.5) == pytest.approx(1.00002 * 0.5 + 1.7e9 + 10.0, abs=1e-4)


def test_clock_jump_resets_after_consistent_samples() -> None:
    m = ClockModel(frame_period_s=0.01, jump_count=3)
    _feed(m, np.arange(50) * 0.05, noise=1e-6)
    _feed(m, 2.5 + np.arange(10) * 0.05, offset=1.7e9 + 0.5, noise=1e-6)  # host clock stepped
    assert m.restarts == 1
    assert m.device_to_host(3.0) == pytest.approx(1.00002 * 3.0 + 1.7e9 + 0.5, abs=1e-4)


def test_no_fit_is_a_clear_error() -> None:
    m = ClockModel()
    with pytest.raises(RuntimeError, match="no fit"):
        m.device_to_host(1.0)
    _feed(m, np.arange(10) * 0.1)
    with pytest.raises(RuntimeError, match="frame period"):
        m.frame_to_host_time(3)
