"""Calibration file formats: round trips to 1e-9 px, external layouts, and malformed files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from flytrack_host.geometry.camera import Camera
from flytrack_host.geometry.formats import (
    CalibrationFormatError,
    detect_format,
    load_calibration,
    load_flydra_xml,
    save_anipose_toml,
    save_calibration,
    save_flydra_xml,
    save_pymvg_json,
)


def _rig() -> dict[str, Camera]:
    cams = {}
    for i, ang in enumerate(np.linspace(0, 2 * np.pi, 4, endpoint=False)):
        pos = (1.5 * np.cos(ang), 1.5 * np.sin(ang), 0.8 + 0.1 * i)
        c = Camera.look_at(f"cam{i}", pos, (0.0, 0.0, 0.2), 1280, 1024, 1100.0 + 20 * i,
                           dist=(-0.21 + 0.01 * i, 0.07, 1e-3, -5e-4, 0.01 * i))
        c.K[0, 2] += 7.3 * i
        c.K[1, 1] *= 1.002
        cams[c.name] = c
    return cams


def _points(n: int = 400) -> np.ndarray:
    rng = np.random.default_rng(1)
    return rng.uniform([-0.3, -0.3, 0.0], [0.3, 0.3, 0.4], size=(n, 3))


def _max_diff(a: dict[str, Camera], b: dict[str, Camera]) -> float:
    X = _points()
    assert list(a) == list(b)
    return max(float(np.nanmax(np.abs(a[k].project(X) - b[k].project(X)))) for k in a)


@pytest.mark.parametrize("suffix", [".xml", ".json", ".toml"])
def test_round_trip_same_projections(tmp_path: Path, suffix: str) -> None:
    cams = _rig()
    p1, p2 = tmp_path / f"a{suffix}", tmp_path / f"b{suffix}"
    save_calibration(cams, p1)
    once = load_calibration(p1)
    save_calibration(once, p2)
    twice = load_calibration(p2)
    assert _max_diff(cams, once) < 1e-9
    assert _max_diff(once, twice) < 1e-9
    for k in cams:
        assert np.allclose(once[k].center, cams[k].center, atol=1e-12)
        assert (once[k].width, once[k].height) == (1280, 1024)


def test_flydra_xml_layout(tmp_path: Path) -> None:
    p = tmp_path / "cal.xml"
    save_flydra_xml(_rig(), p)
    text = p.read_text()
    for tag in ("multi_camera_reconstructor", "single_camera_calibration", "cam_id", "calibration_matrix",
                "resolution", "non_linear_parameters", "fc1", "cc2", "alpha_c", "fc1p", "k1", "p2"):
        assert f"<{tag}>" in text
    assert detect_format(p) == "flydra-xml"


# A file in flydra's own layout (as pymvg's test data shows it): no k3, 2-digit-ish formatting.
FLYDRA_NO_DIST = """  <multi_camera_reconstructor>
    <single_camera_calibration>
      <cam_id>theta: 0</cam_id>
      <calibration_matrix>3.000000e+02  3.200000e+02  0.000000e+00  0.000000e+00;  0.000000e+00  2.400000e+02 \
-3.000000e+02  1.500000e+03;  0.000000e+00  1.000000e+00  0.000000e+00  0.000000e+00</calibration_matrix>
      <resolution>640 480</resolution>
      <non_linear_parameters>
        <fc1>300.0</fc1><fc2>300.0</fc2><cc1>320.0</cc1><cc2>240.0</cc2>
        <k1>0.0</k1><k2>0.0</k2><p1>0.0</p1><p2>0.0</p2><alpha_c>0.0</alpha_c>
      </non_linear_parameters>
    </single_camera_calibration>
    <minimum_eccentricity>1.4</minimum_eccentricity>
  </multi_camera_reconstructor>
