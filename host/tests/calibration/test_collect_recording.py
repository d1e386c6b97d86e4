"""`flytrack calibrate collect --recording`: LED points from a recording made with the recording writer."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from flytrack_host.calibration.collect import points_from_recording
from flytrack_host.calibration.observations import load_points
from flytrack_host.calibration.synthetic import synthetic_rig
from flytrack_host.geometry.formats import save_calibration
from flytrack_host.recording import Recorder
from flytrack_host.recording.schema import CAM_INFO, DATA2D, FLAG_REJECTED


def _row(trigger: int, cam: int, cam_frame: int, x: float, y: float, total: int = 1, idx: int = 0,
         flags: int = 0) -> np.ndarray:
    r = np.zeros(1, dtype=DATA2D)
    r["trigger_frame"], r["camera_index"], r["camera_frame"] = trigger, cam, cam_frame
    r["x_dist"], r["y_dist"], r["total_points"], r["n_points"] = x, y, total, max(total, 1)
    r["frame_pt_idx"], r["flags"] = idx, flags
    return r


def _record(tmp_path: Path, with_calibration: bool) -> tuple[Path, object, set[tuple[int, int]]]:
    """A recording of 3 cameras watching an LED; returns the folder, the rig, and the (frame, camera) dropped."""
    rig = synthetic_rig(3, n_points=120, outliers=0.0, seed=4)
    folder = tmp_path / "run"
    rec = Recorder(folder, flush_interval_s=0.05)
    rec.start()
    names = list(rig.cameras)
    info = np.zeros(3, dtype=CAM_INFO)
    for i, n in enumerate(names):
        info[i] = (7 + i, f"edge-cam-{i}".encode(), b"10.0.0.1", n.encode())  # calibration name != camera name
    rec.append("cam_info", info)
    if with_calibration:
        save_calibration(rig.cameras, tmp_path / "calibration.json")
        rec.attach("calibration.json", (tmp_path / "calibration.json").read_bytes())
    dropped: set[tuple[int, int]] = set()
    seen = {(int(f), int(c)): uv for f, c, uv in zip(rig.obs.frame, rig.obs.cam, rig.obs.uv, strict=True)}
    # The special cases fall on frames the cameras did see.
    special = [min(f for (f, c) in seen if c == cam and f > 3) for cam in range(3)]
    for f in range(120):
        for c in range(3):
            cf = 1000 * c + f  # camera frame counters differ from the trigger count
            if (f, c) not in seen:
                rec.append("data2d_distorted", _row(f, 7 + c, cf, np.nan, np.nan, total=0))
            elif f == special[0] and c == 0:  # a reflection: two points, not the LED alone
                rows = np.concatenate([_row(f, 7, cf, *seen[(f, c)], total=2),
                                       _row(f, 7, cf, 10.0, 10.0, total=2, idx=1)])
                rec.append("data2d_distorted", rows)
                dropped.add((f, c))
            elif f == special[1] and c == 1:  # could not be mapped to the trigger count
                rec.append("data2d_distorted", _row(-1, 8, cf, *seen[(f, c)]))
                dropped.add((f, c))
            elif f == special[2] and c == 2:  # marked rejected by the recorder
                rec.append("data2d_distorted", _row(f, 9, cf, *seen[(f, c)], flags=FLAG_REJECTED))
                dropped.add((f, c))
            else:
                rec.append("data2d_distorted", _row(f, 7 + c, cf, *seen[(f, c)]))
    rec.stop(finalize=False)
    return folder, rig, dropped


@pytest.mark.parametrize("finalised", [False, True])
def test_points_from_recording_match_the_views(tmp_path: Path, finalised: bool) -> None:
    folder, rig, dropped = _record(tmp_path, with_calibration=True)
    path = folder
    if finalised:
        from flytrack_host.recording import finalize

        path = finalize(folder).h5_path
    got = points_from_recording(path)
    obs = got.obs
    assert obs.camera_names == list(rig.cameras)
    assert obs.sizes == [(c.width, c.height) for c in rig.cameras.values()]
    assert (got.frames_multi, got.frames_unmapped, got.rows_rejected) == (1, 1, 1)
    want = [(int(f), int(c)) for f, c in zip(rig.obs.frame, rig.obs.cam, strict=True) if (f, c) not in dropped]
    assert [(int(f), int(c)) for f, c in zip(obs.frame, obs.cam, strict=True)] == sorted(want)
    ref = {(int(f), int(c)): uv for f, c, uv in zip(rig.obs.frame, rig.obs.cam, rig.obs.uv, strict=True)}
    assert np.allclose(obs.uv, [ref[k] for k in sorted(want)], atol=1e-3)  # stored as float32


def test_cli_collect_from_recording(tmp_path: Path) -> None:
    folder, rig, dropped = _record(tmp_path, with_calibration=False)

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "flytrack_host.cli", "calibrate", "collect", *args],
                              capture_output=True, text=True, timeout=120)

    out = tmp_path / "pts.csv"
    r = run("--recording", str(folder), "-o", str(out))  # no calibration stored: sizes must be given
    assert r.returncode == 2 and "image size unknown" in r.stderr and "Traceback" not in r.stderr
    assert not out.exists()
    r = run("--recording", str(tmp_path / "nope"), "-o", str(out))
    assert r.returncode == 2 and "not a FlyTrack recording" in r.stderr and "Traceback" not in r.stderr
    sizes = [f"--camera={n}={c.width}x{c.height}" for n, c in rig.cameras.items()]
    r = run("--recording", str(folder), "-o", str(out), *sizes)
    assert r.returncode == 0, r.stderr
    obs = load_points(out)
    assert len(obs.frame) == len(rig.obs.frame) - len(dropped)
    assert "1 without a trigger frame" in " ".join(r.stdout.split())
