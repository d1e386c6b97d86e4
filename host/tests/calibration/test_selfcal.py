"""LED self-calibration on synthetic rigs, DLT, alignment, and the bad-input paths (library and CLI)."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from flytrack_host.calibration.align import AlignError, align_cameras, umeyama
from flytrack_host.calibration.bundle import bundle_adjust
from flytrack_host.calibration.dlt import DLTError, dlt_camera
from flytrack_host.calibration.evaluate import centre_error, reprojection_error
from flytrack_host.calibration.observations import Observations, load_points, save_points
from flytrack_host.calibration.selfcal import SelfCalError, self_calibrate
from flytrack_host.calibration.synthetic import make_rig, observe, synthetic_rig
from flytrack_host.geometry.camera import Camera


@pytest.mark.parametrize(("n_cams", "seed", "focal_error", "init"),
                         [(4, 0, 1.1, "factorization"), (6, 1, 0.9, "factorization"), (4, 2, 1.1, "pairwise")])
def test_selfcal_reaches_noise_floor_and_true_centres(n_cams: int, seed: int, focal_error: float, init: str) -> None:
    # 3000 LED frames, 0.5 px noise, 30 % missing views, 2 % gross outliers, radial distortion.
    rig = synthetic_rig(n_cams, n_points=3000, seed=seed)
    focal = {k: c.K[0, 0] * focal_error for k, c in rig.cameras.items()}
    res = self_calibrate(rig.obs, focal_px=focal, seed=seed, init=init)
    assert res.init_method == init
    truth_inliers = ~rig.outlier
    floor = reprojection_error(rig.cameras, rig.obs, truth_inliers)  # the true cameras' own error
    ours = reprojection_error(res.cameras, rig.obs, truth_inliers)
    # Measured (Schur bundle adjustment, converged): 0.9983, 0.9979, 0.9979 of the floor (the fit absorbs a
    # little of the noise); centres 6.24, 2.96, 5.45 mm; outliers kept 0, 0, 0.6 %; inliers kept 96.7-99.6 %.
    assert abs(ours / floor - 1.0) < 0.005, (ours, floor)
    # After a similarity onto the true centres, every centre within 7.5 mm (the arena is 1 m).
    assert centre_error(res.cameras, rig.cameras) < 0.0075 * rig.arena_size
    # Gross outliers are rejected, and few good detections are.
    assert np.mean(res.inlier[rig.outlier]) < 0.01
    assert np.mean(res.inlier[truth_inliers]) > 0.95


def test_points_file_round_trip(tmp_path: Path) -> None:
    rig = synthetic_rig(3, n_points=200)
    for name in ("p.csv", "p.npz"):
        save_points(rig.obs, tmp_path / name)
        back = load_points(tmp_path / name)
        assert back.camera_names == rig.obs.camera_names and back.sizes == rig.obs.sizes
        assert np.array_equal(back.frame, rig.obs.frame) and np.array_equal(back.cam, rig.obs.cam)
        assert np.array_equal(back.uv, rig.obs.uv)


def test_too_few_points() -> None:
    rig = synthetic_rig(4, n_points=20)
    with pytest.raises(SelfCalError, match="too few points"):
        self_calibrate(rig.obs)


def test_camera_with_no_points() -> None:
    rig = synthetic_rig(4, n_points=300)
    obs = rig.obs.subset(rig.obs.cam != 2)
    with pytest.raises(SelfCalError, match="cam3 have no points"):
        self_calibrate(obs)


@pytest.mark.parametrize("shape", ["planar", "collinear"])
def test_degenerate_led_path(shape: str) -> None:
    cams = make_rig(4)
    s = np.linspace(0, 1, 600)
    if shape == "planar":
        pts = np.stack([0.4 * np.sin(13 * s), 0.4 * np.cos(7 * s), np.full_like(s, 0.5)], axis=1)
    else:
        pts = np.stack([0.8 * s - 0.4, 0.3 * s - 0.15, 0.2 + 0.6 * s], axis=1)
    obs, _ = observe(cams, pts, outliers=0.0)
    with pytest.raises(SelfCalError, match=shape):
        self_calibrate(obs, focal_px={k: c.K[0, 0] for k, c in cams.items()})


def test_dlt_recovers_camera() -> None:
    cam = make_rig(1)["cam1"]
    cam.dist[:] = 0
    X = np.random.default_rng(0).uniform(-0.4, 0.4, (12, 3)) + [0, 0, 0.5]
    uv = cam.project(X) + np.random.default_rng(1).normal(0, 0.1, (12, 2))
    got, err = dlt_camera("cam1", X, uv, cam.width, cam.height)
    assert err < 0.3
    assert np.linalg.norm(got.center - cam.center) < 0.01


def test_dlt_bad_input() -> None:
    with pytest.raises(DLTError, match="at least 6"):
        dlt_camera("a", np.zeros((5, 3)), np.zeros((5, 2)), 10, 10)
    X = np.c_[np.random.default_rng(0).uniform(size=(10, 2)), np.zeros(10)]
    with pytest.raises(DLTError, match="coplanar"):
        dlt_camera("a", X, np.random.default_rng(1).uniform(size=(10, 2)), 10, 10)


def test_umeyama_and_camera_alignment() -> None:
    cams = make_rig(4)
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    X = rng.uniform(-1, 1, (20, 3))
    Y = 2.5 * X @ R.T + [1, 2, 3]
    sim = umeyama(X, Y)
    assert np.isclose(sim.s, 2.5) and np.allclose(sim.R, R) and np.allclose(sim.apply(X), Y)
    moved = align_cameras(cams, sim)
    for k in cams:  # a moved camera sees the moved points exactly where the original saw the originals
        assert np.allclose(moved[k].project(sim.apply(X)), cams[k].project(X), atol=1e-9, equal_nan=True)
    with pytest.raises(AlignError, match="at least 3"):
        umeyama(X[:2], Y[:2])
    with pytest.raises(AlignError, match="collinear"):
        umeyama(np.outer(np.arange(5), [1, 1, 1]), np.outer(np.arange(5), [1, 0, 0]))


def _run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    # A guard against a hang, not a speed bound: `calibrate selfcal ... --plot` took over 120 s at
    # load 10 (TimeoutExpired in test_cli_selfcal_align_convert); pytest's own timeout is 600 s.
    return subprocess.run([sys.executable, "-m", "flytrack_host.cli", "calibrate", *args],
                          capture_output=True, text=True, timeout=540)


def test_cli_bad_inputs_give_one_paragraph(tmp_path: Path) -> None:
    bad_xml = tmp_path / "bad.xml"
    bad_xml.write_text("<multi_camera_reconstructor>")
    r = _run_cli("convert", str(bad_xml), str(tmp_path / "o.json"))
    assert r.returncode == 2 and "not well-formed XML" in r.stderr and "Traceback" not in r.stderr
    rig = synthetic_rig(3, n_points=15)
    pts = tmp_path / "few.csv"
    save_points(rig.obs, pts)
    r = _run_cli("selfcal", str(pts), "-o", str(tmp_path / "c.xml"))
    assert r.returncode == 2 and "too few points" in r.stderr and "Traceback" not in r.stderr
    bad_csv = tmp_path / "bad.csv"
    bad_csv.write_text("# camera a 10 10\nframe,camera,u,v\n1,b,2,3\n")
    r = _run_cli("selfcal", str(bad_csv), "-o", str(tmp_path / "c.xml"))
    assert r.returncode == 2 and "not declared" in r.stderr
    save_points(synthetic_rig(3, n_points=200).obs, pts)
    r = _run_cli("selfcal", str(pts), "-o", str(tmp_path / "c.xml"), "--init", "svd")
    assert r.returncode == 2 and "initialisation 'svd' unknown" in r.stderr
    pairs = tmp_path / "pairs.csv"
    pairs.write_text("camera,x,y,z,u,v\n")
    r = _run_cli("dlt", str(pairs), "--size", "640x480", "-o", str(tmp_path / "d.xml"))
    assert r.returncode == 2 and "expected NAME=WIDTHxHEIGHT" in r.stderr and "Traceback" not in r.stderr


def test_factorization_needs_three_cameras() -> None:
    rig = synthetic_rig(2, n_points=400)
    with pytest.raises(SelfCalError, match="3 or more cameras"):
        self_calibrate(rig.obs)


def test_cli_selfcal_align_convert(tmp_path: Path) -> None:
    rig = synthetic_rig(4, n_points=1500, seed=3)
    pts = tmp_path / "pts.npz"
    save_points(rig.obs, pts)
    centres = tmp_path / "centres.csv"
    centres.write_text("camera,x,y,z\n" + "".join(f"{k},{c.center[0]},{c.center[1]},{c.center[2]}\n"
                                                  for k, c in rig.cameras.items()))
    r = _run_cli("selfcal", str(pts), "-o", str(tmp_path / "raw.xml"), "--focal", "1000",
                 "--plot", str(tmp_path / "p.png"))
    assert r.returncode == 0, r.stderr
    assert "(factorization start)" in r.stdout
    assert "mean reprojection error" in r.stdout and (tmp_path / "p.png").stat().st_size > 10000
    r = _run_cli("align", str(tmp_path / "raw.xml"), "--centres", str(centres), "-o", str(tmp_path / "w.json"))
    assert r.returncode == 0, r.stderr
    from flytrack_host.geometry.formats import load_calibration

    world = load_calibration(tmp_path / "w.json")
    for k, c in rig.cameras.items():
        assert np.linalg.norm(world[k].center - c.center) < 0.02 * rig.arena_size


def test_collect_over_udp_keeps_single_point_frames() -> None:
    from flytrack_host.calibration.collect import Collector
    from flytrack_host.protocol import FeatureFrame, encode_features
    from flytrack_host.protocol.udp import make_points

    col = Collector(["a", "b"], [(640, 480), (640, 480)])
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(2.0)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sent = []
    for frame in range(5):
        for cam in (0, 1):
            n = 2 if (frame == 3 and cam == 1) else 1
            pts = make_points(n)
            pts["x_dist"] = 100 + frame
            pts["y_dist"] = 50 + cam
            msg = FeatureFrame(camera_index=cam, seq=frame, camera_frame=frame, trigger_frame=frame,
                               total_points=n, points=pts)
            for d in encode_features(msg):
                tx.sendto(d, rx.getsockname())
                sent.append(d)
    tx.sendto(b"garbage", rx.getsockname())
    for _ in range(len(sent) + 1):
        col.add_datagram(rx.recv(2048))
    rx.close()
    tx.close()
    obs: Observations = col.observations()
    assert len(obs.frame) == 9 and col.rejected_multi == 1 and col.bad_datagrams == 1
    assert np.allclose(obs.uv[obs.cam == 0][:, 0], [100, 101, 102, 103, 104])


def _board_intrinsics(rig_cams: dict[str, Camera], names: list[str], seed: int = 5) -> dict[str, Camera]:
    """The true intrinsics with a board calibration's realistic error: 0.1 % in fx and fy, 0.5 px in cx, cy."""
    rng = np.random.default_rng(seed)
    out = {}
    for n in names:
        c = rig_cams[n]
        K = c.K.copy()
        K[0, 0] *= 1 + rng.choice([-1, 1]) * 0.001
        K[1, 1] *= 1 + rng.choice([-1, 1]) * 0.001
        K[:2, 2] += rng.choice([-0.5, 0.5], 2)
        out[n] = Camera(n, c.width, c.height, K, np.eye(3), np.zeros(3), c.dist.copy())
    return out


