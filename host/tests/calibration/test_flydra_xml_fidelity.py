"""flydra XML read exactly as flydra projects: fc/cc differing from P's K, skew, warnings, convert checks."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from flytrack_host.calibration.formats import flydra_projection, load_calibration, load_flydra_xml, save_flydra_xml
from flytrack_host.camera import Camera
from flytrack_host.cli import app


def _xml(P: np.ndarray, nl: dict[str, float], name: str = "cam1") -> str:
    rows = "; ".join(" ".join(repr(float(v)) for v in r) for r in P)
    tags = "".join(f"<{k}>{v!r}</{k}>" for k, v in nl.items())
    return (f"<multi_camera_reconstructor><single_camera_calibration><cam_id>{name}</cam_id>"
            f"<calibration_matrix>{rows}</calibration_matrix><resolution>1280 1024</resolution>"
            f"<non_linear_parameters>{tags}</non_linear_parameters></single_camera_calibration>"
            "<minimum_eccentricity>1.4</minimum_eccentricity></multi_camera_reconstructor>")


def _P() -> np.ndarray:
    c = Camera.look_at("c", (1.2, -0.9, 0.8), (0, 0, 0.15), 1280, 1024, 1150.0)
    return c.P


def _pts(cam: Camera) -> np.ndarray:
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [1279, 1023], (300, 2))
    c, d = cam.rays(uv)
    return c + d * rng.uniform(0.8, 2.5, (300, 1))


def test_fc_cc_apart_from_Ps_K_is_flydras_normal_case(tmp_path: Path) -> None:
    P = _P()
    # The distortion's K 19-31 px from P's: what the old loader got wrong by that much.
    nl = {"fc1": 1180.0, "fc2": 1165.0, "cc1": 639.5 + 31.0, "cc2": 511.5 - 19.0, "k1": -0.21, "k2": 0.06,
          "p1": 8e-4, "p2": -4e-4, "alpha_c": 0.0}
    p = tmp_path / "f.xml"
    p.write_text(_xml(P, nl))
    warns: list[str] = []
    cam = load_flydra_xml(p, warns)["cam1"]
    assert warns == []  # exact, nothing to warn about
    X = _pts(cam)
    err = np.abs(cam.project(X) - flydra_projection(P, nl, X)).max()
    print(f"\nfc/cc apart from P's K: FlyTrack vs flydra {err:.1e} px")
    assert err < 1e-6
    # Written back, the file keeps flydra's parameters and reprojects the same.
    save_flydra_xml({"cam1": cam}, tmp_path / "g.xml")
    text = (tmp_path / "g.xml").read_text()
    assert float(re.search(r"<cc1>([^<]+)</cc1>", text).group(1)) == pytest.approx(670.5)
    again = load_flydra_xml(tmp_path / "g.xml")["cam1"]
    assert np.abs(again.project(X) - flydra_projection(P, nl, X)).max() < 1e-6


def test_skew_round_trips_exactly(tmp_path: Path) -> None:
    c = Camera.look_at("s", (1.0, 1.0, 0.9), (0, 0, 0.1), 1280, 1024, 1000.0, dist=(-0.2, 0.05, 1e-3, 2e-4, 0.01))
    c.K[0, 1] = 3.3  # skew
    save_flydra_xml({"s": c}, tmp_path / "s.xml")
    warns: list[str] = []
    back = load_flydra_xml(tmp_path / "s.xml", warns)["s"]
    X = _pts(c)
    assert warns == [] and np.abs(back.project(X) - c.project(X)).max() < 1e-9


def test_warnings_reach_the_user_and_convert_refuses_an_inexact_model(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    P = _P()
    nl = {"fc1": 1150.0, "fc2": 1150.0, "cc1": 639.5, "cc2": 511.5, "k1": -0.3, "k2": 0.1, "p1": 0.0, "p2": 0.0,
          "alpha_c": 0.0, "fc1p": 1000.0, "fc2p": 1000.0, "cc1p": 600.0, "cc2p": 480.0}  # flydra's non-simple
    p = tmp_path / "ns.xml"
    p.write_text(_xml(P, nl))
    with caplog.at_level(logging.WARNING):
        load_calibration(p)  # no warnings list given: they are logged, not dropped
    assert any("rectified intrinsics" in r.getMessage() for r in caplog.records)
    fid: dict[str, float] = {}
    load_calibration(p, [], fid)
    assert fid["cam1"] > 0.1
    r = CliRunner().invoke(app, ["calibrate", "convert", str(p), str(tmp_path / "out.xml")])
    assert r.exit_code == 2 and "more than 0.1 px" in " ".join(r.output.split()) and not (tmp_path / "out.xml").exists()
    assert "warning" in r.output
    r = CliRunner().invoke(app, ["calibrate", "convert", str(p), str(tmp_path / "out.xml"), "--force"])
    assert r.exit_code == 0 and (tmp_path / "out.xml").exists()
    # An exact one converts and says how close it is.
    nl2 = {k: v for k, v in nl.items() if not k.endswith("p")}
    p.write_text(_xml(P, nl2))
    r = CliRunner().invoke(app, ["calibrate", "convert", str(p), str(tmp_path / "ok.xml")])
    assert r.exit_code == 0 and "largest difference from the source's projection" in " ".join(r.output.split())


def test_edge_undistortion_with_the_distortion_K_gives_Ps_ideal_pixels() -> None:
    """The edge extractor gets Camera.Kd and the coefficients (one-K undistortion); with flydra's model
    that yields P's ideal pixels, the ones the tracker's rays expect."""
    P = _P()
    base = Camera.from_P("c", P, 1280, 1024)
    Kd = base.K.copy()
    Kd[0, 2] += 27.0
    Kd[1, 2] -= 22.0
    cam = Camera.from_P("c", P, 1280, 1024, dist=(-0.2, 0.05, 1e-3, 2e-4, 0.0), K_dist=Kd)
    edge_model = Camera("c", 1280, 1024, cam.Kd, cam.R, cam.t, cam.dist)  # what the edge is configured with
    X = _pts(cam)
    uv = cam.project(X)
    h = np.hstack([X, np.ones((len(X), 1))]) @ P.T
    assert np.abs(edge_model.undistort(uv) - h[:, :2] / h[:, 2:]).max() < 1e-6