"""


def test_flydra_external_file_projects_like_P(tmp_path: Path) -> None:
    p = tmp_path / "ext.xml"
    p.write_text(FLYDRA_NO_DIST)
    cams = load_calibration(p)
    cam = cams["theta: 0"]
    P = np.array([[300, 320, 0, 0], [0, 240, -300, 1500], [0, 1, 0, 0]], dtype=float)
    X = _points() + np.array([0, 5.0, 0])
    Xh = np.hstack([X, np.ones((len(X), 1))]) @ P.T
    assert np.allclose(cam.project(X), Xh[:, :2] / Xh[:, 2:], atol=1e-9)
    assert np.isclose(np.linalg.det(cam.R), 1.0)


def test_flydra_scale_factor(tmp_path: Path) -> None:
    cams = _rig()
    mm = {}
    for k, c in cams.items():  # the same rig in millimetres
        mm[k] = Camera(name=k, width=c.width, height=c.height, K=c.K, R=c.R, t=c.t * 1000.0, dist=c.dist)
    p = tmp_path / "mm.xml"
    save_flydra_xml(mm, p)
    text = p.read_text().replace("</resolution>", "</resolution><scale_factor>0.001</scale_factor>")
    p.write_text(text)
    assert _max_diff(cams, load_flydra_xml(p)) < 1e-9


def test_flydra_nonsimple_intrinsics_warn(tmp_path: Path) -> None:
    p = tmp_path / "a.xml"
    save_flydra_xml(_rig(), p)
    p.write_text(p.read_text().replace("<fc1p>", "<fc1p>1").replace("<cc1p>", "<cc1p>1"))
    warns: list[str] = []
    load_flydra_xml(p, warnings=warns)
    assert len(warns) == 4 and "differ" in warns[0]


def test_pymvg_external_layout(tmp_path: Path) -> None:
    p = tmp_path / "sys.json"
    p.write_text("""{ "__pymvg_file_version__": "1.0", "camera_system": [ {"name": "cam1", "width": 640,
      "height": 480, "P": [[320, 0, 320, 0], [0, 320, 240, 0], [0, 0, 1, 0]],
      "K": [[320, 0, 320], [0, 320, 240], [0, 0, 1]], "D": [0.2, 0.3, 0.1, 0.1, 0.1],
      "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "rotation": [[-1, 0, 0], [0, 1, 0], [0, 0, -1]],
      "translation": [0, 0, 0.9]}]}""")
    cam = load_calibration(p)["cam1"]
    assert np.allclose(cam.dist, [0.2, 0.3, 0.1, 0.1, 0.1])
    assert np.allclose(cam.center, [0, 0, 0.9])


def test_opencv_yaml_single_and_multi(tmp_path: Path) -> None:
    import cv2

    cams = _rig()
    c = cams["cam1"]
    p = tmp_path / "cam1.yaml"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", c.width)
    fs.write("image_height", c.height)
    fs.write("camera_matrix", c.K)
    fs.write("distortion_coefficients", c.dist.reshape(1, 5))
    fs.write("R", c.R)
    fs.write("T", c.t.reshape(3, 1))
    fs.release()
    got = load_calibration(p)
    assert list(got) == ["cam1"]
    assert _max_diff({"cam1": c}, got) < 1e-6

    p2 = tmp_path / "rig.yml"
    fs = cv2.FileStorage(str(p2), cv2.FILE_STORAGE_WRITE)
    for name, c in cams.items():
        fs.startWriteStruct(name, cv2.FILE_NODE_MAP)
        fs.write("camera_matrix", c.K)
        fs.write("dist_coeffs", c.dist)
        rvec, _ = cv2.Rodrigues(c.R)
        fs.write("rvec", rvec)
        fs.write("tvec", c.t)
        fs.write("image_size", np.array([c.width, c.height], dtype=float))
        fs.endWriteStruct()
    fs.release()
    assert _max_diff(cams, load_calibration(p2)) < 1e-6


def test_anipose_toml_layout(tmp_path: Path) -> None:
    import tomllib

    p = tmp_path / "calibration.toml"
    save_anipose_toml(_rig(), p)
    doc = tomllib.loads(p.read_text())
    assert set(doc["cam_0"]) >= {"name", "size", "matrix", "distortions", "rotation", "translation"}
    assert detect_format(p) == "anipose-toml"


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        ("", "empty"),
        ("<multi_camera_reconstructor><single_camera_calibration>", "not well-formed"),
        ("<foo/>", "no <multi_camera_reconstructor>"),
        ("<multi_camera_reconstructor/>", "no <single_camera_calibration>"),
        ("<multi_camera_reconstructor><single_camera_calibration><cam_id>a</cam_id>"
         "<calibration_matrix>1 2 3; 4 5 6</calibration_matrix><resolution>640 480</resolution>"
         "</single_camera_calibration></multi_camera_reconstructor>", "not 3x4"),
        ("<multi_camera_reconstructor><single_camera_calibration><cam_id>a</cam_id>"
         "<calibration_matrix>1 0 0 0; 0 1 0 0; 0 0 0 1</calibration_matrix><resolution>640 480</resolution>"
         "</single_camera_calibration></multi_camera_reconstructor>", "singular"),
        ("<multi_camera_reconstructor><single_camera_calibration><cam_id>a</cam_id>"
         "<calibration_matrix>1 0 0 0; 0 1 0 0; 0 0 1 nan</calibration_matrix><resolution>640 480</resolution>"
         "</single_camera_calibration></multi_camera_reconstructor>", "NaN"),
        ('{"camera_system": [{"name": "a"}]}', "lacks"),
        ('{"camera_system": ', "not valid JSON"),
        ("[cam_0]\nname = 'a'\n", "lacks"),
        ("[cam_0\n", "not valid TOML"),
        ("hello world", "not a calibration format"),
    ],
)
def test_malformed_files_give_clear_errors(tmp_path: Path, content: str, needle: str) -> None:
    p = tmp_path / "bad.cal"
    p.write_text(content)
    with pytest.raises(CalibrationFormatError, match=needle) as info:
        load_calibration(p)
    assert str(p) in str(info.value)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(CalibrationFormatError, match="no such file"):
        load_calibration(tmp_path / "nope.xml")


def test_save_unknown_suffix(tmp_path: Path) -> None:
    with pytest.raises(CalibrationFormatError, match="suffix"):
        save_calibration(_rig(), tmp_path / "x.dat")


def test_pymvg_writer_keys(tmp_path: Path) -> None:
    import json

    p = tmp_path / "c.json"
    save_pymvg_json(_rig(), p)
    doc = json.loads(p.read_text())
    assert doc["__pymvg_file_version__"] == "1.0"
    assert set(doc["camera_system"][0]) == {"name", "width", "height", "P", "K", "D", "R", "Q",
                                            "translation"}