def test_board_intrinsics_are_held_fixed() -> None:
    # 4 cameras, 1500 LED frames, 0.5 px noise, 30 % missing, 2 % outliers; a board file for every camera.
    rig = synthetic_rig(4, n_points=1500, seed=0)
    intr = _board_intrinsics(rig.cameras, list(rig.cameras))
    truth_inliers = ~rig.outlier
    floor = reprojection_error(rig.cameras, rig.obs, truth_inliers)
    free = self_calibrate(rig.obs, seed=0)
    fixed = self_calibrate(rig.obs, intrinsics=intr, seed=0)
    for n, c in fixed.cameras.items():
        assert np.array_equal(c.K, intr[n].K) and np.array_equal(c.dist, intr[n].dist), n
    r_fixed = reprojection_error(fixed.cameras, rig.obs, truth_inliers) / floor
    r_free = reprojection_error(free.cameras, rig.obs, truth_inliers) / floor
    print(f"\nreprojection / noise floor: fixed {r_fixed:.4f}, free {r_free:.4f}")
    # The README says "within 3 % of the noise floor in each case": this is that check.
    assert abs(r_fixed - 1.0) < 0.03 and abs(r_free - 1.0) < 0.03
    assert centre_error(fixed.cameras, rig.cameras) <= centre_error(free.cameras, rig.cameras)
    assert centre_error(fixed.cameras, rig.cameras) < 0.01 * rig.arena_size
    # --refine-intrinsics: the file is only a start, the bundle adjustment moves K (the old behaviour).
    refined = self_calibrate(rig.obs, intrinsics=intr, seed=0, refine_intrinsics=True)
    assert all(not np.array_equal(c.K, intr[n].K) for n, c in refined.cameras.items())
    r_refined = reprojection_error(refined.cameras, rig.obs, truth_inliers) / floor
    print(f"reprojection / noise floor: refined {r_refined:.4f}")
    size = rig.arena_size
    print(f"camera-centre error / arena size: fixed {centre_error(fixed.cameras, rig.cameras) / size:.4f}, "
          f"refined {centre_error(refined.cameras, rig.cameras) / size:.4f}, "
          f"free {centre_error(free.cameras, rig.cameras) / size:.4f}")
    # The README's figures (measured 0.0008, 0.0058, 0.0054): the file held fixed places the cameras best.
    assert centre_error(fixed.cameras, rig.cameras) < 0.0015 * size
    assert centre_error(refined.cameras, rig.cameras) < 0.007 * size
    assert centre_error(free.cameras, rig.cameras) < 0.007 * size
    assert abs(r_refined - 1.0) < 0.03
    assert centre_error(refined.cameras, rig.cameras) < 0.01 * rig.arena_size


