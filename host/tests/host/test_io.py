"""Export to .braidz / CSV and read back; re-tracking from FlyTrack recordings, .braidz and flydra .h5."""

from __future__ import annotations

import gzip
import io
import zipfile

import h5py
import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from flytrack_host.cli import app
from flytrack_host.io.braidz import (
    ASSOC_COLUMNS,
    CAM_INFO_COLUMNS,
    CLOCK_COLUMNS,
    DATA2D_COLUMNS,
    KALMAN_COLUMNS,
    TEXTLOG_COLUMNS,
    export_braidz,
    read_braidz,
)
from flytrack_host.io.csv_export import export_csv
from flytrack_host.io.retrack import cameras_for, load_2d, params_with, retrack
from flytrack_host.recording import load_recording
from flytrack_host.recording.schema import TRIGGER_CLOCK
from flytrack_host.recording.synthetic import start_synthetic_recording, write_scenario_frames
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.synthetic import make_scenario

FPS = 100.0


@pytest.fixture(scope="module")
def scenario():
    return make_scenario(n_cameras=4, n_targets=2, duration_s=1.5, fps=FPS, close_pass_m=None,
                         enter_exit=False, false_positives_per_camera=0.0, seed=3)


@pytest.fixture(scope="module")
def recording(scenario, tmp_path_factory):
    """A FlyTrack recording of the scenario, tracked live-style by the real tracker."""
    d = tmp_path_factory.mktemp("rec")
    rec = start_synthetic_recording(d / "run.flytrack", scenario, FPS)
    clk = np.zeros(3, dtype=TRIGGER_CLOCK)
    clk["framecount"] = [0, 50, 100]
    clk["fraction"] = 0.5
    clk["start_timestamp"] = 1000.0 + clk["framecount"] / FPS
    clk["stop_timestamp"] = clk["start_timestamp"] + 0.001
    rec.append("trigger_clock_info", clk)
    write_scenario_frames(rec, scenario, FPS, track=True, camera_frame_offset=500)
    rec.stop()
    return d / "run.flytrack"


def _csv(z: zipfile.ZipFile, name: str) -> pd.DataFrame:
    return pd.read_csv(io.BytesIO(gzip.decompress(z.read(name))))


def test_export_braidz_and_read_it_back(recording, tmp_path):
    rec = load_recording(recording)
    out = tmp_path / "x.braidz"
    counts = export_braidz(rec, out)
    with zipfile.ZipFile(out) as z:
        names = set(z.namelist())
        assert {"kalman_estimates.csv.gz", "data2d_distorted.csv.gz", "data_association.csv.gz",
                "cam_info.csv.gz", "trigger_clock_info.csv.gz", "textlog.csv.gz", "calibration.xml",
                "braid_metadata.yml", "README.md"} <= names
        for name, cols in (("kalman_estimates", KALMAN_COLUMNS), ("data2d_distorted", DATA2D_COLUMNS),
                           ("data_association", ASSOC_COLUMNS), ("cam_info", CAM_INFO_COLUMNS),
                           ("trigger_clock_info", CLOCK_COLUMNS), ("textlog", TEXTLOG_COLUMNS)):
            assert list(_csv(z, f"{name}.csv.gz").columns) == cols, name
        kal = _csv(z, "kalman_estimates.csv.gz")
        src = rec.table("kalman_estimates")
        assert len(kal) == len(src) == counts["kalman_estimates"] > 0
        assert np.allclose(kal["x"], np.sort(src, order="trigger_frame", kind="stable")["x"])
        d2 = _csv(z, "data2d_distorted.csv.gz")
        assert len(d2) == len(rec.table("data2d_distorted"))
        assert set(d2["camn"]) == {0, 1, 2, 3}
        tl = _csv(z, "textlog.csv.gz")
        assert tl["message"].iloc[0].startswith("MainBrain running at 100 fps, (")  # as Braid writes it
        assert '"tracking_params"' in tl["message"].iloc[1]
        meta = z.read("braid_metadata.yml").decode()
        assert "schema: 3" in meta and "saving_program_name: flytrack" in meta
        clock = _csv(z, "trigger_clock_info.csv.gz")
        assert list(clock["framecount"]) == [0, 50, 100] and list(clock["tcnt"]) == [128] * 3
    back = read_braidz(out)
    assert back.fps == FPS and back.cam_names == {0: "cam0", 1: "cam1", 2: "cam2", 3: "cam3"}
    orig = rec.table("data2d_distorted")
    a = np.sort(back.rows, order=["trigger_frame", "camera_index", "frame_pt_idx"])
    b = np.sort(orig, order=["trigger_frame", "camera_index", "frame_pt_idx"])
    assert np.array_equal(a["trigger_frame"], b["trigger_frame"])
    assert np.allclose(a["x_dist"], b["x_dist"], equal_nan=True)
    assert back.calibration is not None and back.calibration[0] == "calibration.xml"


