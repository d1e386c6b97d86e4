"""`flytrack calibrate intrinsics` (checkerboard and ChArUco) on synthetic images seen through a known lens.

The images are rendered with FlyTrack's own camera model, distortion included: for each output pixel the
ray is undistorted with `Camera.undistort`, intersected with the board plane and the board texture sampled
there (cv2.remap), at 2x2 supersampling, then blurred and noised. OpenCV must then recover K and the
distortion it never saw.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from flytrack_host.calibration.intrinsics import Charuco, Checkerboard, IntrinsicsError
from flytrack_host.calibration.observations import save_points
from flytrack_host.calibration.selfcal import initial_cameras
from flytrack_host.calibration.synthetic import led_path, make_rig, observe
from flytrack_host.geometry.camera import Camera
from flytrack_host.geometry.formats import load_calibration, save_calibration

W, H = 640, 480
SS = 2  # supersampling per axis
SQUARE = 0.03  # metres
CHECKER_CORNERS = (9, 6)  # inner corners: 10x7 squares
CHARUCO_SQUARES = (7, 5)
MARKER = 0.022
PX_PER_M = 4000.0  # board texture resolution (120 px a square: finer than the camera ever sees it)


def true_camera() -> Camera:
    K = [[610.0, 0.0, 327.5], [0.0, 604.0, 236.0], [0.0, 0.0, 1.0]]
    return Camera("cam1", W, H, K, np.eye(3), np.zeros(3), dist=[-0.28, 0.09, 0.0008, -0.0006, -0.02])


@dataclass
class Texture:
    img: NDArray[np.uint8]
    origin_px: float  # texture pixel (x and y) of the board's object-point origin


def checker_texture() -> Texture:
    cols, rows = CHECKER_CORNERS[0] + 1, CHECKER_CORNERS[1] + 1
    s = int(SQUARE * PX_PER_M)
    margin = s  # a white quiet zone of one square, as on a printed board
    img = np.full((rows * s + 2 * margin, cols * s + 2 * margin), 235, np.uint8)
    for r in range(rows):
        for c in range(cols):
            if (r + c) % 2 == 0:
                img[margin + r * s: margin + (r + 1) * s, margin + c * s: margin + (c + 1) * s] = 25
    # Object points start at the first inner corner, one square in from the board's outer corner.
    return Texture(img, margin + s - 0.5)


def charuco_board() -> Charuco:
    return Charuco(CHARUCO_SQUARES, SQUARE, MARKER, "DICT_4X4_50")


def charuco_texture() -> Texture:
    cols, rows = CHARUCO_SQUARES
    s = int(SQUARE * PX_PER_M)
    margin = s // 2
    img = charuco_board().board.generateImage((cols * s + 2 * margin, rows * s + 2 * margin), marginSize=margin)
    img = (25 + img.astype(np.float32) * (210 / 255)).astype(np.uint8)
    return Texture(img, margin - 0.5)  # ChArUco object points start at the board's outer corner


def pixel_rays(cam: Camera) -> NDArray[np.float64]:
    """Normalised ray (x, y) of every supersample of the distorted image, through the camera model."""
    off = (np.arange(SS) + 0.5) / SS - 0.5
    u = (np.arange(W)[:, None] + off[None, :]).ravel()
    v = (np.arange(H)[:, None] + off[None, :]).ravel()
    uu, vv = np.meshgrid(u, v)
    ideal = cam.undistort(np.column_stack([uu.ravel(), vv.ravel()]))
    xy = (ideal - cam.K[:2, 2]) / np.diag(cam.K)[:2]
    assert np.all(np.isfinite(xy))
    return xy.reshape(H * SS, W * SS, 2)


def rotation(ax: float, ay: float, az: float) -> NDArray[np.float64]:
    return cv2.Rodrigues(np.array([ax, 0.0, 0.0]))[0] @ cv2.Rodrigues(np.array([0.0, ay, 0.0]))[0] @ \
        cv2.Rodrigues(np.array([0.0, 0.0, az]))[0]


def render(rays: NDArray[np.float64], tex: Texture, R: NDArray[np.float64], t: NDArray[np.float64],
           rng: np.random.Generator) -> NDArray[np.uint8]:
    """The board (object point Xb -> camera R @ Xb + t) seen by the camera whose rays are given."""
    n = R[:, 2]  # board normal in camera coordinates
    denom = rays[..., 0] * n[0] + rays[..., 1] * n[1] + n[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (n @ t) / denom
    pts = np.stack([rays[..., 0] * s, rays[..., 1] * s, s], axis=-1) - t
    board = pts @ R  # R.T @ (Xc - t) per pixel
    mx = (board[..., 0] * PX_PER_M + tex.origin_px).astype(np.float32)
    my = (board[..., 1] * PX_PER_M + tex.origin_px).astype(np.float32)
    behind = ~(s > 0)
    mx[behind] = -1e6
    my[behind] = -1e6
    hi = cv2.remap(tex.img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=110)
    img = cv2.resize(hi, (W, H), interpolation=cv2.INTER_AREA).astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), 0.6) + rng.normal(0.0, 2.0, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def board_poses(cam: Camera, corners: NDArray[np.float64], n_full: int, n_partial: int,
                seed: int) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """Poses with every corner in view (n_full), then with 45-80 % of them in view (n_partial), the board
    centre spread over a 3x3 grid of the image so that the corners, where distortion is strong, are covered."""
    rng = np.random.default_rng(seed)
    centre = corners.mean(axis=0)
    extent = float(np.ptp(corners[:, 0]))
    near, far = (cam.K[0, 0] * extent / (frac * W) for frac in (0.75, 0.4))  # board 40-75 % of the width
    out: list[tuple[NDArray[np.float64], NDArray[np.float64]]] = []
    while len(out) < n_full + n_partial:
        partial = len(out) >= n_full
        cell = len(out) % 9
        u = (cell % 3 + rng.uniform(0.1, 0.9)) * W / 3
        v = (cell // 3 + rng.uniform(0.1, 0.9)) * H / 3
        if partial:  # push the centre towards the image border
            u = rng.choice([-0.05, 1.05]) * W if rng.random() < 0.5 else u
            v = rng.choice([-0.05, 1.05]) * H if rng.random() < 0.5 else v
        R = rotation(*np.radians(rng.uniform([-40, -40, -15], [40, 40, 15])))
        ray = np.append((cam.undistort([[np.clip(u, 0, W - 1), np.clip(v, 0, H - 1)]])[0] - cam.K[:2, 2])
                        / np.diag(cam.K)[:2], 1.0)
        t = ray * rng.uniform(near, far) - R @ centre
        Xc = corners @ R.T + t
        if np.any(Xc[:, 2] < 0.2):
            continue
        frac = np.mean(cam.in_view(Xc, margin=8.0))
        if (not partial and frac == 1.0) or (partial and 0.45 <= frac <= 0.8):
            out.append((R, t))
    return out


def write_views(folder: Path, tex: Texture, corners: NDArray[np.float64], n_full: int, n_partial: int,
                seed: int) -> list[Path]:
    cam = true_camera()
    rays = pixel_rays(cam)
    rng = np.random.default_rng(seed + 1)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, (R, t) in enumerate(board_poses(cam, corners, n_full, n_partial, seed)):
        p = folder / f"view{i:02d}.png"
        cv2.imwrite(str(p), render(rays, tex, R, t, rng))
        paths.append(p)
    return paths


def blank_views(folder: Path, n: int, seed: int = 7) -> list[Path]:
    """Images with no board: a smooth random scene."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        img = cv2.resize(rng.uniform(60, 200, (12, 16)).astype(np.float32), (W, H), interpolation=cv2.INTER_CUBIC)
        p = folder / f"empty{i}.png"
        cv2.imwrite(str(p), np.clip(img + rng.normal(0, 2, img.shape), 0, 255).astype(np.uint8))
        paths.append(p)
    return paths


