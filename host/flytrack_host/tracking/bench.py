"""`flytrack bench tracker`: per-frame latency of the tracker, and Stone Soup side by side.

For each rig size (cameras x targets) one synthetic scenario (synthetic.py: 0.5 px noise, 5 % missed
detections, 0.3 false positives per camera and frame, a close pass) is tracked frame by frame. Each
`Tracker.process` call is timed with the wall clock and with this thread's CPU clock (the machine may
be shared: CPU time is what our code costs, wall time what a user would see on an idle machine).
Then, in the same run, the Stone Soup tracker of stonesoup_baseline.py is timed the same way and
scored against the ground truth with the same evaluation.score_frames, in two labelled rows:
- "own": Stone Soup's own initiator (MultiMeasurementInitiator over the volume) and deleter, over the
  whole scenario, as a user would run it: the main comparison;
- "given births": our births handed to Stone Soup (our death rule too), on the first
  --stonesoup-frames frames: the per-frame filter and association alone.
The tracker runs its C kernel when it is built (--kernel chooses); the NumPy path is then timed too on
the same frames, side by side (numpy_* keys in the JSON), and checked to give the same estimates.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from flytrack_host.tracking.evaluation import score_frames
from flytrack_host.tracking.kernel import KernelUnavailable
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.synthetic import make_scenario
from flytrack_host.tracking.tracker import Tracker, select_kernel

app = typer.Typer(help="Benchmarks that print measured figures.", no_args_is_help=True)
console = Console(width=200)

@app.callback()
def _group() -> None:
    """Benchmarks that print measured figures (a group, so that `bench tracker` stays a subcommand)."""


CONFIGS = ((2, 1), (2, 3), (2, 10), (5, 1), (5, 2), (5, 3), (5, 10), (11, 1), (11, 3), (11, 10))


def _pct(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q)) if a.size else float("nan")


def _run_ours(sc, n: int, kernel: str = "auto") -> tuple[np.ndarray, np.ndarray, list, list]:  # noqa: ANN001
    tr = Tracker(sc.cameras, TrackingParams(kernel=kernel), sc.frame_period_s)
    wall = np.empty(n)
    cpu = np.empty(n)
    est = []
    births = []
    for i, b in enumerate(sc.bundles[:n]):
        c0 = time.thread_time_ns()
        w0 = time.perf_counter_ns()
        r = tr.process(b)
        wall[i] = time.perf_counter_ns() - w0
        cpu[i] = time.thread_time_ns() - c0
        est.append({e.obj_id: e.state[:3] for e in r.estimates})
        births.append(tr.last_births)
    return wall / 1e6, cpu / 1e6, est, births


def _run_stonesoup(sc, n: int, births: list | None) -> tuple[np.ndarray, np.ndarray, list]:  # noqa: ANN001
    """births None: Stone Soup's own initiator and deleter over the volume; else our births, given."""
    from flytrack_host.tracking.stonesoup_baseline import StoneSoupTracker
    from flytrack_host.tracking.synthetic import ARENA_HI, ARENA_LO

    volume = (ARENA_LO, ARENA_HI) if births is None else None
    ss = StoneSoupTracker(sc.cameras, TrackingParams(), sc.frame_period_s, volume=volume)
    wall = np.empty(n)
    cpu = np.empty(n)
    est = []
    for i, b in enumerate(sc.bundles[:n]):
        if births is not None:
            ss.add_births(births[i], b.trigger_frame)  # initiation is given, not timed
        c0 = time.thread_time_ns()
        w0 = time.perf_counter_ns()
        est.append(ss.process(b))
        wall[i] = time.perf_counter_ns() - w0
        cpu[i] = time.thread_time_ns() - c0
    return wall / 1e6, cpu / 1e6, est


def _stonesoup_available() -> str | None:
    try:
        import stonesoup  # noqa: F401
    except ImportError as exc:
        return (f"Stone Soup is not installed ({exc}); install it with "
                "`.venv/bin/pip install -r host/requirements-bench.txt` (make bench-tracker does).")
    return None


