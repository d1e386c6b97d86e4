"""`flytrack calibrate ...`: the calibration commands."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np
import typer

from flytrack_host.calibration.align import align_cameras, umeyama
from flytrack_host.calibration.cli_common import InputError, _clean_errors, _parse_size, app, console, err
from flytrack_host.calibration.dlt import DLTError, dlt_camera
from flytrack_host.calibration.observations import load_points, save_points
from flytrack_host.geometry.camera import Camera, triangulate
from flytrack_host.geometry.formats import CalibrationFormatError, load_calibration, save_calibration


def _read_rows(path: Path, columns: list[str]) -> list[dict[str, str]]:
    if not path.exists():
        raise InputError(f"{path}: no such file.")
    lines = [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    rows = list(csv.DictReader(lines))
    if not rows or any(c not in rows[0] for c in columns):
        raise InputError(f"{path}: expected a CSV with the header {','.join(columns)} and at least one row.")
    return rows


def _floats(row: dict[str, str], keys: list[str], path: Path) -> list[float]:
    try:
        return [float(row[k]) for k in keys]
    except (TypeError, ValueError):
        raise InputError(f"{path}: row {row} has a value that is not a number.") from None


def _print_report(cameras: dict[str, Camera], obs: Any, residuals: np.ndarray, inlier: np.ndarray,
                  points: np.ndarray, plot: Path | None) -> None:
    from flytrack_host.calibration.report import make_report, plot_report

    rep = make_report(cameras, obs, residuals, inlier)
    for line in rep.lines():
        console.print(line, highlight=False)
    if plot is not None:
        plot_report(cameras, points, obs, residuals, inlier, plot)
        console.print(f"plot written to {plot}", highlight=False)


def _check_intrinsics(intr: dict[str, Camera], path: Path | None, names: list[str], sizes: list[tuple[int, int]],
                      points: Path) -> None:
    """An intrinsics file must name cameras of the points file, for the same image size (pixels must mean
    the same thing: intrinsics of a binned or cropped mode do not apply)."""
    if not any(n in intr for n in names):
        raise InputError(f"--intrinsics {path} holds camera(s) {', '.join(intr)} but {points} has "
                         f"{', '.join(names)}: name the camera as in the points file (flytrack calibrate "
                         "intrinsics NAME ...).")
    for n, (w, h) in zip(names, sizes, strict=True):
        if n in intr and (intr[n].width, intr[n].height) != (w, h):
            raise InputError(f"--intrinsics {path}: {n} is for {intr[n].width}x{intr[n].height} images but "
                             f"{points} says {w}x{h}: calibrate the intrinsics in the mode the rig records in.")
    extra = [n for n in intr if n not in names]
    if extra:
        err.print(f"warning: {path}: camera(s) {', '.join(extra)} are not in {points}; ignored.", highlight=False)


@app.command("selfcal")
@_clean_errors
def selfcal_cmd(
    points: Path = typer.Argument(..., help="Points file (CSV or NPZ of frame, camera, u, v; see docs)."),
    out: Path = typer.Option(..., "--out", "-o", help="Calibration to write (.xml flydra, .json pymvg, .toml)."),
    focal: float = typer.Option(0.0, help="Approximate focal length in pixels (default: the image's larger side)."),
    intrinsics: Path | None = typer.Option(None, help="Intrinsics file (from `calibrate intrinsics`, or any "
                                                      "calibration file) for some or all cameras: their K and "
                                                      "distortion are held FIXED, only their poses are adjusted."),
    refine_intrinsics: bool = typer.Option(False, "--refine-intrinsics",
                                           help="With --intrinsics: use the file only as a starting point and let "
                                                "the bundle adjustment refine K and distortion too."),
    distortion: str = typer.Option("k1k2", help="none, k1, k1k2 or k1k2p1p2 (radial + tangential)."),
    init: str = typer.Option("factorization", "--init",
                             help="Start of the bundle adjustment: factorization (Svoboda: projective factorisation "
                                  "+ Euclidean upgrade, 3+ cameras) or pairwise (essential matrices + PnP from the "
                                  "focal length guess)."),
    plot: Path | None = typer.Option(None, help="Write a PNG of cameras, points and errors."),
) -> None:
    """Self-calibrate all cameras from an LED waved through the volume (up to a similarity; then `align`)."""
    from flytrack_host.calibration.selfcal import self_calibrate

    obs = load_points(points)
    intr = load_calibration(intrinsics) if intrinsics else None
    if intr is not None:
        _check_intrinsics(intr, intrinsics, obs.camera_names, obs.sizes, points)
        named = ", ".join(n for n in obs.camera_names if n in intr)
        if refine_intrinsics:
            console.print(f"starting intrinsics from {intrinsics} for {named} (refined)", highlight=False)
        else:
            console.print(f"intrinsics from {intrinsics} held fixed for {named} (--refine-intrinsics to refine "
                          "them)", highlight=False)
    elif refine_intrinsics:
        raise InputError("--refine-intrinsics needs --intrinsics FILE (without a file every camera's intrinsics "
                         "are refined anyway).")
    res = self_calibrate(obs, focal_px=focal or None, intrinsics=intr, distortion=distortion, init=init,
                         refine_intrinsics=refine_intrinsics)
    save_calibration(res.cameras, out)
    console.print(f"self-calibration of {obs.n_cameras} cameras from {len(res.point_frames)} frames in "
                  f"{sum(res.timings.values()):.1f} s ({res.init_method} start); noise estimate "
                  f"{res.sigma_px:.3f} px", highlight=False)
    _print_report(res.cameras, obs, res.residuals, res.inlier, res.points, plot)
    for w in res.warnings:
        console.print(f"warning: {w}", highlight=False)
    console.print(f"written {out} (frame and scale arbitrary: run `flytrack calibrate align`)", highlight=False)


@app.command("dlt")
@_clean_errors
def dlt_cmd(
    pairs: Path = typer.Argument(..., help="CSV camera,x,y,z,u,v: known 3D points (metres) and their pixels."),
    size: list[str] = typer.Option(..., help="Image size per camera as NAME=WIDTHxHEIGHT (repeat)."),
    out: Path = typer.Option(..., "--out", "-o", help="Calibration to write."),
) -> None:
    """Cameras from 6 or more known 2D/3D pairs each (direct linear transform, no distortion)."""
    sizes = {}
    for s in size:
        name, eq, wh = s.partition("=")
        if not eq or not name:
            raise InputError(f"--size {s!r}: expected NAME=WIDTHxHEIGHT, one per camera, e.g. --size cam1=640x480.")
        sizes[name] = _parse_size(wh)
    rows = _read_rows(pairs, ["camera", "x", "y", "z", "u", "v"])
    by_cam: dict[str, list[list[float]]] = {}
    for r in rows:
        by_cam.setdefault(r["camera"], []).append(_floats(r, ["x", "y", "z", "u", "v"], pairs))
    cams = {}
    for name, vals in by_cam.items():
        if name not in sizes:
            raise InputError(f"camera {name!r} has no --size {name}=WIDTHxHEIGHT.")
        a = np.asarray(vals)
        try:
            cam, e = dlt_camera(name, a[:, :3], a[:, 3:], *sizes[name])
        except DLTError as exc:
            raise DLTError(f"camera {name}: {exc}") from None
        cams[name] = cam
        console.print(f"{name}: {len(a)} pairs, mean reprojection error {e:.3f} px, centre "
                      f"{np.array2string(cam.center, precision=4)}", highlight=False)
    save_calibration(cams, out)
    console.print(f"written {out}", highlight=False)


@app.command("align")
@_clean_errors
def align_cmd(
    calibration: Path = typer.Argument(..., help="Calibration to align (from selfcal)."),
    out: Path = typer.Option(..., "--out", "-o", help="Aligned calibration to write."),
    centres: Path | None = typer.Option(None, help="CSV camera,x,y,z: measured camera centres in metres."),
    marks: Path | None = typer.Option(None, help="CSV mark,camera,u,v: pixels of known marks (with --world)."),
    world: Path | None = typer.Option(None, help="CSV mark,x,y,z: world coordinates of the marks (metres)."),
) -> None:
    """Move, rotate and scale a calibration onto world coordinates (metres, z up) by a similarity."""
    cams = load_calibration(calibration)
    src, dst = [], []
    if centres is not None:
        for r in _read_rows(centres, ["camera", "x", "y", "z"]):
            if r["camera"] not in cams:
                raise InputError(f"{centres}: camera {r['camera']!r} is not in {calibration}.")
            src.append(cams[r["camera"]].center)
            dst.append(_floats(r, ["x", "y", "z"], centres))
    if marks is not None or world is not None:
        if marks is None or world is None:
            raise InputError("--marks and --world go together: pixels of the marks and their world coordinates.")
        wpos = {r["mark"]: _floats(r, ["x", "y", "z"], world) for r in _read_rows(world, ["mark", "x", "y", "z"])}
        seen: dict[str, list[tuple[Camera, np.ndarray]]] = {}
        for r in _read_rows(marks, ["mark", "camera", "u", "v"]):
            if r["camera"] not in cams:
                raise InputError(f"{marks}: camera {r['camera']!r} is not in {calibration}.")
            c = cams[r["camera"]]
            seen.setdefault(r["mark"], []).append((c, c.undistort(_floats(r, ["u", "v"], marks))[0]))
        for m, views in seen.items():
            if m not in wpos or len(views) < 2:
                continue
            src.append(triangulate([v[0] for v in views], [v[1] for v in views]))
            dst.append(wpos[m])
    if not src:
        raise InputError("nothing to align to: give --centres, or --marks with --world.")
    sim = umeyama(np.asarray(src), np.asarray(dst))
    resid = np.linalg.norm(sim.apply(np.asarray(src)) - np.asarray(dst), axis=1)
    aligned = align_cameras(cams, sim)
    save_calibration(aligned, out)
    console.print(f"similarity: scale {sim.s:.6g}; {len(src)} pairs; residual mean {resid.mean():.4g} m, "
                  f"max {resid.max():.4g} m", highlight=False)
    console.print(f"written {out}", highlight=False)


@app.command("intrinsics")
@_clean_errors
def intrinsics_cmd(
    name: str = typer.Argument(..., help="Camera name (as in the rig and points file)."),
    images: list[Path] = typer.Argument(..., help="Images of the board, or folders of them (.png .jpg .tif .bmp)."),
    board: str = typer.Option("checkerboard", help="checkerboard, or charuco (ArUco markers in the white squares; "
                                                   "partial views count)."),
    corners: str | None = typer.Option(None, help="Checkerboard: inner corners as COLSxROWS, e.g. 9x6."),
    squares: str | None = typer.Option(None, help="ChArUco: squares as COLSxROWS, e.g. 7x5."),
    square: float = typer.Option(..., help="Side of one square in metres."),
    marker: float | None = typer.Option(None, help="ChArUco: side of one marker in metres (smaller than --square)."),
    dictionary: str = typer.Option("DICT_4X4_50", help="ChArUco: ArUco dictionary, e.g. DICT_4X4_50, DICT_5X5_100."),
    legacy_pattern: bool = typer.Option(False, "--legacy-pattern",
                                        help="ChArUco: a board printed by OpenCV before 4.6 (matters for an even "
                                             "number of rows)."),
    out: Path = typer.Option(..., "--out", "-o", help="Intrinsics file to write (.json/.xml/.toml)."),
) -> None:
    """Intrinsics of one camera from checkerboard or ChArUco images (OpenCV): a starting point for
    `selfcal --intrinsics`."""
    from flytrack_host.calibration.intrinsics import Charuco, Checkerboard, calibrate_intrinsics, find_images

    if out.suffix.lower() not in (".json", ".xml", ".toml"):
        raise InputError(f"--out {out}: use .json (pymvg), .xml (flydra) or .toml (anipose).")
    kind = board.lower()
    if kind == "checkerboard":
        if corners is None:
            raise InputError("--board checkerboard needs --corners COLSxROWS (inner corners, e.g. 9x6).")
        if squares is not None or marker is not None:
            raise InputError("--squares and --marker are for --board charuco; a checkerboard takes --corners.")
        spec: Checkerboard | Charuco = Checkerboard(_parse_size(corners, "--corners"), square)
    elif kind == "charuco":
        if squares is None or marker is None:
            raise InputError("--board charuco needs --squares COLSxROWS (squares, e.g. 7x5) and --marker (metres).")
        if corners is not None:
            raise InputError("--corners is for --board checkerboard; a ChArUco board takes --squares.")
        spec = Charuco(_parse_size(squares, "--squares"), square, marker, dictionary, legacy_pattern)
    else:
        raise InputError(f"--board {board!r}: use checkerboard or charuco.")
    res = calibrate_intrinsics(name, find_images(images), spec)
    cam = res.camera
    save_calibration({name: cam}, out)
    n_all = len(res.used) + len(res.skipped)
    console.print(f"{name}: {spec.describe()} usable in {len(res.used)} of {n_all} images ({res.n_points} "
                  f"corners); RMS reprojection error {res.rms_px:.3f} px", highlight=False)
    console.print(f"  fx {cam.K[0, 0]:.2f}  fy {cam.K[1, 1]:.2f}  cx {cam.K[0, 2]:.2f}  cy {cam.K[1, 2]:.2f} px; "
                  f"k1 k2 p1 p2 k3 {np.array2string(cam.dist, precision=5)}", highlight=False)
    worst = int(np.argmax(res.view_rms_px))
    console.print(f"  worst view {Path(res.used[worst]).name}: {res.view_rms_px[worst]:.3f} px", highlight=False)
    if res.skipped:
        console.print(f"  not usable: {res.skipped_text()}", highlight=False)
    if res.rms_px > 1.0:
        console.print("warning: RMS above 1 px: check the board size options, the focus and motion blur, or "
                      "remove the worst views.", highlight=False)
    if len(res.used) < 10:
        console.print(f"warning: only {len(res.used)} usable views; 15 or more, tilted and covering the image "
                      "corners, constrain the distortion better.", highlight=False)
    console.print(f"written {out} (start selfcal from it: flytrack calibrate selfcal POINTS --intrinsics {out} ...)",
                  highlight=False)


@app.command("collect")
@_clean_errors
def collect_cmd(
    out: Path = typer.Option(..., "--out", "-o", help="Points file to write (.csv or .npz)."),
    camera: list[str] = typer.Option([], help="NAME=WIDTHxHEIGHT per camera, in camera_index order (repeat); with "
                                              "--recording only needed when it holds no calibration."),
    recording: Path | None = typer.Option(None, help="Take the detections from a FlyTrack recording (folder or "
                                                     "recording.h5) instead of the live rig."),
    port: int = typer.Option(5100, help="UDP port the edge extractors send FEATURES to."),
    seconds: float = typer.Option(120.0, help="How long to collect (Ctrl-C stops early and keeps the data)."),
) -> None:
    """Record single-LED detections from the live rig while you wave the LED (counts and coverage shown),
    or take them from a recording."""
    from flytrack_host.calibration.collect import Collector, collect_udp, points_from_recording

    names, sizes = [], []
    for c in camera:
        name, _, wh = c.partition("=")
        if not name or not wh:
            raise InputError(f"--camera {c!r} is not NAME=WIDTHxHEIGHT (e.g. cam1=1280x1024).")
        names.append(name)
        sizes.append(_parse_size(wh))
    if recording is not None:
        try:
            got = points_from_recording(recording, dict(zip(names, sizes, strict=True)))
        except ValueError as exc:
            raise InputError(str(exc)) from None
        obs = got.obs
        if not len(obs.frame):
            raise InputError(f"{recording}: no camera frame with exactly one point mapped to a trigger frame; "
                             "nothing to calibrate from (was the LED the only light in view?).")
        save_points(obs, out)
        counts = ", ".join(f"{n}: {k}" for n, k in zip(obs.camera_names, obs.counts(), strict=True))
        console.print(f"{len(obs.frame)} detections ({counts}) written to {out}; skipped {got.frames_multi} camera "
                      f"frames with several points, {got.frames_unmapped} without a trigger frame, "
                      f"{got.rows_rejected} rejected rows", highlight=False)
        return
    if not names:
        raise InputError("give --camera NAME=WIDTHxHEIGHT for each camera (or --recording PATH).")
    col = Collector(names, sizes)

    def progress(c: Collector) -> None:
        cov = c.coverage()
        console.print("  ".join(f"{n}: {k} pts {100 * v:.0f}%" for n, k, v in zip(names, c.counts(), cov,
                                                                                   strict=True)), highlight=False)

    collect_udp(col, port, seconds, progress=progress)
    save_points(col.observations(), out)
    console.print(f"{len(col.frames)} detections written to {out} ({col.rejected_multi} frames with several "
                  f"points and {col.bad_datagrams} bad datagrams skipped)", highlight=False)


@app.command("report")
@_clean_errors
def report_cmd(
    calibration: Path = typer.Argument(..., help="Calibration file."),
    points: Path = typer.Argument(..., help="Points file seen by these cameras."),
    plot: Path | None = typer.Option(None, help="Write a PNG of cameras, points and errors."),
) -> None:
    """Reprojection errors of a calibration on a points file, per camera, with advice."""
    from flytrack_host.calibration.selfcal import robust_points

    cams = load_calibration(calibration)
    obs = load_points(points)
    missing = [n for n in obs.camera_names if n not in cams]
    if missing:
        raise InputError(f"camera(s) {', '.join(missing)} of {points} are not in {calibration}.")
    clist = [cams[n] for n in obs.camera_names]
    X, inlier, res = robust_points(clist, obs)
    _print_report({n: cams[n] for n in obs.camera_names}, obs, res, inlier, X, plot)


@app.command("convert")
@_clean_errors
def convert_cmd(
    src: Path = typer.Argument(..., help="Any calibration file (flydra XML, pymvg JSON, OpenCV YAML, anipose)."),
    dst: Path = typer.Argument(..., help="Output: .xml (flydra), .json (pymvg) or .toml (anipose)."),
    force: bool = typer.Option(False, "--force", help="Write even when the output cannot reproduce the source's "
                               "projection within 0.1 px."),
    fmt: str | None = typer.Option(None, "--format", help="Output format when DST's suffix does not say: "
                                   "flydra-xml, pymvg-json or anipose-toml."),
) -> None:
    """Convert a calibration between formats (a flydra .h5's calibration group too). The output is read
    back and compared with the source over each image: more than 0.1 px apart is an error unless --force."""
    from flytrack_host.geometry.formats import compare_projections, single_k_approximation

    warns: list[str] = []
    fidelity: dict[str, float] = {}
    cams = load_calibration(src, warns, fidelity)
    for w in warns:
        err.print(f"[yellow]warning[/yellow] {src}: {w}", highlight=False)
    tmp = dst.with_name(dst.name + ".tmp" + dst.suffix)
    out = cams
    is_xml = fmt == "flydra-xml" if fmt else dst.suffix.lower() == ".xml"
    if not is_xml and any(c.K_dist is not None for c in cams.values()):
        # One K per camera in the output: refit the distortion about P's K; the check below measures it.
        out = {n: single_k_approximation(c) for n, c in cams.items()}
    try:
        save_calibration(out, tmp, fmt=fmt)
    except CalibrationFormatError as exc:  # name the file the user asked for, not the temporary one
        tmp.unlink(missing_ok=True)
        raise CalibrationFormatError(str(exc).replace(str(tmp), str(dst))) from None
    try:
        back = load_calibration(tmp, [])
        diff = compare_projections(cams, back)
    except Exception:
        tmp.unlink(missing_ok=True)
        raise
    worst = {n: max(diff.get(n, 0.0), fidelity.get(n, 0.0)) for n in cams}
    name, px = max(worst.items(), key=lambda kv: kv[1])
    if px > 0.1 and not force:
        tmp.unlink(missing_ok=True)
        raise InputError(f"{dst} would not reproduce {src}'s projection: camera {name!r} is {px:.3g} px off "
                         "(more than 0.1 px). Pass --force to write it anyway, or choose flydra XML (.xml).")
    tmp.replace(dst)
    console.print(f"{len(cams)} cameras written to {dst} (largest difference from the source's projection "
                  f"{px:.2g} px)", highlight=False)


# `dvs-points` and `dvs-sim` (DVS cameras calibrated with a blinking LED) live in their own module.
from flytrack_host.calibration import dvs_cli as _dvs_cli  # noqa: E402, F401
