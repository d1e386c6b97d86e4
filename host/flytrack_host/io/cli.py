"""`flytrack export` and `flytrack retrack`."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.console import Console

console = Console()


def export_command(
    recording: Path = typer.Argument(..., help="A FlyTrack recording (folder, in parts or not, or its recording.h5)."),
    braidz: Path | None = typer.Option(None, "--braidz", help="Write Braid's .braidz archive here."),
    csv: Path | None = typer.Option(None, "--csv", help="Write one CSV file per table into this folder."),
) -> None:
    """Export a recording to .braidz (Braid) and/or CSV (spreadsheets). A recording in parts is read part by
    part, so a day's recording exports in the memory of about two parts."""
    from flytrack_host.io.braidz import export_braidz
    from flytrack_host.io.csv_export import export_csv
    from flytrack_host.recording import RecordingError
    from flytrack_host.recording.source import open_source

    if braidz is None and csv is None:
        console.print("[red]error[/red] nothing to do: pass --braidz OUT and/or --csv OUT_DIR")
        raise typer.Exit(code=2)
    try:
        rec = open_source(recording)
    except RecordingError as exc:
        console.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    if braidz is not None:
        counts = export_braidz(rec, braidz)
        _print_braidz_counts(braidz, counts)
    if csv is not None:
        files = export_csv(rec, csv)
        console.print(f"wrote {len(files)} CSV files to {csv}", highlight=False)


def _print_braidz_counts(path: Path, counts: dict[str, int]) -> None:
    tables = ("kalman_estimates", "data2d_distorted", "data_association")
    console.print(f"wrote {path}: " + ", ".join(f"{k} {counts[k]} rows" for k in tables if k in counts)
                  + f", {counts.get('images', 0)} images, "
                  + ", ".join(k for k in counts if k.endswith(".hlog")), highlight=False)
    left = {k: v for k, v in counts.items() if "not exported" in k and v}
    if left:
        console.print("[yellow]warning[/yellow] rows Braid has no place for were left out: "
                      + ", ".join(f"{k} {v}" for k, v in left.items()), highlight=False)
    late = counts.get("rows written out of frame order")
    if late:
        console.print(f"[yellow]warning[/yellow] {late} rows came more than a part after their frame: written after "
                      "it, out of frame order", highlight=False)


def retrack_command(
    source: Path = typer.Argument(..., help="A FlyTrack recording, a .braidz, a Braid .braid folder or a flydra .h5."),
    out: Path | None = typer.Option(None, "--out", help="New recording folder (default: beside SOURCE, its name "
                                    "without .h5/.braidz/.braid/.flytrack + .retrack.flytrack)."),
    calibration: Path | None = typer.Option(None, help="Calibration file: flydra XML or .h5, pymvg JSON, ... "
                                            "(default: the one in SOURCE)."),
    params: Path | None = typer.Option(None, "--params", help="TOML with tracking parameters ([tracking] table)."),
    set_: list[str] = typer.Option([], "--set", help="Override a tracking parameter: KEY=VALUE (repeatable)."),
    fps: float | None = typer.Option(None, help="Frame rate, when SOURCE does not say."),
    braidz: Path | None = typer.Option(None, "--braidz", help="Also export the result as .braidz."),
    progress: bool = typer.Option(True, help="Show a progress bar."),
) -> None:
    """Re-run the tracker offline over recorded 2D data, possibly with other tracking parameters. The result
    carries the calibration it used; when nothing tracks although points arrived, the run says why."""
    from flytrack_host.io.retrack import RetrackError, cameras_for, default_output, load_2d, params_with, retrack

    warns: list[str] = []
    try:
        data = load_2d(source)
        cams = cameras_for(data, calibration, warns)
        p = params_with(data.tracking_params, params, set_)
    except Exception as exc:  # every loader error is reported the same way
        console.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    for w in [*data.notes, *warns]:
        if w.startswith(("braid tracking_params", "trigger clock")):
            continue  # information kept in the output's text log (the clock's is printed below)
        console.print(f"[yellow]warning[/yellow] {w}", highlight=False)
    data.notes = [*data.notes, *warns]
    rate = fps or data.fps
    if not rate:
        from flytrack_host.io.data2d import infer_fps

        inferred = infer_fps(data.rows)
        if inferred is None:
            console.print("[red]error[/red] the source does not give the frame rate, and its 2D data spans too "
                          "few frames to infer it: pass --fps")
            raise typer.Exit(code=2)
        rate, how = inferred
        console.print(f"frame rate not in the source: {rate:.3f} fps inferred from {how} (--fps overrides)",
                      highlight=False)
    if out is None:
        out = default_output(source)
    if out.exists():
        console.print(f"[red]error[/red] {out} exists; pass another --out")
        raise typer.Exit(code=2)
    try:
        res = retrack(data, cams, p, rate, out=out, progress=progress)
    except RetrackError as exc:
        console.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    for line in res.notes or []:
        if line.startswith("trigger clock"):
            console.print(line, highlight=False)
    console.print(f"tracker: {'C kernel' if res.tracker_path == 'c' else 'NumPy'} path", highlight=False)
    console.print(f"retracked {res.frames} frames in {res.seconds:.2f} s ({res.frames / max(res.seconds, 1e-9):.0f} "
                  f"frames/s): {res.estimates} estimates of {res.objects} objects -> {res.out}", highlight=False)
    for w in res.why_nothing or []:
        console.print(f"[yellow]warning[/yellow] no estimates: {w}", highlight=False)
    if braidz is not None:
        from flytrack_host.io.braidz import export_braidz

        _print_braidz_counts(braidz, export_braidz(res.out, braidz))


def compare_command(
    a: Path = typer.Argument(..., help="Track set A: a FlyTrack recording, a .braidz or a flydra .h5."),
    b: Path = typer.Argument(..., help="Track set B, over the same 2D data (e.g. a retrack of A)."),
    calibration: Path | None = typer.Option(None, help="Calibration for the reprojection errors (default: each "
                                            "source's own)."),
    match_mm: float = typer.Option(10.0, help="Estimates of A and B in one frame farther apart are not paired."),
    nearest_px: float = typer.Option(10.0, help="Without a data association, the 2D point an estimate used is "
                                     "taken as the nearest one of each camera within this distance."),
) -> None:
    """Compare two track sets: coverage, per-frame distances, objects matched, and reprojection of each
    to the 2D points it used. Says whether they agree (>= 90 % of each paired, median distance <= 5 mm)."""
    from flytrack_host.io.compare import CompareError, compare, load_tracks, report_lines

    try:
        ta, tb = load_tracks(a, calibration), load_tracks(b, calibration)
    except CompareError as exc:
        console.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    c = compare(ta, tb, match_mm / 1e3, nearest_px)
    console.print(f"A = {a}\nB = {b}", highlight=False)
    for line in report_lines(c, ta.name, tb.name):
        console.print(line, highlight=False)
    console.print("the two track sets agree" if c.agree() else "the two track sets DIFFER", highlight=False)
