"""flydra XML read exactly as flydra projects: fc/cc differing from P's K, skew, warnings, convert checks."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from flytrack_host.cli import app
from flytrack_host.geometry.camera import Camera
from flytrack_host.geometry.formats import flydra_projection, load_calibration, load_flydra_xml, save_flydra_xml


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


def _mirrored_rig() -> tuple[list[np.ndarray], np.ndarray]:
    """Three cameras around the origin, and their P in a mirrored world (x -> -x), as MultiCamSelfCal gives
    for Braid's own calibrations (strand-braid's cal-2018-11-13-good.xml, sample_calibration.xml): every real
    point then lies behind every camera by the usual rule, yet flydra projects it into each image."""
    cams = [Camera.look_at(f"c{i}", pos, (0, 0, 0.1), 1280, 1024, 1150.0)
            for i, pos in enumerate([(1.2, -0.9, 0.8), (-1.1, -1.0, 0.9), (0.1, 1.4, 1.0)])]
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    rng = np.random.default_rng(3)
    X = rng.uniform([-0.15, -0.15, 0.0], [0.15, 0.15, 0.25], (200, 3)) * [-1.0, 1.0, 1.0]  # mirrored world
    return [c.P @ mirror for c in cams], X


def test_a_mirrored_world_projects_as_flydra_does(tmp_path: Path) -> None:
    Ps, X = _mirrored_rig()
    nl = {"fc1": 1180.0, "fc2": 1165.0, "cc1": 670.5, "cc2": 492.5, "k1": -0.21, "k2": 0.06, "p1": 8e-4,
          "p2": -4e-4, "alpha_c": 0.0}
    body = "".join(re.search(r"(<single_camera_calibration>.*</single_camera_calibration>)",
                             _xml(P, nl, f"c{i}")).group(1) for i, P in enumerate(Ps))
    p = tmp_path / "mirrored.xml"
    p.write_text(f"<multi_camera_reconstructor>{body}</multi_camera_reconstructor>")
    warns: list[str] = []
    cams = load_flydra_xml(p, warns)
    assert len(warns) == 1 and "mirrored" in warns[0], warns
    for i, P in enumerate(Ps):
        uv = cams[f"c{i}"].project(X)
        assert np.isfinite(uv).all()  # NaN for every point ("behind the camera") before
        assert np.abs(uv - flydra_projection(P, nl, X)).max() < 1e-6
    # flydra XML keeps it exactly; a format of rotations refuses it with one clear line.
    r = CliRunner().invoke(app, ["calibrate", "convert", str(p), str(tmp_path / "back.xml")])
    assert r.exit_code == 0, r.output
    again = load_calibration(tmp_path / "back.xml", [])
    assert np.abs(again["c1"].project(X) - flydra_projection(Ps[1], nl, X)).max() < 1e-6
    r = CliRunner().invoke(app, ["calibrate", "convert", str(p), str(tmp_path / "out.json")])
    assert r.exit_code == 2 and "mirrored" in r.output and "out.json:" in " ".join(r.output.split()), r.output


def test_a_mirrored_world_in_a_flydra_h5_tracks(tmp_path: Path) -> None:
    """A flydra .h5 whose calibration group is a mirrored world: the tracker (both kernels) follows the
    animals there, at the mirror images of their true positions (0 estimates before: every point was
    'behind' every camera)."""
    import h5py

    from flytrack_host.tracking.params import TrackingParams
    from flytrack_host.tracking.synthetic import make_scenario
    from flytrack_host.tracking.tracker import Tracker

    sc = make_scenario(n_cameras=3, n_targets=2, duration_s=0.5, fps=100.0, close_pass_m=None, enter_exit=False,
                       false_positives_per_camera=0.0, seed=4)
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    path = tmp_path / "m.h5"
    with h5py.File(path, "w") as f:
        for i, c in sc.cameras.items():
            f[f"calibration/pmat/cam{i}"] = c.P @ mirror
            f[f"calibration/resolution/cam{i}"] = np.array([c.width, c.height])
    warns: list[str] = []
    by_name = load_calibration(path, warns)
    assert any("mirrored" in w for w in warns), warns
    cams = {i: by_name[f"cam{i}"] for i in sc.cameras}
    for kernel in ("numpy", "auto"):
        tr = Tracker(cams, TrackingParams(kernel=kernel), sc.frame_period_s)
        errs = []
        for b, truth in zip(sc.bundles, sc.truth, strict=True):
            for e in tr.process(b).estimates:
                pos = e.state[:3] * [-1.0, 1.0, 1.0]  # back from the mirrored world
                errs.append(min(np.linalg.norm(pos - t) for t in truth.values()))
        assert len(errs) > 80, (kernel, len(errs))
        assert np.median(errs) < 0.002, (kernel, np.median(errs))
