"""Refraction at a flat interface (refraction.py) and its use by the camera, the XML files and the tracker."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from flytrack_host.geometry.camera import Camera, triangulate
from flytrack_host.geometry.formats import CalibrationFormatError, load_flydra_xml, save_calibration, save_flydra_xml
from flytrack_host.geometry.refraction import (
    FlatInterface,
    refract,
    refraction_point,
    refraction_point_jacobian,
    trace_rays,
    triangulate_rays,
)
from flytrack_host.tracking.evaluation import score_frames
from flytrack_host.tracking.observation import CameraArray
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.synthetic import make_scenario
from flytrack_host.tracking.tracker import Tracker

INTERFACES = [
    FlatInterface.water_surface(),  # Braid's <water>
    FlatInterface((0.2, 0.0, 0.0), (1.0, 0.0, 0.0), n_far=1.333),  # a vertical tank wall, camera at +x
    FlatInterface((0.0, 0.1, -0.05), (0.3, -0.2, 1.0), n_far=1.5, n_near=1.1),  # tilted, odd indices
]


def _scene(iface: FlatInterface, n: int = 200, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A camera centre 0.6-1 m on the near side and points 1-40 cm beyond the plane, spread sideways."""
    rng = np.random.default_rng(seed)
    nrm, p0 = np.asarray(iface.normal), np.asarray(iface.point)
    a = np.cross(nrm, [0.3, 0.7, 0.1])
    a /= np.linalg.norm(a)
    b = np.cross(nrm, a)
    C = p0 + 0.8 * nrm + 0.1 * a
    X = p0 + (-rng.uniform(0.01, 0.4, n))[:, None] * nrm + rng.uniform(-0.5, 0.5, (n, 1)) * a
    X += rng.uniform(-0.5, 0.5, (n, 1)) * b
    return C, X


@pytest.mark.parametrize("iface", INTERFACES)
def test_refraction_point_obeys_snell(iface: FlatInterface) -> None:
    C, X = _scene(iface)
    S = refraction_point(C, X, iface)
    n = np.asarray(iface.normal)
    assert np.abs(iface.height(S)).max() < 1e-12  # on the plane
    u1 = (S - C) / np.linalg.norm(S - C, axis=1, keepdims=True)
    u2 = (X - S) / np.linalg.norm(X - S, axis=1, keepdims=True)
    sin1 = np.linalg.norm(np.cross(u1, n), axis=1)
    sin2 = np.linalg.norm(np.cross(u2, n), axis=1)
    assert np.abs(iface.n_near * sin1 - iface.n_far * sin2).max() < 1e-12  # Snell's law
    assert np.abs(np.cross(u1, u2) @ n).max() < 1e-12  # in the plane of incidence
    assert sin1.max() > 0.3  # the scene has steep rays, not just near-normal ones
    # Forward: the air ray to S continues as the refracted ray to X.
    o, t = trace_rays(np.broadcast_to(C, X.shape), u1, iface)
    assert np.abs(o - S).max() < 1e-12 and np.abs(t - u2).max() < 1e-12
    # Points on the camera's side are not refracted: NaN from refraction_point (callers skip them).
    assert np.isnan(refraction_point(C, C + 0.1 * n, iface)).all()


def test_total_internal_reflection_and_misses_are_nan() -> None:
    iface = FlatInterface((0, 0, 0), (0, 0, 1.0), n_far=1.0, n_near=1.5)  # from glass into air
    steep = refract(np.array([np.sin(0.9), 0.0, -np.cos(0.9)]), iface)  # 52 deg > critical 41.8 deg
    assert np.isnan(steep).all()
    assert np.isfinite(refract(np.array([np.sin(0.5), 0.0, -np.cos(0.5)]), iface)).all()
    S, _ = trace_rays(np.array([0, 0, 1.0]), np.array([0, 0, 1.0]), FlatInterface.water_surface())  # away
    assert np.isnan(S).all()


@pytest.mark.parametrize("iface", INTERFACES)
def test_refraction_point_jacobian_matches_numeric(iface: FlatInterface) -> None:
    C, X = _scene(iface, 50, seed=1)
    J = refraction_point_jacobian(C, X, refraction_point(C, X, iface), iface)
    h = 1e-6
    Jn = np.stack([(refraction_point(C, X + h * e, iface) - refraction_point(C, X - h * e, iface)) / (2 * h)
                   for e in np.eye(3)], axis=-1)
    assert np.abs(J - Jn).max() < 1e-7 and np.abs(J).max() > 0.1


def _water_rig() -> list[Camera]:
    w = FlatInterface.water_surface()
    return [
        Camera.look_at("a", [0.3, -0.4, 0.9], [0, 0, -0.2], 640, 480, 700, dist=(-0.1, 0.02, 1e-3, -5e-4, 0),
                       interface=w),
        Camera.look_at("b", [-0.6, 0.2, 0.8], [0, 0, -0.2], 640, 480, 650, interface=w),
        Camera.look_at("c", [0.5, 0.6, 0.7], [0, 0, -0.2], 800, 600, 800, dist=(-0.05, 0, 0, 0, 0), interface=w),
        Camera.look_at("d", [0.0, 0.05, 1.2], [0, 0, -0.2], 640, 480, 600, interface=w),
    ]


