"""Measured: DVS cameras self-calibrated together with frame cameras from a simulated blinking LED wand.

The chain a user runs, on sim/dvs_wand.py's ground truth: the DVS cameras' event files through the
LED finder (calibrate dvs-points: read, find the LED by its frequency, stamp trigger frames through the
sync events), merged with the frame cameras' points, through `calibrate selfcal`; then, per camera,
the reprojection error of its own points, the error of its points against the LED's true projection
(DVS cameras: how well the finder did), and after aligning the calibration's LED points onto the true
ones, the camera-centre error (mm) and how far the camera projects the true points from the true
camera (px). Prints a table; --json writes the figures.

Also `flytrack calibrate dvs-sim` (`dvs_sim_cmd`, added to the calibrate group by flytrack_host/cli.py):
the simulated wand's files, for trying `calibrate dvs-points` and `selfcal` by hand.

Run: python -m flytrack_host.sim.dvs_calibration [--seconds 20] [--dvs 2] [--frame-cameras 4]
     [--sensor davis346] [--no-frequency-check] [--json PATH]   (make demo-dvs-calib)
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import typer
from rich.progress import BarColumn, Progress, TextColumn

from flytrack_host.calibration.cli_common import InputError, _clean_errors, console, err
from flytrack_host.calibration.dvs_cli import extract_file, to_observations
from flytrack_host.calibration.evaluate import errors_against_truth
from flytrack_host.calibration.led_events import LedParams
from flytrack_host.calibration.observations import save_points
from flytrack_host.calibration.selfcal import self_calibrate
from flytrack_host.sim.dvs_wand import WandParams, simulate_wand


def run(seconds: float = 20.0, n_frame: int = 4, n_dvs: int = 2, sensor: str = "davis346", seed: int = 0,
        check_frequency: bool = True, wave_s: float = 20.0, out_dir: Path | None = None) -> dict:
    with tempfile.TemporaryDirectory(prefix="flytrack-dvs-calib-") as tmp:
        d = Path(out_dir or tmp)
        t0 = time.perf_counter()
        wp = WandParams(wave_s=wave_s)
        scene = simulate_wand(d, n_frame, n_dvs, seconds, sensor=sensor, seed=seed, params=wp)
        t_sim = time.perf_counter() - t0
        params = LedParams(wp.led_hz, check_frequency=check_frequency)
        results = [extract_file(scene.dvs_files[n], n, params) for n in scene.dvs_files]
    fig: dict = {"seconds": seconds, "frames": len(scene.t), "frame_cameras": n_frame, "dvs_cameras": n_dvs,
                 "sensor": sensor, "led_hz": wp.led_hz, "check_frequency": check_frequency, "sim_s": t_sim,
                 "dvs": {}, "frame": {}}
    for r in results:
        cam = scene.dvs_cameras[r.name]
        e = np.linalg.norm(r.points.uv - cam.project(scene.led[r.points.frame]), axis=1)
        visible = cam.in_view(scene.led, margin=2.0) & ~scene.dvs_hidden[r.name]
        fig["dvs"][r.name] = {
            "events": r.points.stats["events"], "extract_s": r.seconds,
            "events_per_s": r.points.stats["events"] / max(r.seconds, 1e-9),
            "events_per_cpu_s": r.points.stats["events"] / max(r.cpu_seconds, 1e-9),
            "points": len(r.points.frame), "frames_led_visible": int(visible.sum()),
            "points_at_hidden_frames": int(scene.dvs_hidden[r.name][r.points.frame].sum()),
            "point_err_median_px": float(np.median(e)) if len(e) else float("nan"),
            "point_err_p95_px": float(np.percentile(e, 95)) if len(e) else float("nan"),
            "points_over_2px": int((e > 2).sum()),
        }
    obs = to_observations(results, scene.frame_obs)
    t0 = time.perf_counter()
    res = self_calibrate(obs, seed=seed)
    fig["selfcal_s"] = time.perf_counter() - t0
    truth = {**scene.frame_cameras, **scene.dvs_cameras}
    te = errors_against_truth(res.cameras, res.points, truth, scene.led[res.point_frames])
    for ci, name in enumerate(obs.camera_names):
        use = res.inlier & (obs.cam == ci)
        rep = np.linalg.norm(res.residuals[use], axis=1)
        row = fig["dvs"][name] if name in fig["dvs"] else fig["frame"].setdefault(name, {})
        row.update({"reproj_mean_px": float(np.mean(rep)), "inliers": int(use.sum()),
                    "observations": int((obs.cam == ci).sum()),
                    "centre_err_mm": 1000 * te[name]["centre"], "truth_proj_mean_px": te[name]["proj_mean_px"],
                    "truth_proj_p95_px": te[name]["proj_p95_px"]})
    return fig


@_clean_errors
def dvs_sim_cmd(
    out_dir: Path = typer.Argument(..., help="Folder to write frames.csv, dvsN.raw, truth.xml and led.csv into."),
    frame_cameras: int = typer.Option(4, help="Frame cameras."),
    dvs: int = typer.Option(2, help="DVS cameras."),
    seconds: float = typer.Option(10.0, help="Length of the wave, seconds."),
    fps: float = typer.Option(100.0, help="Trigger rate (frames per second)."),
    led_hz: float = typer.Option(500.0, "--led-hz", help="LED blink frequency."),
    sensor: str = typer.Option("davis346", help="DVS sensor: davis346 or dvs128."),
    seed: int = typer.Option(0, help="Random seed."),
) -> None:
    """Simulate an LED wand blinking at --led-hz waved through a 1 m arena: the frame cameras' points
    (frames.csv), one EVT 2.0 file per DVS camera with a moving non-blinking distractor, noise and sync
    events (dvsN.raw), the true cameras (truth.xml) and LED positions per frame (led.csv)."""
    from flytrack_host.geometry.formats import save_calibration
    from flytrack_host.sim.dvs_wand import WandParams, simulate_wand

    try:
        params = WandParams(led_hz=led_hz)
        with Progress(TextColumn("[bold]rendering DVS events[/bold]"), BarColumn(), console=err,
                      transient=True) as prog:
            prog.add_task("sim", total=None)
            scene = simulate_wand(out_dir, frame_cameras, dvs, seconds, fps, sensor=sensor, seed=seed, params=params)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    save_points(scene.frame_obs, out_dir / "frames.csv")
    save_calibration({**scene.frame_cameras, **scene.dvs_cameras}, out_dir / "truth.xml")
    with (out_dir / "led.csv").open("w") as fh:
        fh.write("frame,x,y,z\n")
        for i, (x, y, z) in enumerate(scene.led):
            fh.write(f"{i},{float(x)!r},{float(y)!r},{float(z)!r}\n")
    ev = ", ".join(f"{n}: {scene.dvs_events[n]} events, {scene.dvs_syncs[n]} sync" for n in scene.dvs_files)
    console.print(f"written {out_dir}: frames.csv ({len(scene.frame_obs.frame)} points of {frame_cameras} frame "
                  f"cameras), {ev}; truth.xml, led.csv", highlight=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--dvs", type=int, default=2)
    ap.add_argument("--frame-cameras", type=int, default=4)
    ap.add_argument("--sensor", default="davis346")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-frequency-check", action="store_true", help="take every event as the LED's")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    f = run(a.seconds, a.frame_cameras, a.dvs, a.sensor, a.seed, not a.no_frequency_check)
    print(f"LED wand at {f['led_hz']:g} Hz, {f['seconds']:g} s, {f['frames']} trigger frames, "
          f"{f['frame_cameras']} frame cameras + {f['dvs_cameras']} DVS ({f['sensor']}); frequency check "
          f"{'on' if f['check_frequency'] else 'OFF'}; simulated in {f['sim_s']:.1f} s, selfcal {f['selfcal_s']:.1f} s")
    print(f"{'DVS':>5} {'events':>9} {'M ev/s':>7} {'/CPU s':>7} {'points':>6} {'LED seen':>8} {'at hidden':>9} "
          f"{'pt err med px':>13} {'p95 px':>7} {'>2 px':>6}")
    for n, d in f["dvs"].items():
        print(f"{n:>5} {d['events']:>9d} {d['events_per_s'] / 1e6:>7.2f} {d['events_per_cpu_s'] / 1e6:>7.2f} "
              f"{d['points']:>6d} "
              f"{d['frames_led_visible']:>8d} {d['points_at_hidden_frames']:>9d} {d['point_err_median_px']:>13.3f} "
              f"{d['point_err_p95_px']:>7.3f} {d['points_over_2px']:>6d}")
    print(f"{'camera':>6} {'inliers/obs':>12} {'reproj px':>9} {'vs truth px (mean/p95)':>22} {'centre err mm':>13}")
    for n, d in {**f["frame"], **f["dvs"]}.items():
        print(f"{n:>6} {d['inliers']:>5d}/{d['observations']:<6d} {d['reproj_mean_px']:>9.3f} "
              f"{d['truth_proj_mean_px']:>10.3f} / {d['truth_proj_p95_px']:<9.3f} {d['centre_err_mm']:>13.1f}")
    if a.json:
        a.json.write_text(json.dumps({"demo-dvs-calib": f}, indent=2) + "\n")


if __name__ == "__main__":
    main()
