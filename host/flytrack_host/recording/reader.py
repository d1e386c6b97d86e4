"""Read a FlyTrack recording, finalised (HDF5) or not (raw folder), into NumPy tables.

`load_recording` reads it whole: a recording in parts (parts.py) gives the same tables as one written
unparted (the parts' rows in order, the header rows the parts repeat kept once). A day's recording does
not fit in memory whole: the readers that can stream read part by part (source.py).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from flytrack_host.recording.finalize import (
    RecordingError,
    is_attached,
    read_meta,
    read_raw_table,
    read_raw_textlog,
)
from flytrack_host.recording.parts import is_parted, part_dirs, whole_meta
from flytrack_host.recording.schema import H5_NAME, META_NAME, TABLES, dtype_from_json


@dataclass
class Recording:
    tables: dict[str, np.ndarray]
    textlog: list[dict]
    meta: dict
    files: dict[str, bytes] = field(default_factory=dict)  # rig.toml or rig.json, calibration.*

    def table(self, name: str) -> np.ndarray:
        return self.tables.get(name, np.zeros(0, dtype=TABLES[name]))

    @property
    def fps(self) -> float | None:
        v = self.meta.get("fps")
        return float(v) if v else None

    @property
    def calibration(self) -> tuple[str, bytes] | None:
        for name, data in self.files.items():
            if name.startswith("calibration."):
                return name, data
        return None


def load_recording(path: Path | str) -> Recording:
    path = Path(path)
    if path.is_dir() and not (path / META_NAME).exists() and is_parted(path):
        return _load_parts(path)
    if path.is_dir():
        h5_path = path / H5_NAME
        if not h5_path.exists():
            return _load_raw(path)
        path = h5_path
    if path.suffix in (".h5", ".hdf5") and path.exists():
        return _load_h5(path)
    raise RecordingError(f"{path}: not a FlyTrack recording (a folder with meta.json, or its recording.h5)")


def load_folder(p: Path, tables: list[str] | None = None) -> Recording:
    """One recording folder (a part, or an unparted recording), from its HDF5 file if it has one, else
    from its raw files; `tables`: only these (None: all)."""
    h5 = p / H5_NAME if p.is_dir() else p
    if h5.exists() and h5.is_file():
        return _load_h5(h5, tables)
    rec = _load_raw(p, tables)
    return rec


def drop_carried(rec: Recording, index: int) -> Recording:
    """A part's Recording without the header rows it repeats (parts.py), unless it is the first (index 0)."""
    if index > 0:
        for name, n in (rec.meta.get("carried_rows") or {}).items():
            if name in rec.tables and n:
                rec.tables[name] = rec.tables[name][int(n):]
    return rec


def _load_parts(folder: Path) -> Recording:
    parts = [drop_carried(load_folder(p), i) for i, p in enumerate(part_dirs(folder))]
    if not parts:
        raise RecordingError(f"{folder}: a recording in parts without any part (no part-NNNN/meta.json)")
    names = list(parts[0].tables)
    tables = {n: np.concatenate([p.table(n) for p in parts]) for n in names}
    return Recording(tables=tables, textlog=[line for p in parts for line in p.textlog],
                     meta=whole_meta(parts[0].meta, len(parts)), files=parts[0].files)


def _load_raw(folder: Path, names: list[str] | None = None) -> Recording:
    meta = read_meta(folder)
    tables = {}
    for name, desc in meta["tables"].items():
        if names is None or name in names:
            tables[name], _ = read_raw_table(folder, name, dtype_from_json(desc))
    log, _ = read_raw_textlog(folder)
    files = {
        p.name: p.read_bytes()
        for p in folder.iterdir()
        if is_attached(p.name)
    }
    return Recording(tables=tables, textlog=log, meta=meta, files=files)


def _load_h5(path: Path, names: list[str] | None = None) -> Recording:
    """Read `path` (`names`: only these tables; None: all)."""
    try:
        h5 = h5py.File(path, "r")
    except OSError as exc:  # truncated, not HDF5 at all, unreadable: name the file, never a traceback
        raise RecordingError(f"{path}: not a readable HDF5 file ({exc})") from None
    with h5:
        fmt = h5.attrs.get("format")
        if isinstance(fmt, bytes):
            fmt = fmt.decode(errors="replace")
        if "data2d_distorted" not in h5 or fmt != '"flytrack-recording"':
            raise RecordingError(f"{path}: not a FlyTrack recording (no format attribute 'flytrack-recording')")
        meta = {k: json.loads(v) for k, v in h5.attrs.items()}
        tables = {name: h5[name][...] for name in TABLES if name in h5 and (names is None or name in names)}
        log = []
        if "textlog" in h5:
            for row in h5["textlog"][...]:
                src, msg = row["source"], row["message"]
                log.append({
                    "host_time": float(row["host_time"]),
                    "source": src.decode() if isinstance(src, bytes) else str(src),
                    "message": msg.decode() if isinstance(msg, bytes) else str(msg),
                })
        files = {}
        if "files" in h5:
            for name, ds in h5["files"].items():
                files[name] = ds[...].tobytes()
    return Recording(tables=tables, textlog=log, meta=meta, files=files)
