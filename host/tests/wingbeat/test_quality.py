"""`flytrack wingbeat` on recordings of something that is not a tethered fly: the trackers always
find *some* beat (they are built to), so the result carries a fit quality, the share of the events'
angle spread that a wing stroke phase-locked to the reported beats explains, and the command refuses
(or, when told to go on, warns) below a threshold. The simulated tethered fly keeps a high quality."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from flytrack_host.cli import app
from flytrack_host.dvs.wingbeat.analysis import track_wings
from flytrack_host.dvs.wingbeat.simulate import EVENT_DTYPE, FlySimParams, simulate_tethered_fly


def random_events(seconds: float = 0.6, rate: float = 300e3, seed: int = 1) -> np.ndarray:
    """Uniform noise over a DVS128 at a fly's event rate."""
    rng = np.random.default_rng(seed)
    n = int(seconds * rate)
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(0, int(seconds * 1e6), n))
    ev["x"], ev["y"], ev["p"] = rng.integers(0, 128, n), rng.integers(0, 128, n), rng.integers(0, 2, n)
    return ev


def moving_bar(seconds: float = 0.6, seed: int = 2) -> np.ndarray:
    """A vertical bar 3 px wide sweeping across and back twice a second: its leading side gives OFF
    events, its trailing side ON, like a wing's edges, but nothing beats."""
    rng = np.random.default_rng(seed)
    parts = []
    for t in range(0, int(seconds * 1e6), 200):
        ph = (t / 500_000) % 1.0
        xc = 10 + 108 * (2 * ph if ph < 0.5 else 2 - 2 * ph)
        k = 30
        e = np.empty(k, EVENT_DTYPE)
        e["t"] = t + np.sort(rng.integers(0, 200, k))
        e["x"] = np.clip(int(xc) + rng.integers(-1, 2, k), 0, 127)
        e["y"] = rng.integers(20, 108, k)
        e["p"] = rng.integers(0, 2, k)
        parts.append(e)
    return np.concatenate(parts)


NOT_A_FLY = {"random events": random_events, "moving bar": moving_bar}


@pytest.fixture(scope="module")
def fly() -> np.ndarray:
    return simulate_tethered_fly(FlySimParams(duration_s=0.6, seed=5))[0]


@pytest.mark.parametrize("method", ["ekf", "wra"])
def test_quality_is_high_for_the_simulated_fly(fly: np.ndarray, method: str) -> None:
    r = track_wings(fly, method)
    assert r.quality > 0.9, [w.quality for w in r.wings]
    assert all(w.quality > 0.9 for w in r.wings)


@pytest.mark.parametrize("method", ["ekf", "wra"])
@pytest.mark.parametrize("name", sorted(NOT_A_FLY))
def test_quality_is_low_when_nothing_beats(name: str, method: str) -> None:
    r = track_wings(NOT_A_FLY[name](), method)
    assert r.quality < 0.2, (name, method, [w.quality for w in r.wings])


@pytest.mark.parametrize("name", sorted(NOT_A_FLY))
def test_cli_refuses_what_is_not_a_wing_beat(tmp_path: Path, name: str) -> None:
    path = tmp_path / "rec.npy"
    np.save(path, NOT_A_FLY[name]())
    r = CliRunner().invoke(app, ["wingbeat", str(path)])
    out = " ".join(r.output.split())
    assert r.exit_code == 2, out
    assert "fit quality" in out and "--min-quality" in out, out
    assert "Hz" not in out  # no frequency reported as if it were a beat
    # told to go on: the estimates, with the warning beside them
    r = CliRunner().invoke(app, ["wingbeat", str(path), "--min-quality", "0", "--json", str(tmp_path / "q.json")])
    out = " ".join(r.output.split())
    assert r.exit_code == 0, out
    assert "warning" in out and "fit quality" in out
    q = json.loads((tmp_path / "q.json").read_text())
    assert q["ekf"]["quality"] < 0.2 and q["wra"]["quality"] < 0.2


def test_cli_reports_the_quality_of_a_fly(tmp_path: Path, fly: np.ndarray) -> None:
    path = tmp_path / "fly.npy"
    np.save(path, fly)
    r = CliRunner().invoke(app, ["wingbeat", str(path), "--method", "ekf", "--json", str(tmp_path / "f.json")])
    out = " ".join(r.output.split())
    assert r.exit_code == 0, out
    assert "fit quality 0.9" in out and "warning" not in out
    q = json.loads((tmp_path / "f.json").read_text())["ekf"]
    assert q["quality"] > 0.9 and all(w["quality"] > 0.9 for w in q["wings"])