@app.command("tracker")
def tracker_bench(
    quick: bool = typer.Option(False, "--quick", help="Fewer frames and rig sizes (about 30 s)."),
    frames: int | None = typer.Option(None, min=1, help="Frames tracked per rig size (default 1000, quick 300)."),
    stonesoup_frames: int | None = typer.Option(
        None, min=1, help="Frames of the given-births Stone Soup row (default 100, quick 40); the own-"
        "initiator row tracks the whole scenario."),
    no_stonesoup: bool = typer.Option(False, "--no-stonesoup", help="Skip the Stone Soup comparison."),
    json_path: Path | None = typer.Option(None, "--json", help="Also write the figures to this JSON file."),
    seed: int = typer.Option(1, min=0, help="Scenario seed."),
    kernel: str = typer.Option("auto", help="Tracker path: auto (C when built), c or numpy."),
    no_numpy: bool = typer.Option(False, "--no-numpy", help="Do not also time the NumPy path."),
) -> None:
    """Tracker latency (P50, P99) for 2, 5 and 11 cameras with 1 to 10 targets; real time at 100 and
    200 fps; speed and accuracy against Stone Soup's EKF + nearest-neighbour tracker."""
    if kernel not in ("auto", "c", "numpy"):
        raise typer.BadParameter(f"must be auto, c or numpy, got {kernel!r}", param_hint="--kernel")
    n = frames or (300 if quick else 1000)
    n_ss = min(n, stonesoup_frames or (40 if quick else 100))
    configs = ((2, 1), (5, 2), (5, 10), (11, 3), (11, 10)) if quick else CONFIGS
    ss_missing = None if no_stonesoup else _stonesoup_available()
    if ss_missing:
        console.print(f"[yellow]{ss_missing}[/yellow] Comparison skipped.", highlight=False)
    use_ss = not no_stonesoup and ss_missing is None
    try:
        path, why = select_kernel(TrackingParams(kernel=kernel))  # type: ignore[arg-type]
    except (KernelUnavailable, ValueError) as exc:  # asked for C without the library; a bad env value
        Console(stderr=True, soft_wrap=True).print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    console.print(f"tracker path: {'C kernel' if path == 'c' else 'NumPy'} ({why})", highlight=False)
    compare_numpy = path == "c" and not no_numpy
    rows: list[dict] = []
    for C, T in configs:
        sc = make_scenario(n_cameras=C, n_targets=T, duration_s=n / 100.0, fps=100.0,
                           close_pass_m=0.006 if T >= 2 else None, seed=seed)
        wall, cpu, est, births = _run_ours(sc, n, path)
        s_all = score_frames(sc.truth[:n], est)
        row: dict = {
            "cameras": C, "targets": T, "frames": n, "kernel": path,
            "p50_ms": _pct(wall, 50), "p99_ms": _pct(wall, 99), "mean_ms": float(wall.mean()),
            "cpu_p50_ms": _pct(cpu, 50), "cpu_p99_ms": _pct(cpu, 99), "cpu_mean_ms": float(cpu.mean()),
            "cpu_max_ms": float(cpu.max()),
            "rmse_mm": s_all.rmse_mm, "mota": s_all.mota, "idf1": s_all.idf1,
            "id_switches": s_all.id_switches, "id_switches_free_flight": s_all.id_switches_free_flight,
            "merges": s_all.merges, "merge_frames": s_all.merge_frames, "duplicates": s_all.duplicates,
        }
        for fps in (100, 200):
            period = 1e3 / fps
            row[f"keeps_up_{fps}fps"] = bool(row["mean_ms"] < period)  # throughput: no backlog grows
            row[f"p99_within_period_{fps}fps"] = bool(row["p99_ms"] < period)
            row[f"cpu_p99_within_period_{fps}fps"] = bool(row["cpu_p99_ms"] < period)
        if compare_numpy:
            np_wall, np_cpu, np_est, _ = _run_ours(sc, n, "numpy")
            diff = max((float(np.abs(a[k] - b[k]).max()) for a, b in zip(est, np_est, strict=True) for k in a
                        if k in b), default=0.0)
            same_ids = all(a.keys() == b.keys() for a, b in zip(est, np_est, strict=True))
            row.update({
                "numpy_p50_ms": _pct(np_wall, 50), "numpy_p99_ms": _pct(np_wall, 99),
                "numpy_cpu_p50_ms": _pct(np_cpu, 50), "numpy_cpu_p99_ms": _pct(np_cpu, 99),
                "numpy_cpu_mean_ms": float(np_cpu.mean()),
                "c_speedup_cpu_p50": _pct(np_cpu, 50) / _pct(cpu, 50),
                "c_speedup_cpu_mean": float(np_cpu.mean() / cpu.mean()),
                "c_vs_numpy_max_position_diff_m": diff, "c_vs_numpy_same_ids": same_ids,
            })
        if use_ss:
            from flytrack_host.tracking.stonesoup_baseline import check_camera_model

            check_camera_model(sc.cameras)  # Stone Soup sees our cameras, or the comparison means nothing
            ow_wall, ow_cpu, ow_est = _run_stonesoup(sc, n, None)
            s_own = score_frames(sc.truth[:n], ow_est)
            row.update({
                "ss_own_frames": n, "ss_own_cpu_p50_ms": _pct(ow_cpu, 50), "ss_own_cpu_p99_ms": _pct(ow_cpu, 99),
                "ss_own_cpu_mean_ms": float(ow_cpu.mean()),
                "ss_own_speed_ratio_cpu_mean": float(ow_cpu.mean() / cpu.mean()),
                "ss_own_rmse_mm": s_own.rmse_mm, "ss_own_mota": s_own.mota, "ss_own_idf1": s_own.idf1,
                "ss_own_id_switches": s_own.id_switches, "ss_own_duplicates": s_own.duplicates,
            })
            ss_wall, ss_cpu, ss_est = _run_stonesoup(sc, n_ss, births)
            s_ours = score_frames(sc.truth[:n_ss], est[:n_ss])
            s_ss = score_frames(sc.truth[:n_ss], ss_est)
            row.update({
                "ss_frames": n_ss,
                "ss_p50_ms": _pct(ss_wall, 50), "ss_cpu_p50_ms": _pct(ss_cpu, 50),
                "ss_cpu_mean_ms": float(ss_cpu.mean()),
                "speed_ratio_cpu_mean": float(ss_cpu.mean() / cpu[:n_ss].mean()),
                "speed_ratio_cpu_p50": float(_pct(ss_cpu, 50) / _pct(cpu[:n_ss], 50)),
                **({"numpy_speed_ratio_cpu_mean": float(ss_cpu.mean() / np_cpu[:n_ss].mean())}
                   if compare_numpy else {}),
                "same_frames_ours_rmse_mm": s_ours.rmse_mm, "same_frames_ours_mota": s_ours.mota,
                "ss_rmse_mm": s_ss.rmse_mm, "ss_mota": s_ss.mota, "ss_idf1": s_ss.idf1,
            })
        rows.append(row)
        _print_row(row)
    _print_table(rows, use_ss)
    if compare_numpy:
        _print_numpy_table(rows, use_ss)
    newcomers = [_newcomers(path, seed)] + ([_newcomers("numpy", seed)] if compare_numpy else [])
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps({"tracker": rows, "newcomers": newcomers}, indent=2))
        console.print(f"figures written to {json_path}", highlight=False)


