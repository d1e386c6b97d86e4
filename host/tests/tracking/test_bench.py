"""The tracker benchmark runs end to end (tiny sizes), and the Stone Soup comparator is sound."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from flytrack_host.tracking.bench import app
from flytrack_host.tracking.synthetic import arena_cameras
from flytrack_host.tracking.tracker import KERNEL_ENV
from flytrack_host.util.testing import under_make


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
    if under_make() and not os.environ.get(KERNEL_ENV):  # make builds the kernel: NumPy here = broken build
        assert path == "c", res.output
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


def test_stonesoup_camera_model_matches_ours(monkeypatch: pytest.MonkeyPatch) -> None:
    # Stone Soup is not installed by `make test`; `make bench-tracker` installs it and the bench runs
    # the same check_camera_model before it times anything.
    pytest.importorskip("stonesoup", reason="benchmark-only dependency (host/requirements-bench.txt)")
    from flytrack_host.tracking import stonesoup_baseline as ssb

    cams = arena_cameras(3, seed=2)
    ssb.check_camera_model(cams)
    # The check can fail: a Jacobian that is not the camera's is caught.
    monkeypatch.setattr(ssb.CameraMeasurementModel, "jacobian", lambda self, state, **kw: np.zeros((2, 6)))
    with pytest.raises(AssertionError, match="camera 0: Stone Soup Jacobian"):
        ssb.check_camera_model(cams)


def _flytrack(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "flytrack_host.cli", *args], capture_output=True, text=True,
                          timeout=60, env={**os.environ, **(env or {})})


@pytest.mark.parametrize(("args", "opt"), [(["--frames", "-1"], "--frames"), (["--frames", "0"], "--frames"),
                                           (["--stonesoup-frames", "0"], "--stonesoup-frames"),
                                           (["--seed", "-1"], "--seed"), (["--kernel", "fortran"], "--kernel")])
def test_bad_numbers_are_one_clear_error(args: list[str], opt: str) -> None:
    r = _flytrack("bench", "tracker", "--quick", "--no-stonesoup", *args)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "Invalid value for" in r.stderr and opt in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_c_kernel_asked_but_not_built_is_one_clear_error(tmp_path: Path) -> None:
    r = _flytrack("bench", "tracker", "--quick", "--no-stonesoup", "--kernel", "c",
                  env={"FLYTRACK_BUILD_DIR": str(tmp_path)})
    assert r.returncode == 2 and "make build" in r.stderr and "Traceback" not in r.stderr, r.stdout + r.stderr
