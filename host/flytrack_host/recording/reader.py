"""Read a FlyTrack recording, finalised (HDF5) or not (raw folder), into NumPy tables."""

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
from flytrack_host.recording.schema import H5_NAME, TABLES, dtype_from_json


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
    if path.is_dir():
        h5_path = path / H5_NAME
        if not h5_path.exists():
            return _load_raw(path)
        path = h5_path
    if path.suffix in (".h5", ".hdf5") and path.exists():
        return _load_h5(path)
    raise RecordingError(f"{path}: not a FlyTrack recording (a folder with meta.json, or its recording.h5)")


def _load_raw(folder: Path) -> Recording:
    meta = read_meta(folder)
    tables = {}
    for name, desc in meta["tables"].items():
        tables[name], _ = read_raw_table(folder, name, dtype_from_json(desc))
    log, _ = read_raw_textlog(folder)
    files = {
        p.name: p.read_bytes()
        for p in folder.iterdir()
        if is_attached(p.name)
    }
    return Recording(tables=tables, textlog=log, meta=meta, files=files)


def _load_h5(path: Path) -> Recording:
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
        tables = {name: h5[name][...] for name in TABLES if name in h5}
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