def checker_corners() -> NDArray[np.float64]:
    cols, rows = CHECKER_CORNERS
    g = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * SQUARE
    return np.column_stack([g, np.zeros(len(g))])


def charuco_corners() -> NDArray[np.float64]:
    return np.asarray(charuco_board().board.getChessboardCorners(), np.float64)


@pytest.fixture(scope="module")
def checker_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("checker")
    write_views(d, checker_texture(), checker_corners(), n_full=14, n_partial=0, seed=1)
    return d


@pytest.fixture(scope="module")
def charuco_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("charuco")
    write_views(d, charuco_texture(), charuco_corners(), n_full=10, n_partial=6, seed=2)
    return d


def flytrack(*args: str | Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "COLUMNS": "1000"}  # rich wraps at the terminal width, even inside long paths
    return subprocess.run([sys.executable, "-m", "flytrack_host.cli", "calibrate", *map(str, args)],
                          capture_output=True, text=True, timeout=120, env=env)


def lens_error_px(est: Camera, truth: Camera) -> float:
    """Largest pixel disagreement of the two lens models over the image: the same ideal rays through each."""
    g = np.stack(np.meshgrid(np.linspace(0, W - 1, 17), np.linspace(0, H - 1, 13)), axis=-1).reshape(-1, 2)
    xy = (truth.undistort(g) - truth.K[:2, 2]) / np.diag(truth.K)[:2]
    rays = np.column_stack([xy, np.ones(len(xy))])
    return float(np.max(np.linalg.norm(est.project(rays) - truth.project(rays), axis=1)))