def test_camera_projects_backprojects_and_triangulates_through_water() -> None:
    cams = _water_rig()
    rng = np.random.default_rng(2)
    X = rng.uniform([-0.15, -0.15, -0.35], [0.15, 0.15, -0.02], (30, 3))
    for cam in cams:
        uv = cam.project(X)
        assert cam.in_view(X).all()
        o, d = cam.refracted_rays(uv)  # the refracted line through each pixel passes through its point
        s = np.einsum("ij,ij->i", X - o, d)
        assert np.linalg.norm(o + s[:, None] * d - X, axis=1).max() < 1e-9
        assert np.abs(o[:, 2]).max() < 1e-12
        for x in X[:5]:  # analytic Jacobian through distortion and refraction
            uv0, J = cam.project_jacobian(x)
            h = 1e-6
            Jn = np.stack([(cam.project(x + h * e)[0] - cam.project(x - h * e)[0]) / (2 * h) for e in np.eye(3)],
                          axis=1)
            assert np.abs(uv0 - cam.project(x)[0]).max() < 1e-9
            assert np.abs(J - Jn).max() < 1e-4 * np.abs(J).max()
    for x in X:
        got = triangulate(cams, [c.project_undistorted(x)[0] for c in cams])
        assert np.linalg.norm(got - x) < 1e-9
    # Ignoring the water would put the points millimetres to centimetres off: the model matters.
    plain = [Camera(c.name, c.width, c.height, c.K, c.R, c.t, c.dist) for c in cams]
    off = [np.linalg.norm(triangulate(plain, [c.project_undistorted(x)[0] for c in cams]) - x) for x in X]
    assert min(off) > 1e-3
    # Least-squares lines: exact for consistent lines, NaN for parallel ones.
    o = np.array([[0, 0, 0], [1, 0, 0.0]])
    assert np.allclose(triangulate_rays(o, np.array([[1, 1, 0], [-1, 1, 0.0]])), [0.5, 0.5, 0])
    assert np.isnan(triangulate_rays(o, np.array([[0, 1, 0], [0, 1, 0.0]]))).all()


def test_camera_array_matches_camera_for_a_mixed_rig() -> None:
    cams = _water_rig()
    cams[1] = Camera.look_at("b", [-0.6, 0.2, 0.8], [0, 0, -0.2], 640, 480, 650)  # this one ignores water
    arr = CameraArray(dict(enumerate(cams)))
    assert arr.refractive
    X = np.array([[0.05, -0.02, -0.1], [-0.1, 0.1, -0.3], [0.0, 0.0, 0.05]])  # the last above the water
    uv, J, front = arr.project_jacobian(X)
    assert front.all()
    for s, cam in enumerate(cams):
        for k, x in enumerate(X):
            u_ref, J_ref = cam.project_jacobian(x)
            assert np.abs(uv[s, k] - u_ref).max() < 1e-9
            assert np.abs(J[s, k] - J_ref).max() < 1e-9
        ideal, fr = arr.project_ideal(np.full(len(X), s), X)
        assert fr.all() and np.abs(ideal - cam.project_undistorted(X)).max() < 1e-9
        # The lines hold the points beyond the plane (the tracker's targets are all in the water).
        o, d = arr.ray_lines(np.full(2, s), ideal[:2, 0], ideal[:2, 1])
        t = np.einsum("ij,ij->i", X[:2] - o, d) / np.einsum("ij,ij->i", d, d)
        assert np.linalg.norm(o + t[:, None] * d - X[:2], axis=1).max() < 1e-9
    allp, fr = arr.project_ideal_all(X)
    assert fr.all() and np.abs(allp[:, 2] - cams[2].project_undistorted(X)).max() < 1e-9


def test_water_in_flydra_xml_round_trip(tmp_path) -> None:  # noqa: ANN001
    cams = {c.name: c for c in _water_rig()}
    p = tmp_path / "water.xml"
    save_flydra_xml(cams, p)
    assert "<water>1.333</water>" in p.read_text()
    back = load_flydra_xml(p)
    X = np.array([[0.05, -0.02, -0.1], [-0.1, 0.1, -0.3]])
    for name, cam in cams.items():
        assert back[name].interface == FlatInterface.water_surface(1.333)
        assert np.abs(back[name].project(X) - cam.project(X)).max() < 1e-6
    # Without <water> the cameras see straight lines.
    p.write_text(p.read_text().replace("<water>1.333</water>", ""))
    assert all(c.interface is None for c in load_flydra_xml(p).values())
    end = "</multi_camera_reconstructor>"
    p.write_text(p.read_text().replace(end, "<water>wet</water>" + end))
    with pytest.raises(CalibrationFormatError, match="not a refractive index"):
        load_flydra_xml(p)
    # Formats with no place for refraction refuse rather than drop it; so does XML for a tank wall.
    with pytest.raises(CalibrationFormatError, match="no place for refraction"):
        save_calibration(cams, tmp_path / "w.json")
    wall = {"s": Camera.look_at("s", [1.0, 0, 0], [0, 0, 0], 640, 480, 600, interface=INTERFACES[1])}
    with pytest.raises(CalibrationFormatError, match="one water surface"):
        save_flydra_xml(wall, tmp_path / "wall.xml")


