"""The tracker benchmark runs end to end (tiny sizes), and the Stone Soup comparator is sound."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from flytrack_host.tracking.bench import app
from flytrack_host.tracking.synthetic import arena_cameras


def test_bench_cli_writes_figures(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    res = CliRunner().invoke(app, ["tracker", "--quick", "--frames", "30", "--no-stonesoup", "--json", str(out)])
    assert res.exit_code == 0, res.output
    rows = json.loads(out.read_text())["tracker"]
    assert [(r["cameras"], r["targets"]) for r in rows] == [(2, 1), (5, 2), (5, 10), (11, 3), (11, 10)]
    assert all(r["p50_ms"] > 0 and r["frames"] == 30 for r in rows)
    assert "P50" in res.output
    # The start-up case: ten animals new at once in 11 cameras, all born in frame 0, confirmed at 2.
    new = json.loads(out.read_text())["newcomers"]
    assert new[0]["kernel"] == rows[0]["kernel"] and new[0]["first_frame_cpu_ms"] > 0
    assert all(n["all_confirmed_at_frame"] == 2 and n["mota"] > 0.95 for n in new)
    assert "newcomers: 11 cameras x 10 animals" in res.output
    path = rows[0]["kernel"]
    assert f"tracker path: {'C kernel' if path == 'c' else 'NumPy'}" in res.output
    if path == "c":  # the NumPy path timed side by side on the same frames, same estimates
        assert "C kernel vs NumPy path" in res.output
        assert all(r["numpy_cpu_p50_ms"] > 0 and r["c_vs_numpy_same_ids"] for r in rows)
        assert all(r["c_vs_numpy_max_position_diff_m"] < 1e-9 for r in rows)


def test_bench_cli_numpy_path(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    res = CliRunner().invoke(app, ["tracker", "--quick", "--frames", "20", "--no-stonesoup", "--kernel", "numpy",
                                   "--json", str(out)])
    assert res.exit_code == 0, res.output
    rows = json.loads(out.read_text())["tracker"]
    assert all(r["kernel"] == "numpy" and "numpy_cpu_p50_ms" not in r for r in rows)
    assert "tracker path: NumPy" in res.output


def test_stonesoup_camera_model_matches_ours() -> None:
    pytest.importorskip("stonesoup", reason="benchmark-only dependency (host/requirements-bench.txt)")
    from stonesoup.types.array import StateVector
    from stonesoup.types.state import State

    from flytrack_host.tracking.stonesoup_baseline import CameraMeasurementModel

    cam = arena_cameras(3, seed=2)[1]
    model = CameraMeasurementModel(ndim_state=6, mapping=(0, 2, 4), noise_covar=np.eye(2), camera=cam)
    X = np.array([0.6, 0.05, 0.1])
    sv = np.zeros(6)
    sv[[0, 2, 4]] = X
    state = State(StateVector(sv))
    np.testing.assert_allclose(np.asarray(model.function(state)).ravel(), cam.project(X)[0])
    H = model.jacobian(state)
    np.testing.assert_allclose(H[:, [0, 2, 4]], cam.project_jacobian(X)[1])
    assert np.all(H[:, [1, 3, 5]] == 0)
