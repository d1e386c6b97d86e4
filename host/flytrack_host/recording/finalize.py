"""Turn a recording folder's append-only raw files into one HDF5 file (on stop, or after a crash).

A raw file cut by a crash ends in at most one partial row: it is dropped and counted. A text log cut
mid-line loses that line only. The HDF5 file is written under a temporary name and renamed, so it is
either complete or absent. Tables are copied in chunks of `CHUNK_BYTES` (a memory map of the raw
file into a resizable dataset), so a recording of any length finalises in bounded memory; the
latency histogram and its percentiles (0.1 ms bins) are accumulated over the same chunks.

A recording in parts (parts.py) is finalised part by part: each part gets its own recording.h5.
`main` finalises one folder in a process of its own (the background finaliser, finalizer.py).
"""

from __future__ import annotations

import errno
import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from flytrack_host.recording.parts import is_parted, part_dirs
from flytrack_host.recording.schema import H5_NAME, META_NAME, PARTS_NAME, RAW_SUFFIX, TEXTLOG_NAME, dtype_from_json

ATTACHED = ("rig.toml", "rig.json")  # rig.json: a rig given without its TOML text


def is_attached(name: str) -> bool:
    """Small files a recording carries: the rig, the calibration, background images (background_<camera>.*)."""
    return name in ATTACHED or (name.startswith(("calibration.", "background_")) and not name.endswith(".tmp"))
CHUNK_BYTES = 8 << 20  # raw bytes copied per step when finalising
H5_CHUNK_BYTES = 64 << 10  # HDF5 storage chunk of the tables


class RecordingError(Exception):
    """A folder that is not a FlyTrack recording, or one that cannot be read."""


@dataclass
class FinalizeReport:
    h5_path: Path
    rows: dict[str, int] = field(default_factory=dict)
    partial_bytes_dropped: dict[str, int] = field(default_factory=dict)
    log_lines: int = 0
    log_lines_dropped: int = 0
    last_host_time: float | None = None
    parts: list[FinalizeReport] = field(default_factory=list)  # a recording in parts: one per part finalised
    raw_bytes: int = 0  # bytes of raw files read


def read_meta(folder: Path) -> dict:
    meta_path = folder / META_NAME
    if not meta_path.exists():
        raise RecordingError(f"{folder}: no {META_NAME}; this is not a FlyTrack recording folder")
    try:
        return json.loads(meta_path.read_text())
    except json.JSONDecodeError as exc:
        raise RecordingError(f"{meta_path}: unreadable ({exc})") from None


def read_raw_table(folder: Path, name: str, dtype: np.dtype) -> tuple[np.ndarray, int]:
    """Rows of a raw table file and the number of trailing bytes of a partial row (dropped)."""
    path = folder / (name + RAW_SUFFIX)
    if not path.exists():
        return np.zeros(0, dtype=dtype), 0
    data = path.read_bytes()
    n = len(data) // dtype.itemsize
    return np.frombuffer(data[: n * dtype.itemsize], dtype=dtype).copy(), len(data) - n * dtype.itemsize


def read_raw_textlog(folder: Path) -> tuple[list[dict], int]:
    path = folder / TEXTLOG_NAME
    if not path.exists():
        return [], 0
    rows, dropped = [], 0
    with open(path, "rb") as f:
        for line in f:
            line = line.rstrip(b"\n")
            if not line:
                continue
            try:
                rows.append(json.loads(line))
            except (json.JSONDecodeError, UnicodeDecodeError):
                dropped += 1
    return rows, dropped


