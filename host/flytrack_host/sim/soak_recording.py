"""The soak's recording after the run (sim/soak.py): its raw size, reading it back whole from the disk, and
finalising a quarter, a half and all of its rows again to see how the finalise's time grows with length.
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.sim.soak_sampling import folder_bytes

SCALING_FRACTIONS = (0.25, 0.5, 1.0)


def raw_bytes(recording: str | None) -> int:
    """The raw files of a recording (its folder, or its parts, without the HDF5 files)."""
    if not recording:
        return 0
    p = Path(recording)
    return folder_bytes(p if p.is_dir() else p.parent)


def h5_files(recording: Path) -> list[Path]:
    """The HDF5 files of a finalised recording: its recording.h5, or one per part."""
    from flytrack_host.recording.parts import part_dirs
    from flytrack_host.recording.schema import H5_NAME

    if recording.is_file():
        return [recording]
    return [p / H5_NAME for p in part_dirs(recording) if (p / H5_NAME).exists()]


def drop_cache(path: Path) -> bool:
    """Write the file out and drop it from the page cache, so a read comes from the disk."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        os.fsync(fd)
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        return True
    except (OSError, AttributeError):
        return False
    finally:
        os.close(fd)


def read_back(h5: Path) -> dict[str, Any]:
    """Read the finalised recording whole (every table, the text log, the files), from the disk (page cache
    dropped for the file) and again warm."""
    from flytrack_host.recording import load_recording

    files = h5_files(h5)
    out: dict[str, Any] = {"h5_bytes": sum(f.stat().st_size for f in files),
                           "cache_dropped": bool(files) and all([drop_cache(f) for f in files])}
    t0 = time.monotonic()
    rec = load_recording(h5)
    out["cold_s"] = time.monotonic() - t0
    out["table_bytes"] = int(sum(a.nbytes for a in rec.tables.values()))
    out["rows"] = {k: len(v) for k, v in rec.tables.items() if len(v)}
    out["textlog_lines"] = len(rec.textlog)
    del rec
    t0 = time.monotonic()
    rec = load_recording(h5)
    out["warm_s"] = time.monotonic() - t0
    del rec
    return out


def finalise_scaling(h5: Path, work: Path, fractions: tuple[float, ...] = SCALING_FRACTIONS) -> dict[str, Any]:
    """Finalise the first `fractions` of every raw table's rows again (copies in `work`, removed after):
    time against size, and the exponent of a power law through them (1: linear)."""
    from flytrack_host.recording.finalize import finalize, read_meta
    from flytrack_host.recording.schema import H5_NAME, RAW_SUFFIX, dtype_from_json

    folder = h5.parent if h5.is_file() else h5_files(h5)[0].parent  # in parts: the first part
    meta = read_meta(folder)
    sizes = {name + RAW_SUFFIX: dtype_from_json(d).itemsize for name, d in meta["tables"].items()}
    points = []
    for frac in fractions:
        d = work / f"finalise_{int(round(frac * 100))}pct"
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
        try:
            raw = 0
            for e in os.scandir(folder):
                if not e.is_file() or e.name == H5_NAME or e.name.endswith(".tmp"):
                    continue
                n = e.stat().st_size
                if e.name in sizes:  # whole rows of this fraction of the table
                    item = sizes[e.name]
                    n = int(n * frac) // item * item
                with open(e.path, "rb") as src, open(d / e.name, "wb") as dst:
                    _copy_bytes(src, dst, n)
                raw += n
            os.sync()  # the copies' writing is not the finalise's
            t0 = time.monotonic()
            rep = finalize(d)
            dt = time.monotonic() - t0
            points.append({"fraction": frac, "raw_bytes": raw, "h5_bytes": rep.h5_path.stat().st_size,
                           "finalise_s": dt})
        finally:
            shutil.rmtree(d, ignore_errors=True)
    out: dict[str, Any] = {"points": points}
    if len(points) >= 2 and all(p["finalise_s"] > 0 and p["raw_bytes"] > 0 for p in points):
        x = np.log([p["raw_bytes"] for p in points])
        y = np.log([p["finalise_s"] for p in points])
        out["exponent"] = float(np.polyfit(x, y, 1)[0])
    return out


def _copy_bytes(src: Any, dst: Any, n: int) -> None:
    while n > 0:
        b = src.read(min(n, 8 << 20))
        if not b:
            return
        dst.write(b)
        n -= len(b)
