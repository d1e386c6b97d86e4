"""The simulated rig's own figures (tracking quality is scored by flytrack_host.tracking.evaluation)."""

import math

import pytest

from flytrack_host.sim.metrics import latency_percentiles_ms


def test_latency_percentiles_ms():
    s = latency_percentiles_ms([0.001] * 98 + [0.002, 0.010, float("nan")])
    assert s["p50_ms"] == pytest.approx(1.0)
    assert s["max_ms"] == pytest.approx(10.0)
    assert s["n"] == 100
    assert math.isnan(latency_percentiles_ms([])["p50_ms"])
