"""`flytrack export` and `flytrack retrack`."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.console import Console

console = Console()


def export_command(
    recording: Path = typer.Argument(..., help="A FlyTrack recording (folder or its recording.h5)."),
    braidz: Path | None = typer.Option(None, "--braidz", help="Write Braid's .braidz archive here."),
    csv: Path | None = typer.Option(None, "--csv", help="Write one CSV file per table into this folder."),
) -> None:
    """Export a recording to .braidz (Braid) and/or CSV (spreadsheets)."""
    from flytrack_host.io.braidz import export_braidz
    from flytrack_host.io.csv_export import export_csv
    from flytrack_host.recording import RecordingError, load_recording

    if braidz is None and csv is None:
        console.print("[red]error[/red] nothing to do: pass --braidz OUT and/or --csv OUT_DIR")
        raise typer.Exit(code=2)
    try:
        rec = load_recording(recording)
    except RecordingError as exc:
        console.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    if braidz is not None:
        counts = export_braidz(rec, braidz)
        console.print(f"wrote {braidz}: " + ", ".join(f"{k} {v} rows" for k, v in counts.items()), highlight=False)
    if csv is not None:
        files = export_csv(rec, csv)
        console.print(f"wrote {len(files)} CSV files to {csv}", highlight=False)


def retrack_command(
    source: Path = typer.Argument(..., help="A FlyTrack recording, a .braidz or a flydra .h5."),
    out: Path | None = typer.Option(None, "--out", help="New recording folder (default: SOURCE.retrack)."),
    calibration: Path | None = typer.Option(None, help="Calibration file (default: the one in SOURCE)."),
    params: Path | None = typer.Option(None, "--params", help="TOML with tracking parameters ([tracking] table)."),
    set_: list[str] = typer.Option([], "--set", help="Override a tracking parameter: KEY=VALUE (repeatable)."),
    fps: float | None = typer.Option(None, help="Frame rate, when SOURCE does not say."),
    braidz: Path | None = typer.Option(None, "--braidz", help="Also export the result as .braidz."),
    progress: bool = typer.Option(True, help="Show a progress bar."),
) -> None:
    """Re-run the tracker offline over recorded 2D data, possibly with other tracking parameters."""
    from flytrack_host.io.retrack import RetrackError, cameras_for, load_2d, params_with, retrack

    try:
        data = load_2d(source)
        cams = cameras_for(data, calibration)
        p = params_with(data.tracking_params, params, set_)
    except Exception as exc:  # every loader error is reported the same way
        console.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    rate = fps or data.fps
    if not rate:
        console.print("[red]error[/red] the source does not give the frame rate: pass --fps")
        raise typer.Exit(code=2)
    if out is None:
        out = source.with_name(source.stem + ".retrack.flytrack")
    if out.exists():
        console.print(f"[red]error[/red] {out} exists; pass another --out")
        raise typer.Exit(code=2)
    try:
        res = retrack(data, cams, p, rate, out=out, progress=progress)
    except RetrackError as exc:
        console.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    console.print(f"retracked {res.frames} frames in {res.seconds:.2f} s ({res.frames / max(res.seconds, 1e-9):.0f} "
                  f"frames/s): {res.estimates} estimates of {res.objects} objects -> {res.out}", highlight=False)
    if braidz is not None:
        from flytrack_host.io.braidz import export_braidz
        from flytrack_host.recording import load_recording

        export_braidz(load_recording(res.out), braidz)
        console.print(f"wrote {braidz}", highlight=False)
