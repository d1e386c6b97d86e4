"""Turn a recording folder's append-only raw files into one HDF5 file (on stop, or after a crash).

A raw file cut by a crash ends in at most one partial row: it is dropped and counted. A text log cut
mid-line loses that line only. The HDF5 file is written under a temporary name and renamed, so it is
either complete or absent.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from flytrack_host.recording.schema import LATENCY, dtype_from_json
from flytrack_host.recording.writer import H5_NAME, META_NAME, RAW_SUFFIX, TEXTLOG_NAME

ATTACHED = ("rig.toml",)


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
    for line in path.read_bytes().split(b"\n"):
        if not line:
            continue
        try:
            rows.append(json.loads(line))
        except (json.JSONDecodeError, UnicodeDecodeError):
            dropped += 1
    return rows, dropped


def finalize(folder: Path | str) -> FinalizeReport:
    folder = Path(folder)
    meta = read_meta(folder)
    report = FinalizeReport(h5_path=folder / H5_NAME)
    tmp = folder / (H5_NAME + ".tmp")
    last_t: list[float] = []
    with h5py.File(tmp, "w") as h5:
        for name, desc in meta["tables"].items():
            dt = dtype_from_json(desc)
            rows, partial = read_raw_table(folder, name, dt)
            report.rows[name] = len(rows)
            if partial:
                report.partial_bytes_dropped[name] = partial
            h5.create_dataset(name, data=rows, maxshape=(None,), chunks=True if len(rows) else None)
            for tcol in ("cam_received_timestamp", "host_time", "estimate_time", "stop_timestamp"):
                if tcol in dt.names and len(rows):
                    finite = rows[tcol][np.isfinite(rows[tcol])]
                    if len(finite):
                        last_t.append(float(finite.max()))
        log, dropped = read_raw_textlog(folder)
        report.log_lines, report.log_lines_dropped = len(log), dropped
        str_dt = h5py.string_dtype()
        tl = np.zeros(len(log), dtype=[("host_time", "<f8"), ("source", str_dt), ("message", str_dt)])
        for i, row in enumerate(log):
            tl[i] = (row.get("host_time", np.nan), str(row.get("source", "")), str(row.get("message", "")))
        h5.create_dataset("textlog", data=tl)
        if "latency" in meta["tables"]:
            from flytrack_host.latency import latency_histogram, latency_summary  # (import cycle)

            lat = h5["latency"][...].astype(LATENCY)
            counts, edges = latency_histogram(lat)
            g = h5.create_group("latency_histogram")
            g.create_dataset("counts", data=counts)
            g.create_dataset("edges_ms", data=edges)
            for k, v in latency_summary(lat).items():
                g.attrs[k] = v
        files = h5.create_group("files")
        for p in sorted(folder.iterdir()):
            if p.name in ATTACHED or p.name.startswith("calibration."):
                files.create_dataset(p.name, data=np.frombuffer(p.read_bytes(), dtype=np.uint8))
        for k, v in meta.items():
            if k == "tables":
                continue
            h5.attrs[k] = json.dumps(v)
        h5.attrs["recovered_partial_bytes"] = json.dumps(report.partial_bytes_dropped)
    os.replace(tmp, report.h5_path)
    report.last_host_time = max(last_t) if last_t else None
    return report