def _newcomers(kernel: str, seed: int, cameras: int = 11, targets: int = 10, fps: float = 200.0) -> dict:
    """The simulated rig's start-up: every animal new in the first frame, seen by all cameras (one
    second at 200 fps). The birth search runs on all the points at once; its cost is the frame's."""
    sc = make_scenario(n_cameras=cameras, n_targets=targets, duration_s=1.0, fps=fps, enter_exit=False,
                       close_pass_m=None, seed=seed)
    n = len(sc.bundles)
    wall, cpu, est, _ = _run_ours(sc, n, kernel)
    tr_confirmed = next((i for i, e in enumerate(est) if len(e) == targets), -1)
    s = score_frames(sc.truth[:n], est)
    r = {"cameras": cameras, "targets": targets, "fps": fps, "frames": n, "kernel": kernel,
         "first_frame_cpu_ms": float(cpu[0]), "cpu_max_ms": float(cpu.max()), "cpu_p99_ms": _pct(cpu, 99),
         "cpu_p50_ms": _pct(cpu, 50), "wall_max_ms": float(wall.max()), "all_confirmed_at_frame": tr_confirmed,
         "rmse_mm": s.rmse_mm, "mota": s.mota}
    console.print(f"newcomers: {cameras} cameras x {targets} animals all new in frame 0, {fps:.0f} fps, {n} frames "
                  f"({kernel}): CPU frame 0 {r['first_frame_cpu_ms']:.2f} ms, max {r['cpu_max_ms']:.2f} ms, "
                  f"P99 {r['cpu_p99_ms']:.3f} ms, P50 {r['cpu_p50_ms']:.3f} ms; all {targets} confirmed at frame "
                  f"{tr_confirmed}; RMSE {r['rmse_mm']:.2f} mm, MOTA {r['mota']:.3f}", highlight=False)
    return r


