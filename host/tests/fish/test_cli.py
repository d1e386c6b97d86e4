"""`flytrack fish track` on real video files (FFV1 through OpenCV) and a calibration file, and its bad input:
videos of different lengths or frame rates, a calibration missing a camera, frames with no fish, a fish
leaving the view."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from flytrack_host.cli import app
from flytrack_host.fish.io import read_tracks
from flytrack_host.fish.render import render_sequence
from flytrack_host.fish.school import make_school
from flytrack_host.fish.shape import default_model
from flytrack_host.fish.views import AirView, tank_rig
from flytrack_host.geometry.formats import save_calibration

runner = CliRunner()
N_BG = 3
QUICK = ["--sa-levels", "2", "--polish-iterations", "8", "--background-frames", str(N_BG)]


def _write(path: Path, frames: list[np.ndarray], fps: float) -> None:
    h, w = frames[0].shape
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), fps, (w, h), False)
    assert vw.isOpened()
    for f in frames:
        vw.write(f)
    vw.release()


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """One fish, 12 frames: absent in the first two (no fish), gone from the top view in the last three."""
    d = tmp_path_factory.mktemp("fishcli")
    school = make_school(1, 12)
    truth = school.truth.copy()
    truth[:2] = np.nan  # frames with no fish
    truth[-3:] = np.nan  # the fish has left the view
    rig = tank_rig((640, 512), (512, 384), top_zoom=2.0)
    views = [AirView(rig["top"]), AirView(rig["side"])]
    imgs = render_sequence(views, default_model(school.length), truth, np.random.default_rng(5), n_background=N_BG)
    cal = d / "rig.json"
    save_calibration({"top": rig["top"], "side": rig["side"]}, cal)
    return {"dir": d, "imgs": imgs, "cal": cal, "T": truth.shape[0]}


def _run(args: list[str]) -> tuple[int, str]:
    r = runner.invoke(app, args)
    return r.exit_code, r.output


def test_track_writes_hdf5_and_plots_and_reports_absent_fish(scene: dict) -> None:
    d = scene["dir"]
    _write(d / "top.avi", scene["imgs"][0], 250.0)
    _write(d / "side.avi", scene["imgs"][1], 250.0)
    out = d / "tracks.h5"
    code, text = _run(["fish", "track", str(d / "top.avi"), str(d / "side.avi"), "--calibration", str(scene["cal"]),
                       "--out", str(out), "--plots", str(d / "plots"), *QUICK])
    assert code == 0, text
    assert "no fish in the top view" in text  # frames 0 and 1
    assert "no silhouette in 3 frames" in text  # the fish left the view
    tr = read_tracks(out)
    assert len(tr["fish"]) == 1
    assert tr["frame"][0] == 2  # modelled in the first frame with the fish
    assert len(tr["frame"]) == scene["T"] - 2
    for name in ("fish_fig5_state.png", "fish_fig9_midlines.png", "fish_fig11_curvature.png"):
        assert (d / "plots" / name).stat().st_size > 10_000


def test_different_lengths_and_frame_rates_are_said_and_tracked(scene: dict) -> None:
    d = scene["dir"]
    _write(d / "top.avi", scene["imgs"][0], 250.0)
    _write(d / "side.avi", scene["imgs"][1][:-2], 250.0)  # two frames short
    code, text = _run(["fish", "track", str(d / "top.avi"), str(d / "side.avi"), "--calibration", str(scene["cal"]),
                       "--out", str(d / "short.h5"), *QUICK])
    assert code == 0, text
    assert "different lengths" in text and "tracking the first" in text
    assert len(read_tracks(d / "short.h5")["frame"]) == scene["T"] - 2 - 2
    # the side camera at twice the rate (each frame twice): paired by time, tracked the same
    doubled = [f for f in scene["imgs"][1] for _ in range(2)]
    _write(d / "side.avi", doubled, 500.0)
    code, text = _run(["fish", "track", str(d / "top.avi"), str(d / "side.avi"), "--calibration", str(scene["cal"]),
                       "--out", str(d / "rate.h5"), *QUICK])
    assert code == 0, text
    assert "500 fps" in text and "nearest frame in time" in text
    assert len(read_tracks(d / "rate.h5")["fish"]) == 1


def test_bad_input_is_one_clear_error(scene: dict, tmp_path: Path) -> None:
    d = scene["dir"]
    _write(d / "top.avi", scene["imgs"][0], 250.0)
    _write(d / "front.avi", scene["imgs"][1], 250.0)
    code, text = _run(["fish", "track", str(d / "top.avi"), str(d / "front.avi"), "--calibration", str(scene["cal"]),
                       *QUICK])
    assert code == 2 and "no camera front" in text and "Traceback" not in text
    code, text = _run(["fish", "track", str(d / "top.avi"), str(tmp_path / "none.avi"), "--calibration",
                       str(scene["cal"]), "--cameras", "top,side"])
    assert code == 2 and "no such video file" in text
    (tmp_path / "bad.json").write_text("{ not json")
    code, text = _run(["fish", "track", str(d / "top.avi"), str(d / "front.avi"), "--calibration",
                       str(tmp_path / "bad.json"), "--cameras", "top,side"])
    assert code == 2 and "error" in text
    # a video that never shows a fish: no model can be made
    _write(d / "empty.avi", scene["imgs"][0][:N_BG + 2], 250.0)
    _write(d / "empty_side.avi", scene["imgs"][1][:N_BG + 2], 250.0)
    code, text = _run(["fish", "track", str(d / "empty.avi"), str(d / "empty_side.avi"), "--calibration",
                       str(scene["cal"]), "--cameras", "top,side", *QUICK])
    assert code == 2 and "no model could be made" in text


def test_fewer_fish_in_clear_view_than_asked_tracks_those_and_says_so(scene: dict) -> None:
    d = scene["dir"]
    _write(d / "top.avi", scene["imgs"][0], 250.0)
    _write(d / "side.avi", scene["imgs"][1], 250.0)
    code, text = _run(["fish", "track", str(d / "top.avi"), str(d / "side.avi"), "--calibration", str(scene["cal"]),
                       "--out", str(d / "two.h5"), "--fish", "2", *QUICK])
    assert code == 0, text
    flat = " ".join(text.split())  # rich wraps long lines
    assert "only 1 of 2 fish were seen in clear view" in flat and "the first modelled in frame 2" in flat
    tr = read_tracks(d / "two.h5")
    assert len(tr["fish"]) == 1 and tr["frame"][0] == 2 and tr["fish"][0]["model_frame"] == 2


def test_demo_reports_its_blas_threads_and_refuses_a_negative_count(tmp_path: Path) -> None:
    out = tmp_path / "demo.json"
    code, text = _run(["fish", "demo", "--fish", "1", "--frames", "20", "--small", "--blas-threads", "2",
                       "--json", str(out)])
    assert code == 0, text
    assert "2 BLAS threads" in text
    s = json.loads(out.read_text())
    assert s["blas_threads"] == 2 and s["fish"] == 1 and s["fish_frames_per_cpu_s"] > 0
    code, text = _run(["fish", "demo", "--blas-threads", "-1"])
    assert code == 2 and "--blas-threads" in text
