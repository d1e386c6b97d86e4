"""A recording read part by part: what the readers that stream use (`recording info`, export, retrack).

    src = open_source(path)     # a recording in parts, an unparted folder or recording.h5, or a Recording
    src.parts                   # PartInfo each: rows per table, bytes, finalised or not (nothing loaded)
    for tables in src.iter_tables(["data2d_distorted", "kalman_estimates"]):
        ...                     # one part's rows at a time, header rows repeated by the parts left out

An unparted recording (or a Recording already in memory) is a source of one part, so a reader has
one code path for both layouts. Memory: one part's tables of the names asked for.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from flytrack_host.recording.finalize import RecordingError, read_meta
from flytrack_host.recording.parts import is_parted, part_dirs, whole_meta
from flytrack_host.recording.reader import Recording, drop_carried, load_folder, load_recording
from flytrack_host.recording.schema import H5_NAME, META_NAME, RAW_SUFFIX, TABLES, TEXTLOG_NAME, dtype_from_json


@dataclass
class PartInfo:
    """One part, described without reading its rows."""

    path: Path  # the part's folder (an unparted recording: its folder, or its .h5 file)
    index: int  # 1, 2, ... (0: an unparted recording)
    finalised: bool  # has its HDF5 file (else it is read from its raw files)
    rows: dict[str, int] = field(default_factory=dict)  # rows per table, header rows repeated included
    carried: dict[str, int] = field(default_factory=dict)  # header rows it repeats from the parts before
    raw_bytes: int = 0
    h5_bytes: int = 0
    log_lines: int = 0
    start_time: float | None = None  # host time the part started (None: unknown)
    partial_bytes: int = 0  # bytes of rows cut by a crash (raw files only)

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def table_bytes(self) -> int:
        """Bytes of its tables in memory, read whole."""
        return sum(n * TABLES[t].itemsize for t, n in self.rows.items() if t in TABLES)


class RecordingSource:
    """A recording on disk, read part by part (see the module docstring)."""

    def __init__(self, path: Path, parts: list[Path | None], parted: bool):
        self.path = path
        self.parted = parted
        self._paths = parts
        self.parts = [_part_info(p, i + 1 if parted else 0) for i, p in enumerate(parts)]
        first = self.load_part(0, tables=[]) if parts else None
        self.meta = whole_meta(first.meta, len(parts)) if (first and parted) else (first.meta if first else {})
        self.files: dict[str, bytes] = first.files if first else {}

    @property
    def fps(self) -> float | None:
        v = self.meta.get("fps")
        return float(v) if v else None

    @property
    def calibration(self) -> tuple[str, bytes] | None:
        return Recording({}, [], self.meta, self.files).calibration

    @property
    def table_names(self) -> list[str]:
        """The tables of the recording, in the order a whole read gives them."""
        return list(self.parts[0].rows) if self.parts else []

    def rows(self, name: str) -> int:
        return sum(p.rows.get(name, 0) - p.carried.get(name, 0) for p in self.parts)

    def largest_part_bytes(self) -> int:
        """Bytes of the largest part's tables: what reading one part whole holds."""
        return max((p.table_bytes for p in self.parts), default=0)

    def load_part(self, i: int, tables: list[str] | None = None) -> Recording:
        """Part i (0-based) as a Recording: `tables` (None: all), its text log and files, header rows it
        repeats left out (but in the first part)."""
        return drop_carried(load_folder(self._paths[i], tables), i)

    def iter_tables(self, names: list[str]) -> Iterator[dict[str, np.ndarray]]:
        """Each part's rows of `names`, in order."""
        for i in range(len(self.parts)):
            rec = self.load_part(i, names)
            yield {n: rec.table(n) for n in names}

    def iter_textlog(self) -> Iterator[list[dict]]:
        for i in range(len(self.parts)):
            yield self.load_part(i, tables=[]).textlog

    def table(self, name: str) -> np.ndarray:
        """A whole table (for the small ones: cam_info, trigger_clock_info, camera_status)."""
        chunks = [t[name] for t in self.iter_tables([name])]
        return np.concatenate(chunks) if chunks else np.zeros(0, dtype=TABLES[name])