def test_tracker_follows_fish_under_water_on_the_numpy_path(caplog, monkeypatch) -> None:  # noqa: ANN001
    import flytrack_host.tracking.tracker as tracker_mod

    monkeypatch.setattr(tracker_mod, "_logged", set())  # the reason is logged once per process: as in a fresh one
    water = FlatInterface.water_surface(1.333, z=0.3)  # the arena's top is the surface
    sc = make_scenario(n_cameras=5, n_targets=3, duration_s=3.0, noise_px=0.5, p_miss=0.05,
                       false_positives_per_camera=0.3, close_pass_m=None, seed=4, interface=water)
    with caplog.at_level(logging.INFO, logger="flytrack_host.tracking.tracker"):
        tr = Tracker(sc.cameras, TrackingParams(kernel="auto"), sc.frame_period_s)
    assert tr.kernel_path == "numpy"  # the C kernel has no refraction: the tracker says so and falls back
    assert any("refractive interface" in r.getMessage() and r.levelno == logging.WARNING for r in caplog.records)
    with pytest.raises(Exception, match="refractive"):
        Tracker(sc.cameras, TrackingParams(kernel="c"), sc.frame_period_s)
    res = [tr.process(b) for b in sc.bundles]
    s = score_frames(sc.truth, [{e.obj_id: e.state[:3] for e in r.estimates} for r in res])
    print(f"\nunder water: {s.line()}")
    assert s.rmse_mm < 2.0 and s.mota > 0.9
    # The same detections tracked as if there were no water: births fail or the positions are off.
    plain = {i: Camera(c.name, c.width, c.height, c.K, c.R, c.t, c.dist) for i, c in sc.cameras.items()}
    tr2 = Tracker(plain, TrackingParams(kernel="numpy"), sc.frame_period_s)
    res2 = [tr2.process(b) for b in sc.bundles]
    s2 = score_frames(sc.truth, [{e.obj_id: e.state[:3] for e in r.estimates} for r in res2])
    print(f"water ignored: {s2.line()}")
    assert not (s2.rmse_mm < 2.0 and s2.mota > 0.9)


def test_triangulate_rays_leaves_out_a_line_that_is_not_finite():
    from flytrack_host.geometry.refraction import triangulate_rays

    o = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    d = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 1.0], [np.nan, 0.0, 1.0]])
    assert np.allclose(triangulate_rays(o, d), [0.0, 0.0, 1.0])  # the two good lines meet there
    assert np.all(np.isnan(triangulate_rays(o[[0, 2]], d[[0, 2]])))  # one line left: no point


def test_water_matches_flydras_pixels_and_triangulates_within_braids_bound() -> None:
    """Braid's own water test: through its sample calibration, flydra's code projects (0.01, 0.02, -0.03) m,
    3 cm under the surface, to these distorted pixels; Braid asks the point back from them within 1e-5
    relative. flydra and Braid take air as 1.0003 (with 1.0: 5 mpx off, the point 10 um off)."""
    from pathlib import Path

    from flytrack_host.geometry.formats import load_calibration

    cams = load_calibration(Path(__file__).parent / "data" / "braid_sample_calibration_water.xml", [])
    flydra_px = {"Basler_21425994": (324.36365541, 230.81705908), "Basler_21425998": (295.26854971, 180.42595947),
                 "Basler_21426001": (366.88089027, 241.41399229), "Basler_21426006": (248.31394233, 238.94298696)}
    X = np.array([0.01, 0.02, -0.03])
    for name, px in flydra_px.items():
        assert np.max(np.abs(cams[name].project(X[None])[0] - px)) < 1e-6  # measured 5e-9 px
    uv = [cams[n].undistort(np.array([px])) for n, px in flydra_px.items()]
    back = triangulate([cams[n] for n in flydra_px], uv)
    assert np.all(np.abs(back - X) <= 1e-5 * np.abs(X)), back - X  # measured 2e-12 m


def test_braid_water_is_air_of_index_1_0003() -> None:
    w = FlatInterface.water_surface()
    assert w.n_near == 1.0003 and w.n_far == 1.333 and w.is_braid_water
    assert not FlatInterface((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), n_far=1.333).is_braid_water  # air of 1.0