@pytest.mark.parametrize("init", ["factorization", "pairwise"])
def test_board_intrinsics_for_some_cameras_fix_only_those(init: str) -> None:
    rig = synthetic_rig(4, n_points=1500, seed=0)
    intr = _board_intrinsics(rig.cameras, ["cam1", "cam3"])
    focal = {k: c.K[0, 0] * 1.1 for k, c in rig.cameras.items()}
    res = self_calibrate(rig.obs, focal_px=focal, intrinsics=intr, seed=0, init=init)
    for n in ("cam1", "cam3"):
        assert np.array_equal(res.cameras[n].K, intr[n].K) and np.array_equal(res.cameras[n].dist, intr[n].dist)
    for n in ("cam2", "cam4"):  # refined from the LED data, close to the truth
        assert not np.array_equal(res.cameras[n].K, res.initial_cameras[n].K)
        assert abs(res.cameras[n].K[0, 0] / rig.cameras[n].K[0, 0] - 1) < 0.01
    floor = reprojection_error(rig.cameras, rig.obs, ~rig.outlier)
    assert abs(reprojection_error(res.cameras, rig.obs, ~rig.outlier) / floor - 1.0) < 0.2
    assert centre_error(res.cameras, rig.cameras) < 0.01 * rig.arena_size


def test_bundle_holds_only_the_named_cameras_intrinsics() -> None:
    rig = synthetic_rig(3, n_points=300, noise_px=0.3, outliers=0.0, seed=4)
    cams = list(rig.cameras.values())
    frames, inv = rig.obs.point_index()
    start = [Camera(c.name, c.width, c.height, c.K * [[1.02], [1.02], [1]], c.R, c.t, c.dist) for c in cams]
    res = bundle_adjust(start, rig.points[frames], rig.obs.cam, inv, rig.obs.uv, fixed_intrinsics={"cam2", "nope"},
                        max_nfev=5)
    assert np.array_equal(res.cameras[1].K, start[1].K) and np.array_equal(res.cameras[1].dist, start[1].dist)
    assert not np.array_equal(res.cameras[0].K, start[0].K) and not np.array_equal(res.cameras[2].K, start[2].K)


