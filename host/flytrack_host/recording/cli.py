"""`flytrack recording ...`: recover a recording left by a crash, summarise one."""

from __future__ import annotations

import errno
import shutil
from pathlib import Path

import typer
from rich.console import Console

from flytrack_host.recording.finalize import RecordingError, finalize
from flytrack_host.recording.parts import is_parted, part_dirs
from flytrack_host.recording.schema import H5_NAME, META_NAME
from flytrack_host.recording.source import open_source

app = typer.Typer(help="Recordings: recover after a crash, summarise.", no_args_is_help=True)
console = Console()


@app.command("recover")
def recover(
    path: Path = typer.Argument(..., help="The recording folder (holds meta.json and *.bin files, or parts), "
                                "or one part of it."),
    force: bool = typer.Option(False, help="Rewrite recording.h5 (of every part) even if it already exists."),
    out: Path | None = typer.Option(None, "--out", help="Write the HDF5 file here instead of PATH/recording.h5 "
                                    "(e.g. on another disk when the recording's disk is full). A recording in "
                                    "parts: a new folder, which becomes the recording with one HDF5 file per part."),
) -> None:
    """Complete a recording whose process died: turn its raw files into recording.h5 (a recording in parts:
    each part that has none yet; a crash leaves at most the part being written)."""
    if not path.exists():
        console.print(f"[red]error[/red] {path}: no such folder", highlight=False)
        raise typer.Exit(code=2)
    if not path.is_dir():
        console.print(f"[red]error[/red] {path}: not a folder (give the recording folder, which holds "
                      "meta.json and the *.bin files)", highlight=False)
        raise typer.Exit(code=2)
    parted = is_parted(path) and not (path / META_NAME).exists()
    target = out if out is not None else path / H5_NAME
    parts = [(out if out is not None else path) / p.name for p in part_dirs(path)] if parted else []
    done = all((p / H5_NAME).exists() for p in parts) if parts else (not parted and target.exists())
    if done and not force:
        what = f"every one of its {len(parts)} parts has its {H5_NAME}" if parted else f"{target} exists"
        console.print(f"{path}: already finalised ({what}); use --force to rebuild it")
        return
    try:
        rep = finalize(path, out=out, force=force)
    except RecordingError as exc:
        console.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    except (OSError, RuntimeError) as exc:  # h5py reports a full disk as OSError or RuntimeError
        full = getattr(exc, "errno", None) == errno.ENOSPC or "space" in str(exc).lower()
        why = "the disk is full" if full else f"{type(exc).__name__}: {exc}"
        free = shutil.disk_usage(target.parent).free if target.parent.exists() else 0
        where = target if not parted else (out if out is not None else path)
        console.print(f"[red]error[/red] cannot write {where}: {why} ({free / 1e6:.1f} MB free there). "
                      f"Nothing is lost: the raw files in {path} are untouched. Free some space on that disk and "
                      f"run this again, or write the file elsewhere: flytrack recording recover {path} "
                      + (f"--out OTHER_DISK/{path.name}" if parted else "--out OTHER_DISK/recording.h5"),
                      highlight=False, soft_wrap=True)
        raise typer.Exit(code=2) from None
    console.print(f"[green]recovered[/green] {rep.h5_path}"
                  + (f" ({', '.join(r.h5_path.parent.name for r in rep.parts)})" if parted else ""), highlight=False)
    for name, n in rep.rows.items():
        drop = rep.partial_bytes_dropped.get(name, 0)
        console.print(f"  {name}: {n} rows" + (f" (dropped {drop} bytes of a partial row)" if drop else ""))
    cut = f" ({rep.log_lines_dropped} cut lines dropped)" if rep.log_lines_dropped else ""
    console.print(f"  textlog: {rep.log_lines} lines{cut}")


@app.command("info")
def info(path: Path = typer.Argument(..., help="A recording folder (in parts or not) or its recording.h5.")) -> None:
    """Print the tables of a recording and their row counts, and its parts (counted, not read)."""
    try:
        src = open_source(path)
    except RecordingError as exc:
        console.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    parts = src.parts
    size = sum(p.h5_bytes if p.finalised and p.path.is_file() else p.raw_bytes + p.h5_bytes for p in parts)
    console.print(f"{path}: rig {src.meta.get('rig_name', '?')!r}, fps {src.fps}"
                  + (f", {len(parts)} parts" if src.parted else "") + f", {size / 1e6:.1f} MB on disk", highlight=False)
    for name in src.table_names:
        console.print(f"  {name}: {src.rows(name)} rows")
    files = ", ".join(src.files) or "-"
    console.print(f"  textlog: {sum(p.log_lines for p in parts)} lines; files: {files}", highlight=False)
    if src.parted:
        t0 = parts[0].start_time
        console.print("  parts:")
        for p in parts:
            start = f"+{(p.start_time - t0) / 60:.1f} min" if p.start_time is not None and t0 is not None else "?"
            state = "finalised" if p.finalised else "raw (not finalised: `flytrack recording recover`)"
            cut = f", {p.partial_bytes} bytes of a cut row" if p.partial_bytes else ""
            console.print(f"    {p.name}  from {start}  {p.rows.get('data2d_distorted', 0)} 2D rows, "
                          f"{p.rows.get('kalman_estimates', 0)} estimates, {p.raw_bytes / 1e6:.1f} MB raw  "
                          f"{state}{cut}", highlight=False)
    console.print(f"  read part by part (export, retrack): about {2 * src.largest_part_bytes() / 1e6:.1f} MB of rows "
                  f"in memory at once (two parts); read whole: {sum(p.table_bytes for p in parts) / 1e6:.1f} MB",
                  highlight=False)