def _copy_table(h5: h5py.File, folder: Path, name: str, dt: np.dtype, report: FinalizeReport,
                last_t: list[float], on_chunk=None) -> None:
    """Raw file -> dataset `name`, CHUNK_BYTES at a time."""
    path = folder / (name + RAW_SUFFIX)
    size = path.stat().st_size if path.exists() else 0
    n = size // dt.itemsize
    report.rows[name] = n
    if size - n * dt.itemsize:
        report.partial_bytes_dropped[name] = size - n * dt.itemsize
    ds = h5.create_dataset(name, shape=(n,), maxshape=(None,), dtype=dt,
                           chunks=(max(1, H5_CHUNK_BYTES // dt.itemsize),))
    if n == 0:
        return
    tcols = [c for c in ("cam_received_timestamp", "host_time", "estimate_time", "stop_timestamp") if c in dt.names]
    step = max(1, CHUNK_BYTES // dt.itemsize)
    mm = np.memmap(path, dtype=dt, mode="r", shape=(n,))
    try:
        for a in range(0, n, step):
            block = np.array(mm[a : a + step])
            ds[a : a + len(block)] = block
            for tcol in tcols:
                finite = block[tcol][np.isfinite(block[tcol])]
                if len(finite):
                    last_t.append(float(finite.max()))
            if on_chunk is not None:
                on_chunk(block)
    finally:
        del mm


def finalize(folder: Path | str, out: Path | str | None = None, force: bool = True) -> FinalizeReport:
    """Raw files of `folder` -> its recording.h5 (or `out`, e.g. on another disk when this one is
    full). Written to a temporary file first: a failure (a full disk) leaves no half file behind.

    A recording in parts: every part without its recording.h5 (every part with `force`), in order;
    the report sums them (h5_path is the folder, or `out`) and lists each in `parts`. With `out` (a
    folder), the parts are written there as a recording in parts of HDF5 files (see finalize_parts)."""
    folder = Path(folder)
    if is_parted(folder) and not (folder / META_NAME).exists():
        return finalize_parts(folder, force=force, out=Path(out) if out is not None else None)
    meta = read_meta(folder)
    report = FinalizeReport(h5_path=Path(out) if out is not None else folder / H5_NAME)
    tmp = report.h5_path.with_name(report.h5_path.name + ".tmp")
    # HDF5 handles a full disk badly (it can crash the process): check the room first. The file is
    # about the size of the raw files (no compression) plus its index.
    need = sum(f.stat().st_size for f in folder.iterdir() if f.is_file() and f.suffix != ".tmp") + (1 << 20)
    tmp.unlink(missing_ok=True)
    free = shutil.disk_usage(report.h5_path.parent).free
    if free < need:
        raise OSError(errno.ENOSPC, f"not enough space: about {need / 1e6:.1f} MB needed, {free / 1e6:.1f} MB free "
                      f"on the disk of {report.h5_path.parent} (the disk is full)")
    try:
        _write_h5(folder, meta, report, tmp)
    except BaseException:
        tmp.unlink(missing_ok=True)  # frees what it took: the raw files stay, nothing is lost
        raise
    os.replace(tmp, report.h5_path)
    report.raw_bytes = need - (1 << 20)
    return report


def finalize_parts(folder: Path, force: bool = False, out: Path | None = None) -> FinalizeReport:
    """Finalise the parts of a recording in parts (those not finalised yet, or all with `force`).

    `out`: a new folder (e.g. on another disk when this one is full) that becomes the same recording in
    parts, each part its meta.json, small files and recording.h5 (the raw files stay where they are)."""
    parts = part_dirs(folder)
    if not parts:
        raise RecordingError(f"{folder}: a recording in parts without any part (no part-NNNN/meta.json)")
    if out is not None:
        if out.suffix in (".h5", ".hdf5"):
            raise RecordingError(f"{folder} is a recording in parts: give --out a folder (e.g. OTHER_DISK/"
                                 f"{folder.name}), which becomes the recording in parts with one HDF5 file per part")
        out.mkdir(parents=True, exist_ok=True)
        if (folder / PARTS_NAME).exists():
            shutil.copyfile(folder / PARTS_NAME, out / PARTS_NAME)
    total = FinalizeReport(h5_path=out if out is not None else folder)
    for part in parts:
        dest = part if out is None else out / part.name
        if not force and (dest / H5_NAME).exists():
            continue
        if out is not None:
            dest.mkdir(exist_ok=True)
            for f in part.iterdir():
                if f.name == META_NAME or is_attached(f.name):
                    shutil.copyfile(f, dest / f.name)
        rep = finalize(part, out=dest / H5_NAME)
        total.parts.append(rep)
        for k, v in rep.rows.items():
            total.rows[k] = total.rows.get(k, 0) + v
        for k, v in rep.partial_bytes_dropped.items():
            total.partial_bytes_dropped[k] = total.partial_bytes_dropped.get(k, 0) + v
        total.log_lines += rep.log_lines
        total.log_lines_dropped += rep.log_lines_dropped
        total.raw_bytes += rep.raw_bytes
        if rep.last_host_time is not None:
            total.last_host_time = max(total.last_host_time or rep.last_host_time, rep.last_host_time)
    return total


def _write_h5(folder: Path, meta: dict, report: FinalizeReport, tmp: Path) -> None:
    last_t: list[float] = []
    from flytrack_host.recording.latency import LatencyStats  # (import cycle)

    lat_stats = LatencyStats()
    with h5py.File(tmp, "w") as h5:
        for name, desc in meta["tables"].items():
            _copy_table(h5, folder, name, dtype_from_json(desc), report, last_t,
                        on_chunk=lat_stats.add_rows if name == "latency" else None)
        log, dropped = read_raw_textlog(folder)
        report.log_lines, report.log_lines_dropped = len(log), dropped
        str_dt = h5py.string_dtype()
        tl = np.zeros(len(log), dtype=[("host_time", "<f8"), ("source", str_dt), ("message", str_dt)])
        for i, row in enumerate(log):
            tl[i] = (row.get("host_time", np.nan), str(row.get("source", "")), str(row.get("message", "")))
        h5.create_dataset("textlog", data=tl)
        if "latency" in meta["tables"]:
            counts, edges = lat_stats.histogram()
            g = h5.create_group("latency_histogram")
            g.create_dataset("counts", data=counts)
            g.create_dataset("edges_ms", data=edges)
            for k, v in lat_stats.summary().items():
                g.attrs[k] = v
        files = h5.create_group("files")
        for p in sorted(folder.iterdir()):
            if is_attached(p.name):
                files.create_dataset(p.name, data=np.frombuffer(p.read_bytes(), dtype=np.uint8))
        for k, v in meta.items():
            if k == "tables":
                continue
            h5.attrs[k] = json.dumps(v)
        h5.attrs["recovered_partial_bytes"] = json.dumps(report.partial_bytes_dropped)
    report.last_host_time = max(last_t) if last_t else None


def main(argv: list[str] | None = None) -> int:
    """Finalise one recording folder (a part, as the background finaliser does). Exit 1 on failure."""
    import sys

    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: finalize FOLDER", file=sys.stderr)
        return 2
    try:
        finalize(Path(args[0]))
    except (RecordingError, OSError, RuntimeError) as exc:
        print(f"finalising {args[0]} failed: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    return 0