def _print_row(r: dict) -> None:
    line = (f"{r['cameras']:>2} cameras x {r['targets']:>2} targets ({r['kernel']}): wall P50 {r['p50_ms']:.3f} ms, "
            f"P99 {r['p99_ms']:.3f} ms; CPU P50 {r['cpu_p50_ms']:.3f} ms, P99 {r['cpu_p99_ms']:.3f} ms; "
            f"RMSE {r['rmse_mm']:.2f} mm, MOTA {r['mota']:.3f}, IDF1 {r['idf1']:.3f}")
    if "ss_own_mota" in r:
        line += (f" | Stone Soup (own initiator, {r['ss_own_frames']} frames) CPU mean "
                 f"{r['ss_own_cpu_mean_ms']:.2f} ms "
                 f"({r['ss_own_speed_ratio_cpu_mean']:.0f}x slower), RMSE {r['ss_own_rmse_mm']:.2f} mm, "
                 f"MOTA {r['ss_own_mota']:.3f}, IDF1 {r['ss_own_idf1']:.3f}")
    if "ss_p50_ms" in r:
        line += (f" | Stone Soup (given births) CPU P50 {r['ss_cpu_p50_ms']:.2f} ms "
                 f"({r['speed_ratio_cpu_mean']:.0f}x slower), RMSE {r['ss_rmse_mm']:.2f} mm vs "
                 f"{r['same_frames_ours_rmse_mm']:.2f}, MOTA {r['ss_mota']:.3f} vs "
                 f"{r['same_frames_ours_mota']:.3f} on {r['ss_frames']} frames")
    if "numpy_cpu_p50_ms" in r:
        line += (f" | NumPy path CPU P50 {r['numpy_cpu_p50_ms']:.3f} ms ({r['c_speedup_cpu_p50']:.1f}x), "
                 f"max |C - NumPy| {r['c_vs_numpy_max_position_diff_m']:.1e} m")
    console.print(line, highlight=False)