def check_recovered(out: Path, stdout: str, lens_tol_px: float) -> Camera:
    truth = true_camera()
    stdout = " ".join(stdout.split())  # rich wraps long lines
    rms = float(re.search(r"RMS reprojection error ([0-9.]+) px", stdout).group(1))  # type: ignore[union-attr]
    # Bounds near what is measured (checkerboard / ChArUco): RMS 0.073 / 0.068 px, fx fy 0.04 / 0.10 %,
    # cx cy 0.52 / 0.75 px, k1 0.0011 / 0.0004, lens 0.65 / 1.28 px (the README quotes them).
    assert rms < 0.1, stdout
    cam = load_calibration(out)["cam1"]
    assert (cam.width, cam.height) == (W, H)
    assert np.allclose(np.diag(cam.K)[:2], np.diag(truth.K)[:2], rtol=0.002), cam.K
    assert np.allclose(cam.K[:2, 2], truth.K[:2, 2], atol=1.2), cam.K
    assert abs(cam.dist[0] - truth.dist[0]) < 0.004, cam.dist
    assert lens_error_px(cam, truth) < lens_tol_px  # worst at the image corners, where the fit extrapolates
    return cam


def test_checkerboard_cli_recovers_the_lens_and_feeds_selfcal(checker_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "intr.json"
    r = flytrack("intrinsics", "cam1", checker_dir, "--corners", "9x6", "--square", SQUARE, "-o", out)
    assert r.returncode == 0, r.stderr
    assert "checkerboard with 9x6 inner corners usable in" in " ".join(r.stdout.split())
    est = check_recovered(out, r.stdout, lens_tol_px=1.0)
    # The file is selfcal's starting point for cam1 of a 4-camera LED rig whose cam1 has this lens.
    truth = true_camera()
    cams = make_rig(4, width=W, height=H, seed=3)
    cams["cam1"].K, cams["cam1"].dist = truth.K.copy(), truth.dist.copy()
    obs, _ = observe(cams, led_path(600, seed=3), noise_px=0.3, missing=0.2, outliers=0.0, seed=3)
    save_points(obs, tmp_path / "points.csv")
    start = initial_cameras(obs, intrinsics=load_calibration(out))[0][0]
    assert np.array_equal(start.K, est.K) and np.array_equal(start.dist, est.dist)
    s = flytrack("selfcal", tmp_path / "points.csv", "--intrinsics", out, "--init", "pairwise",
                 "--distortion", "k1k2p1p2", "-o", tmp_path / "cal.json")
    assert s.returncode == 0, s.stderr
    assert f"intrinsics from {out} held fixed for cam1" in " ".join(s.stdout.split())
    assert np.array_equal(load_calibration(tmp_path / "cal.json")["cam1"].K, load_calibration(out)["cam1"].K)
    assert set(load_calibration(tmp_path / "cal.json")) == {"cam1", "cam2", "cam3", "cam4"}
    # Intrinsics of another image size, or of no camera in the points file, are refused.
    cams["cam1"].width, cams["cam1"].height = 1280, 960
    save_points(observe(cams, led_path(50), seed=3)[0], tmp_path / "big.csv")
    s = flytrack("selfcal", tmp_path / "big.csv", "--intrinsics", out, "-o", tmp_path / "cal2.json")
    assert s.returncode == 2 and "Traceback" not in s.stderr
    assert "cam1 is for 640x480 images but" in " ".join(s.stderr.split())
    save_calibration({"left": est}, tmp_path / "other.json")
    s = flytrack("selfcal", tmp_path / "points.csv", "--intrinsics", tmp_path / "other.json", "-o", tmp_path / "c.json")
    assert s.returncode == 2 and "Traceback" not in s.stderr
    assert "holds camera(s) left but" in " ".join(s.stderr.split())


def test_charuco_cli_with_partial_views(charuco_dir: Path, tmp_path: Path) -> None:
    blank_views(charuco_dir / "more", 1)
    out = tmp_path / "intr.toml"
    r = flytrack("intrinsics", "cam1", charuco_dir, charuco_dir / "more" / "empty0.png", "--board", "charuco",
                 "--squares", "7x5", "--square", SQUARE, "--marker", MARKER, "--dictionary", "DICT_4X4_50",
                 "-o", out)
    assert r.returncode == 0, r.stderr
    text = " ".join(r.stdout.split())
    m = re.search(r"usable in (\d+) of (\d+) images", text)
    assert m is not None, r.stdout
    assert int(m.group(2)) == 17 and int(m.group(1)) >= 12, r.stdout
    assert "empty0.png (no markers found)" in text
    partial_dropped = [f"view{i:02d}.png" in text for i in range(10, 16)]  # views 10-15 are partial
    assert sum(partial_dropped) <= 3, r.stdout
    check_recovered(out, r.stdout, lens_tol_px=1.5)


def test_bad_board_options() -> None:
    with pytest.raises(IntrinsicsError, match="must be smaller than --square"):
        Charuco((7, 5), 0.03, 0.03)
    with pytest.raises(IntrinsicsError, match="not an OpenCV ArUco dictionary"):
        Charuco((7, 5), 0.03, 0.022, "DICT_9X9_1")
    with pytest.raises(IntrinsicsError, match="has 72 markers but DICT_4X4_50 holds only 50"):
        Charuco((12, 12), 0.03, 0.022, "DICT_4X4_50")
    with pytest.raises(IntrinsicsError, match="at least 2x2 inner corners"):
        Checkerboard((1, 6), 0.03)


def test_cli_option_errors(tmp_path: Path) -> None:
    r = flytrack("intrinsics", "cam1", tmp_path, "--board", "charuco", "--squares", "7x5", "--square", SQUARE,
                 "-o", tmp_path / "i.json")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "--board charuco needs --squares COLSxROWS" in " ".join(r.stderr.split())


def test_no_images_in_folder(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("no images here")
    r = flytrack("intrinsics", "cam1", tmp_path / "empty", "--corners", "9x6", "--square", SQUARE,
                 "-o", tmp_path / "i.json")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "holds no images" in r.stderr
    assert not (tmp_path / "i.json").exists()


def test_no_board_found_names_the_images(tmp_path: Path) -> None:
    blank_views(tmp_path / "views", 3)
    (tmp_path / "views" / "broken.png").write_bytes(b"not a png")
    r = flytrack("intrinsics", "cam1", tmp_path / "views", "--corners", "9x6", "--square", SQUARE,
                 "-o", tmp_path / "i.json")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    msg = " ".join(r.stderr.split())
    assert "usable in only 0 of 4 images" in msg
    assert "broken.png (not readable as an image)" in msg and "empty2.png (no board found)" in msg
    assert not (tmp_path / "i.json").exists()


def test_too_few_usable_views(checker_dir: Path, tmp_path: Path) -> None:
    views = sorted(checker_dir.glob("view*.png"))
    r = flytrack("intrinsics", "cam1", *views[2:6], *blank_views(tmp_path / "blank", 2), "--corners", "9x6",
                 "--square", SQUARE, "-o", tmp_path / "i.json")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    msg = " ".join(r.stderr.split())
    assert "usable in only 4 of 6 images; at least 5 are needed" in msg
    assert "empty0.png (no board found), empty1.png (no board found)" in msg
