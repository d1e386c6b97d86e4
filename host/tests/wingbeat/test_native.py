"""The edge's C wing-beat tracker (edge/events/algos/wingbeat.c) against the host's Python one on the same
simulated events: the same fly found, the same beats, the same scores against the truth."""

from __future__ import annotations

import numpy as np
import pytest

from flytrack_host.dvs.wingbeat.analysis import WingbeatResult, WingTrack, _combine, score_wings, track_wings
from flytrack_host.dvs.wingbeat.geometry import WingbeatError
from flytrack_host.dvs.wingbeat.native import NativeWingbeat, edge_beats
from flytrack_host.dvs.wingbeat.simulate import FlySimParams, simulate_tethered_fly

SIM = FlySimParams(duration_s=1.0, manoeuvre_start_s=0.4, manoeuvre_s=0.3, seed=7)


@pytest.fixture(scope="module")
def fly():
    return simulate_tethered_fly(SIM)


@pytest.fixture(scope="module")
def both(fly):
    ev, _ = fly
    py = track_wings(ev, "ekf")
    c = NativeWingbeat(128, 128)
    beats = np.concatenate([c.feed(ev[i:i + 5000]) for i in range(0, len(ev), 5000)])  # streamed in chunks
    return py, c, beats


def test_same_fly_found(both):
    py, c, _ = both
    g = c.geometry
    assert g["body"] == pytest.approx(py.geometry.body, abs=1e-9)
    assert g["heading_rad"] == pytest.approx(py.geometry.heading_rad, abs=1e-12)
    assert g["size_px"] == pytest.approx(py.geometry.size_px, abs=1e-9)
    assert g["mean_stroke"] == pytest.approx(py.geometry.mean_stroke, abs=1e-9)
    assert g["spread"] == pytest.approx(py.geometry.spread, abs=1e-9)
    assert g["start_freq_hz"] == pytest.approx(py.start_freq_hz, rel=1e-9)


def test_same_beats_per_edge(both):
    py, c, beats = both
    for w in (0, 1):
        for e, name in ((0, "leading"), (1, "trailing")):
            p = py.wings[w].edges[name].beats
            n = edge_beats(beats, w, e)
            assert len(n.t_us) == len(p.t_us) > 150
            assert np.abs(n.t_us - p.t_us).max() <= 1.0  # the C side rounds to whole microseconds
            assert np.abs(n.freq_hz - p.freq_hz).max() < 1e-3  # float32 on the wire, double inside
            assert np.abs(n.amplitude - p.amplitude).max() < 1e-5
    assert c.stats["in_roi"] == py.events_in_roi


def test_same_scores_against_truth(fly, both):
    _, truth = fly
    py, _, beats = both
    wings = [WingTrack(w, {}, _combine(edge_beats(beats, w, 0), edge_beats(beats, w, 1))) for w in (0, 1)]
    cres = WingbeatResult("ekf", py.geometry, py.start_freq_hz, wings, py.events_total, py.events_in_roi, 0.0)
    for sp, sc in zip(score_wings(py, truth.freq_at, truth.amplitude_at),
                      score_wings(cres, truth.freq_at, truth.amplitude_at), strict=True):
        print(f"wing {sp.wing}: frequency error Python {sp.freq_err_pct_mean:.3f} % C {sc.freq_err_pct_mean:.3f} %, "
              f"amplitude error Python {sp.amp_err_pct_mean:.3f} % C {sc.amp_err_pct_mean:.3f} %")
        assert sc.beats == sp.beats
        assert sc.freq_err_pct_mean == pytest.approx(sp.freq_err_pct_mean, abs=0.01)
        assert sc.amp_err_pct_mean == pytest.approx(sp.amp_err_pct_mean, abs=0.01)
        assert sc.freq_err_pct_mean < 1.0 and sc.amp_err_pct_mean < 5.0


def test_live_estimate_follows_the_manoeuvre(fly, both):
    _, truth = fly
    _, c, _ = both
    w = c.wings()
    end = truth.t_us[-1]
    for k in (0, 1):
        assert w["freq_hz"][k] == pytest.approx(truth.freq_at(end), rel=0.01)
        assert w["amplitude"][k] == pytest.approx(truth.amplitude_at(k, end), rel=0.08)
        assert 0.0 <= w["phase"][k] < 2 * np.pi


def test_no_fly_is_a_clear_error_and_nothing_breaks():
    rng = np.random.default_rng(1)
    from flytrack_host.dvs.events.files import EVENT_DTYPE

    ev = np.zeros(30_000, EVENT_DTYPE)  # 0.3 s of uniform noise, 100 k events/s
    ev["t"] = np.sort(rng.integers(0, 300_000, len(ev)))
    ev["x"], ev["y"] = rng.integers(0, 128, len(ev)), rng.integers(0, 128, len(ev))
    c = NativeWingbeat(128, 128)
    assert len(c.feed(ev)) == 0 and not c.tracking
    msg, fails = c.last_error()
    assert fails == 2 and "no beating wing in view" in msg
    with pytest.raises(WingbeatError, match="no beating wing"):
        _ = c.geometry
    assert np.all(c.wings()["updates"] == 0)
    with pytest.raises(ValueError, match="bad wing-beat parameters"):
        NativeWingbeat(128, 128, harmonics=9)
    with pytest.raises(ValueError, match="unknown parameter"):
        NativeWingbeat(128, 128, nonsense=1)