def _print_table(rows: list[dict], use_ss: bool) -> None:
    t = Table(title="Tracker per-frame latency (ms) and accuracy")
    cols = ["cams x targets", "P50", "P99", "CPU P50", "CPU P99", "keeps up 100 fps", "keeps up 200 fps",
            "RMSE mm", "MOTA"]
    if use_ss:
        cols += ["SS own: CPU mean", "speed ratio", "RMSE mm", "MOTA",
                 "SS given births: CPU P50", "speed ratio", "RMSE mm", "MOTA", "ours (same frames)"]
    for c in cols:
        t.add_column(c, justify="right")
    for r in rows:
        yes = lambda b: "yes" if b else "NO"  # noqa: E731
        cells = [f"{r['cameras']} x {r['targets']}", f"{r['p50_ms']:.3f}", f"{r['p99_ms']:.3f}",
                 f"{r['cpu_p50_ms']:.3f}", f"{r['cpu_p99_ms']:.3f}",
                 f"{yes(r['keeps_up_100fps'])}, P99 {yes(r['p99_within_period_100fps'])} "
                 f"({yes(r['cpu_p99_within_period_100fps'])} CPU)",
                 f"{yes(r['keeps_up_200fps'])}, P99 {yes(r['p99_within_period_200fps'])} "
                 f"({yes(r['cpu_p99_within_period_200fps'])} CPU)",
                 f"{r['rmse_mm']:.2f}", f"{r['mota']:.3f}"]
        if use_ss:
            cells += [f"{r['ss_own_cpu_mean_ms']:.2f}", f"{r['ss_own_speed_ratio_cpu_mean']:.0f}x",
                      f"{r['ss_own_rmse_mm']:.2f}", f"{r['ss_own_mota']:.3f}"]
            cells += [f"{r['ss_cpu_p50_ms']:.2f}", f"{r['speed_ratio_cpu_mean']:.0f}x",
                      f"{r['ss_rmse_mm']:.2f}", f"{r['ss_mota']:.3f}",
                      f"{r['same_frames_ours_rmse_mm']:.2f} mm, {r['same_frames_ours_mota']:.3f}"]
        t.add_row(*cells)
    console.print(t)
    console.print("100/200 fps: 'keeps up' when the mean per-frame time is under the frame period (no "
                  "backlog grows); 'P99' when the 99th percentile wall-clock latency is too (in brackets "
                  "the same on this thread's CPU time, which other load on a shared machine does not "
                  "inflate). "
                  "SS own: Stone Soup's own MultiMeasurementInitiator and CovarianceBasedDeleter over the "
                  "whole scenario, scored like ours (speed ratio on mean CPU time, initiation included on "
                  "both sides). SS given births: Stone Soup gets our births (same frame, state and "
                  "covariance) on the first frames only; its time excludes initiation, ours includes the "
                  "birth search.", highlight=False)


def _print_numpy_table(rows: list[dict], use_ss: bool) -> None:
    t = Table(title="Same scenarios: C kernel vs NumPy path (ms)")
    cols = ["cams x targets", "C CPU P50", "C CPU mean", "NumPy CPU P50", "NumPy CPU mean", "C speed-up P50",
            "C speed-up mean", "max |C - NumPy| m", "same ids"]
    if use_ss:
        cols += ["vs Stone Soup (C)", "vs Stone Soup (NumPy)"]
    for c in cols:
        t.add_column(c, justify="right")
    for r in rows:
        cells = [f"{r['cameras']} x {r['targets']}", f"{r['cpu_p50_ms']:.3f}", f"{r['cpu_mean_ms']:.3f}",
                 f"{r['numpy_cpu_p50_ms']:.3f}", f"{r['numpy_cpu_mean_ms']:.3f}", f"{r['c_speedup_cpu_p50']:.1f}x",
                 f"{r['c_speedup_cpu_mean']:.1f}x", f"{r['c_vs_numpy_max_position_diff_m']:.1e}",
                 "yes" if r["c_vs_numpy_same_ids"] else "NO"]
        if use_ss:
            cells += [f"{r['speed_ratio_cpu_mean']:.0f}x", f"{r['numpy_speed_ratio_cpu_mean']:.0f}x"]
        t.add_row(*cells)
    console.print(t)
    console.print("Speed-ups and Stone Soup ratios are on this thread's CPU time (means over the frames "
                  "Stone Soup tracked); the mean includes the NumPy birth search, which both paths share.",
                  highlight=False)
