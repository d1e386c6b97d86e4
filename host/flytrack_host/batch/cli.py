"""`flytrack batch retrack` and `flytrack batch export`: many recordings at once on Dask."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape

from flytrack_host.batch.plan import BatchError, param_sets, plan_exports, plan_retracks
from flytrack_host.batch.results import plot_param_sets, results_frame, write_results
from flytrack_host.batch.runner import BatchReport, run_batch

app = typer.Typer(no_args_is_help=True, rich_markup_mode="markdown")
console = Console()
err = Console(stderr=True)

_SCHED = typer.Option(None, "--scheduler", help="Address of a running Dask scheduler (e.g. tcp://10.0.0.5:8786); "
                      "default: a local cluster of --workers processes on this machine.")
_WORKERS = typer.Option(None, "--workers", min=1, help="Worker processes of the local cluster (default: one per core).")
_PROGRESS = typer.Option(True, help="Show a progress bar over tasks.")


def _finish(rep: BatchReport, out: Path, plot: bool) -> None:
    df = results_frame(rep.rows)
    if not df.empty:
        files = write_results(df, out)
        if plot and "params" in df and "coverage" in df:
            files.append(plot_param_sets(df, out / "results.png"))
        console.print("wrote " + ", ".join(str(f) for f in files), highlight=False)
    console.print(f"{rep.ran} tasks run, {rep.skipped} already done (skipped), {len(rep.failures)} failed, "
                  f"in {rep.wall_s:.1f} s on {rep.workers} workers ({rep.scheduler or 'nothing to run'})",
                  highlight=False)
    for row in rep.rows:
        if row.get("why_no_estimates"):
            err.print(f"[yellow]no estimates[/yellow] {escape(str(row.get('name')))} "
                      f"{escape('[' + str(row.get('params')) + ']')}: {escape(row['why_no_estimates'])}",
                      highlight=False)
    for label, msg in rep.failures:
        # escape: a label's "[parameter set]" is not rich markup (it vanished from the line before)
        err.print(f"[red]failed[/red] {escape(label)}: {escape(str(msg))}", highlight=False)
    if rep.failures:
        raise typer.Exit(code=1)


@app.command("retrack")
def retrack_cmd(
    recordings: list[Path] = typer.Argument(..., help="FlyTrack recordings, .braidz files or flydra .h5 files."),
    out: Path = typer.Option(Path("flytrack-batch"), "--out",
                             help="Folder for the outputs (OUT/<recording>/<parameter set>.flytrack) and the "
                                  "results table (OUT/results.csv, .parquet, .png)."),
    set_: list[str] = typer.Option([], "--set", help="A tracking parameter for every run: KEY=VALUE (repeatable)."),
    sweep: list[str] = typer.Option([], "--sweep", help="Values to try: KEY=V1,V2,... (repeatable; every "
                                    "combination of the sweeps is run)."),
    calibration: Path | None = typer.Option(None, help="Calibration for every recording (default: each one's own)."),
    fps: float | None = typer.Option(None, help="Frame rate, for sources that do not say."),
    scheduler: str | None = _SCHED,
    workers: int | None = _WORKERS,
    progress: bool = _PROGRESS,
) -> None:
    """Re-track each recording with each parameter set, on Dask.

    Workers read the recordings where they are, so with a remote `--scheduler` the paths must be the same on
    every worker (a shared folder). Run it again to resume: finished outputs are skipped. A task that fails
    is reported at the end (exit code 1) without stopping the others."""
    try:
        tasks = plan_retracks([p.resolve() for p in recordings], param_sets(set_, sweep), out.resolve(),
                              calibration.resolve() if calibration else None, fps)
        rep = run_batch(tasks, scheduler, workers, progress)
    except BatchError as exc:
        err.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    _finish(rep, out, plot=True)


@app.command("export")
def export_cmd(
    recordings: list[Path] = typer.Argument(..., help="FlyTrack recordings (folders or their recording.h5)."),
    out: Path = typer.Option(Path("flytrack-export"), "--out", help="Folder for OUT/<recording>/ with the exports."),
    braidz: bool = typer.Option(False, "--braidz", help="Write Braid's .braidz of each recording."),
    csv: bool = typer.Option(False, "--csv", help="Write one CSV file per table of each recording."),
    scheduler: str | None = _SCHED,
    workers: int | None = _WORKERS,
    progress: bool = _PROGRESS,
) -> None:
    """Export many recordings to .braidz and/or CSV on Dask (resumable; failures reported at the end)."""
    formats = tuple(f for f, on in (("braidz", braidz), ("csv", csv)) if on)
    try:
        tasks = plan_exports([p.resolve() for p in recordings], out.resolve(), formats)
        rep = run_batch(tasks, scheduler, workers, progress)
    except BatchError as exc:
        err.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    _finish(rep, out, plot=False)
