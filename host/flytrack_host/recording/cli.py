"""`flytrack recording ...`: recover a recording left by a crash, summarise one."""

from __future__ import annotations

import errno
import shutil
from pathlib import Path

import typer
from rich.console import Console

from flytrack_host.recording.finalize import RecordingError, finalize
from flytrack_host.recording.reader import load_recording
from flytrack_host.recording.schema import H5_NAME

app = typer.Typer(help="Recordings: recover after a crash, summarise.", no_args_is_help=True)
console = Console()


@app.command("recover")
def recover(
    path: Path = typer.Argument(..., help="The recording folder (holds meta.json and *.bin files)."),
    force: bool = typer.Option(False, help="Rewrite recording.h5 even if it already exists."),
    out: Path | None = typer.Option(None, "--out", help="Write the HDF5 file here instead of PATH/recording.h5 "
                                    "(e.g. on another disk when the recording's disk is full)."),
) -> None:
    """Complete a recording whose process died: turn its raw files into recording.h5."""
    if not path.exists():
        console.print(f"[red]error[/red] {path}: no such folder", highlight=False)
        raise typer.Exit(code=2)
    if not path.is_dir():
        console.print(f"[red]error[/red] {path}: not a folder (give the recording folder, which holds "
                      "meta.json and the *.bin files)", highlight=False)
        raise typer.Exit(code=2)
    target = out if out is not None else path / H5_NAME
    if target.exists() and not force:
        console.print(f"{path}: already finalised ({target} exists); use --force to rebuild it")
        return
    try:
        rep = finalize(path, out=out)
    except RecordingError as exc:
        console.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    except (OSError, RuntimeError) as exc:  # h5py reports a full disk as OSError or RuntimeError
        full = getattr(exc, "errno", None) == errno.ENOSPC or "space" in str(exc).lower()
        why = "the disk is full" if full else f"{type(exc).__name__}: {exc}"
        free = shutil.disk_usage(target.parent).free if target.parent.exists() else 0
        console.print(f"[red]error[/red] cannot write {target}: {why} ({free / 1e6:.1f} MB free there). "
                      f"Nothing is lost: the raw files in {path} are untouched. Free some space on that disk and "
                      f"run this again, or write the file elsewhere: flytrack recording recover {path} "
                      "--out OTHER_DISK/recording.h5", highlight=False, soft_wrap=True)
        raise typer.Exit(code=2) from None
    console.print(f"[green]recovered[/green] {rep.h5_path}", highlight=False)
    for name, n in rep.rows.items():
        drop = rep.partial_bytes_dropped.get(name, 0)
        console.print(f"  {name}: {n} rows" + (f" (dropped {drop} bytes of a partial row)" if drop else ""))
    cut = f" ({rep.log_lines_dropped} cut lines dropped)" if rep.log_lines_dropped else ""
    console.print(f"  textlog: {rep.log_lines} lines{cut}")


@app.command("info")
def info(path: Path = typer.Argument(..., help="A recording folder or its recording.h5.")) -> None:
    """Print the tables of a recording and their row counts."""
    try:
        rec = load_recording(path)
    except RecordingError as exc:
        console.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    console.print(f"{path}: rig {rec.meta.get('rig_name', '?')!r}, fps {rec.fps}")
    for name, rows in rec.tables.items():
        console.print(f"  {name}: {len(rows)} rows")
    console.print(f"  textlog: {len(rec.textlog)} lines; files: {', '.join(rec.files) or '-'}")
