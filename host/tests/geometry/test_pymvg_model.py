"""pymvg JSON cameras project as pymvg 2.1.0 itself projects them (its CameraModel from PyPI is the
oracle), skewed and distorted ones included, and FlyTrack's pymvg files read back the same in pymvg."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from flytrack_host.geometry.formats import load_calibration, save_calibration
from flytrack_host.util.testing import missing_part


@pytest.fixture(scope="module")
def pymvg_system():  # noqa: ANN201
    try:
        import pymvg.multi_camera_system as mcs
    except ImportError:  # under make a failure (setup installs it), a skip for bare pytest without it
        missing_part("pymvg 2.1.0 (host/requirements-nodeps.txt, installed by `make setup`)")
    return mcs


def _rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    return (np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]]) @ np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
            @ np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]]))


# (skew, distortion): pymvg's model and OpenCV's part ways only when both are there.
CASES = {"skewed, distorted": (12.0, [-0.30, 0.12, 0.002, -0.001, 0.0]),
         "skewed": (12.0, [0.0] * 5), "distorted": (0.0, [-0.30, 0.12, 0.002, -0.001, 0.0])}


def _write_pymvg(path: Path, skew: float, dist: list[float]) -> None:
    K = np.array([[800.0, skew, 330.0], [0.0, 790.0, 250.0], [0.0, 0.0, 1.0]])
    R = _rotation(0.2, -0.3, 0.1)
    t = -R @ np.array([0.1, -0.2, -1.5])  # centre 1.5 m behind the origin, looking at it
    P = np.hstack([K, np.zeros((3, 1))])
    doc = {"__pymvg_file_version__": "1.0", "camera_system": [{
        "name": "cam", "width": 659, "height": 494, "P": P.tolist(), "K": K.tolist(), "D": dist,
        "R": np.eye(3).tolist(), "Q": R.tolist(), "translation": t.tolist()}]}
    path.write_text(json.dumps(doc))


def _points_in_view(cam) -> np.ndarray:  # noqa: ANN001
    """A grid of world points that project inside the image (a quarter of them near its corners)."""
    u, v = np.meshgrid(np.linspace(5, cam.width - 5, 15), np.linspace(5, cam.height - 5, 11))
    uv = np.column_stack([u.ravel(), v.ravel()])
    origins, dirs = cam.ideal_rays(cam.undistort(uv))
    return origins + dirs * np.linspace(1.0, 2.5, len(uv))[:, None]


@pytest.mark.parametrize("case", list(CASES))
def test_projects_as_pymvg_does(tmp_path: Path, case: str, pymvg_system) -> None:  # noqa: ANN001
    skew, dist = CASES[case]
    path = tmp_path / "cams.json"
    _write_pymvg(path, skew, dist)
    ours = load_calibration(path)["cam"]
    theirs = pymvg_system.MultiCameraSystem.from_pymvg_file(str(path)).get_camera("cam")
    X = _points_in_view(ours)
    diff = np.abs(ours.project(X) - theirs.project_3d_to_pixel(X, distorted=True))
    assert diff.max() < 1e-6, f"{case}: up to {diff.max():.3g} px from pymvg"  # measured ~1e-10
    # and the way back: pymvg's rays through our pixels hit the same points
    assert np.abs(ours.undistort(ours.project(X)) - theirs.project_3d_to_pixel(X, distorted=False)).max() < 1e-6


def test_our_pymvg_file_reads_the_same_in_pymvg(tmp_path: Path, pymvg_system) -> None:  # noqa: ANN001
    src = tmp_path / "in.json"
    _write_pymvg(src, *CASES["skewed, distorted"])
    cam = load_calibration(src)["cam"]
    out = tmp_path / "out.json"
    save_calibration({"cam": cam}, out)
    theirs = pymvg_system.MultiCameraSystem.from_pymvg_file(str(out)).get_camera("cam")
    X = _points_in_view(cam)
    assert np.abs(cam.project(X) - theirs.project_3d_to_pixel(X, distorted=True)).max() < 1e-6