class MemorySource(RecordingSource):
    """A Recording already in memory, as a source of one part."""

    def __init__(self, rec: Recording):
        self.rec = rec
        self.path = Path(".")
        self.parted = False
        self.meta, self.files = rec.meta, rec.files
        self.parts = [PartInfo(Path("."), 0, True, rows={n: len(t) for n, t in rec.tables.items()})]

    def load_part(self, i: int, tables: list[str] | None = None) -> Recording:
        names = list(self.rec.tables) if tables is None else tables
        return Recording({n: self.rec.table(n) for n in names}, self.rec.textlog, self.meta, self.files)


def open_source(path: Path | str | Recording | RecordingSource) -> RecordingSource:
    """A recording to read part by part: a folder in parts, an unparted folder or its recording.h5, or a
    Recording (one part). Raises RecordingError for anything else."""
    if isinstance(path, RecordingSource):
        return path
    if isinstance(path, Recording):
        return MemorySource(path)
    path = Path(path)
    if path.is_dir() and is_parted(path) and not (path / META_NAME).exists():
        parts = part_dirs(path)
        if not parts:
            raise RecordingError(f"{path}: a recording in parts without any part (no part-NNNN/meta.json)")
        return RecordingSource(path, list(parts), parted=True)
    if path.is_dir():
        read_meta(path)  # the error of a folder that is not a recording
        return RecordingSource(path, [path], parted=False)
    if path.suffix in (".h5", ".hdf5") and path.is_file():
        if _h5_meta(path) is None:
            load_recording(path)  # raises the error of a file that is not a FlyTrack recording
        return RecordingSource(path, [path], parted=False)
    raise RecordingError(f"{path}: not a FlyTrack recording (a folder with meta.json or parts, or its recording.h5)")


def _h5_of(p: Path) -> Path | None:
    if p.is_file():
        return p
    h5 = p / H5_NAME
    return h5 if h5.exists() else None


def _h5_meta(h5: Path) -> dict | None:
    try:
        with h5py.File(h5, "r") as f:
            if f.attrs.get("format") not in ('"flytrack-recording"', b'"flytrack-recording"'):
                return None
            return {k: json.loads(v) for k, v in f.attrs.items()}
    except OSError:
        return None


def _part_info(p: Path, index: int) -> PartInfo:
    h5 = _h5_of(p)
    info = PartInfo(path=p, index=index, finalised=h5 is not None)
    folder = p if p.is_dir() else None
    if folder is not None:
        info.raw_bytes = sum(f.stat().st_size for f in folder.iterdir() if f.is_file() and f.name != H5_NAME
                             and not f.name.endswith(".tmp"))
    if h5 is not None:
        info.h5_bytes = h5.stat().st_size
        meta = _h5_meta(h5) or {}
        with h5py.File(h5, "r") as f:
            info.rows = {n: int(f[n].shape[0]) for n in TABLES if n in f}
            info.log_lines = int(f["textlog"].shape[0]) if "textlog" in f else 0
    else:
        meta = read_meta(p)
        for name, desc in meta.get("tables", {}).items():
            raw = p / (name + RAW_SUFFIX)
            size = raw.stat().st_size if raw.exists() else 0
            item = dtype_from_json(desc).itemsize
            info.rows[name] = size // item
            info.partial_bytes += size % item
        tl = p / TEXTLOG_NAME
        if tl.exists():
            with open(tl, "rb") as f:
                info.log_lines = sum(1 for line in f if line.strip())
    info.carried = {k: int(v) for k, v in (meta.get("carried_rows") or {}).items()}
    info.start_time = meta.get("part_start_time", meta.get("start_time"))
    return info