def test_cli_refine_intrinsics(tmp_path: Path) -> None:
    from flytrack_host.geometry.formats import load_calibration, save_calibration

    rig = synthetic_rig(4, n_points=800, seed=3)
    pts = tmp_path / "pts.npz"
    save_points(rig.obs, pts)
    intr = _board_intrinsics(rig.cameras, ["cam2"])
    save_calibration(intr, tmp_path / "intr.json")
    board = load_calibration(tmp_path / "intr.json")["cam2"]
    r = _run_cli("selfcal", str(pts), "-o", str(tmp_path / "a.json"), "--intrinsics", str(tmp_path / "intr.json"))
    assert r.returncode == 0, r.stderr
    assert "held fixed for cam2" in " ".join(r.stdout.split())
    assert np.array_equal(load_calibration(tmp_path / "a.json")["cam2"].K, board.K)
    r = _run_cli("selfcal", str(pts), "-o", str(tmp_path / "b.json"), "--intrinsics", str(tmp_path / "intr.json"),
                 "--refine-intrinsics")
    assert r.returncode == 0, r.stderr
    assert "starting intrinsics from" in r.stdout
    assert not np.array_equal(load_calibration(tmp_path / "b.json")["cam2"].K, board.K)
    r = _run_cli("selfcal", str(pts), "-o", str(tmp_path / "c.json"), "--refine-intrinsics")
    assert r.returncode == 2 and "needs --intrinsics" in r.stderr and "Traceback" not in r.stderr


def test_cameras_that_never_share_a_frame_are_a_clear_error_for_both_initialisations() -> None:
    # 3 cameras, each sees the LED only in frames of its own: no pair can be fitted (one check serves both).
    from flytrack_host.calibration.selfcal import factorization_cameras, initial_cameras

    rng = np.random.default_rng(0)
    n = 40
    obs = Observations(frame=np.arange(3 * n), cam=np.repeat(np.arange(3), n), uv=rng.uniform(50, 600, (3 * n, 2)),
                       camera_names=["a", "b", "c"], sizes=[(640, 480)] * 3)
    for init in (initial_cameras, factorization_cameras):
        with pytest.raises(SelfCalError, match="no pair of cameras shares .* must overlap"):
            init(obs, focal_px=600.0)