def test_export_csv(recording, tmp_path):
    files = export_csv(load_recording(recording), tmp_path / "csv")
    k = pd.read_csv(files["kalman_estimates"])
    assert {"obj_id", "trigger_frame", "x", "P00", "P55"} <= set(k.columns) and len(k) > 0
    assert pd.read_csv(files["cam_info"])["name"].tolist() == ["cam0", "cam1", "cam2", "cam3"]


def _track_quality(scenario, out):
    rec = load_recording(out)
    k = rec.table("kalman_estimates")
    assert len(k) > 0
    # Every estimate lies near some true target of its frame.
    errs = []
    for row in k[::7]:
        truth = scenario.truth[int(row["trigger_frame"])]
        p = np.array([row["x"], row["y"], row["z"]])
        errs.append(min(np.linalg.norm(p - t) for t in truth.values()))
    return len(k), float(np.median(errs))


def test_retrack_from_own_recording_with_other_params(scenario, recording, tmp_path):
    data = load_2d(recording)
    cams = cameras_for(data)
    params = params_with(data.tracking_params, sets=["motion_noise_scale=0.2"])
    assert params.motion_noise_scale == 0.2
    res = retrack(data, cams, params, data.fps, out=tmp_path / "rt.flytrack", progress=False)
    assert res.frames == len(scenario.bundles) and res.objects >= 2
    n, med = _track_quality(scenario, res.out)
    assert n > len(scenario.bundles)  # two targets most of the time
    assert med < 0.01, med
    assert load_recording(res.out).meta["tracking_params"]["motion_noise_scale"] == 0.2


def test_retrack_from_braidz(scenario, recording, tmp_path):
    bz = tmp_path / "x.braidz"
    export_braidz(load_recording(recording), bz)
    data = load_2d(bz)
    assert np.isnan(data.rows["x_undist"]).all()  # braidz has distorted pixels only; filled from calibration
    res = retrack(data, cameras_for(data), TrackingParams(), data.fps, out=tmp_path / "rt.flytrack", progress=False)
    assert res.objects >= 2
    n, med = _track_quality(scenario, res.out)
    assert med < 0.01, med


def test_retrack_from_flydra_h5(scenario, recording, tmp_path):
    """A flydra-style .h5 (PyTables tables are HDF5 compound datasets) with a calibration group."""
    rec = load_recording(recording)
    d2 = rec.table("data2d_distorted")
    table = np.zeros(len(d2), dtype=[("camn", "<u2"), ("frame", "<i8"), ("timestamp", "<f8"),
                                      ("cam_received_timestamp", "<f8"), ("x", "<f4"), ("y", "<f4"),
                                      ("area", "<f4"), ("slope", "<f4"), ("eccentricity", "<f4"),
                                      ("frame_pt_idx", "u1"), ("cur_val", "u1"), ("mean_val", "<f4"),
                                      ("sumsqf_val", "<f4")])
    table["camn"], table["frame"] = d2["camera_index"], d2["trigger_frame"]
    table["timestamp"], table["cam_received_timestamp"] = d2["timestamp"], d2["cam_received_timestamp"]
    table["x"], table["y"], table["area"] = d2["x_dist"], d2["y_dist"], d2["area"]
    table["slope"], table["eccentricity"] = np.nan, np.nan
    table["frame_pt_idx"] = d2["frame_pt_idx"]
    path = tmp_path / "flydra.h5"
    with h5py.File(path, "w") as h5:
        h5["data2d_distorted"] = table
        ci = np.zeros(4, dtype=[("camn", "<u2"), ("cam_id", "S16")])
        ci["camn"] = range(4)
        ci["cam_id"] = [f"cam_{i}".encode() for i in range(4)]
        h5["cam_info"] = ci
        for i, cam in scenario.cameras.items():
            h5[f"calibration/pmat/cam_{i}"] = cam.P
            h5[f"calibration/resolution/cam_{i}"] = np.array([cam.width, cam.height])
            h5[f"calibration/intrinsic_nonlinear/cam_{i}"] = cam.dist[:4]
    data = load_2d(path)
    res = retrack(data, cameras_for(data), TrackingParams(), FPS, out=tmp_path / "rt.flytrack", progress=False)
    assert res.objects >= 2
    n, med = _track_quality(scenario, res.out)
    assert med < 0.01, med


def test_cli_export_and_retrack(recording, tmp_path):
    runner = CliRunner()
    bz = tmp_path / "cli.braidz"
    r = runner.invoke(app, ["export", str(recording), "--braidz", str(bz), "--csv", str(tmp_path / "csv")])
    assert r.exit_code == 0, r.output
    assert bz.exists() and (tmp_path / "csv" / "data2d_distorted.csv").exists()
    out = tmp_path / "cli_rt.flytrack"
    r = runner.invoke(app, ["retrack", str(bz), "--out", str(out), "--set", "motion_noise_scale=0.2",
                            "--no-progress"])
    assert r.exit_code == 0, r.output
    assert "objects" in r.output and (out / "recording.h5").exists()
    r = runner.invoke(app, ["retrack", str(bz), "--out", str(tmp_path / "bad"), "--set", "no_such_param=1"])
    assert r.exit_code == 2 and "no_such_param" in r.output
