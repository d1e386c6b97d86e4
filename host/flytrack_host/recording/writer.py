"""Crash-safe recording: append-only raw files written by a separate thread.

The tracking thread only puts NumPy arrays on a queue (`append`), which never blocks. A writer thread
appends their bytes to one raw file per table and flushes every `flush_interval_s`, so a process
killed at any moment (even with SIGKILL) leaves files that `finalize`/`recover` turn into HDF5,
losing at most the rows of the last flush interval.
"""

from __future__ import annotations

import json
import os
import queue
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.recording.schema import TABLES, dtype_to_json

RAW_SUFFIX = ".bin"
TEXTLOG_NAME = "textlog.jsonl"
META_NAME = "meta.json"
H5_NAME = "recording.h5"
FORMAT_VERSION = 1

_STOP = object()


@dataclass
class RecorderStats:
    rows: dict[str, int] = field(default_factory=dict)
    bytes_written: int = 0
    log_lines: int = 0
    flushes: int = 0
    max_queue_depth: int = 0
    write_errors: int = 0


class Recorder:
    """Records one run into the folder `path` (created; must not exist yet)."""

    def __init__(self, path: Path | str, flush_interval_s: float = 1.0, meta: dict[str, Any] | None = None):
        self.path = Path(path)
        self.flush_interval_s = float(flush_interval_s)
        self.meta = dict(meta or {})
        self.stats = RecorderStats()
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._files: dict[str, Any] = {}
        self._error: BaseException | None = None
        self._stopped = False
        self._wake = threading.Event()
        self.poll_s = min(0.05, self.flush_interval_s)

    # --- life cycle ---------------------------------------------------------------------------
    def start(self) -> None:
        self.path.mkdir(parents=True, exist_ok=False)
        meta = {
            "format": "flytrack-recording",
            "format_version": FORMAT_VERSION,
            "tables": {name: dtype_to_json(dt) for name, dt in TABLES.items()},
            "start_time": time.time(),
            "hostname": socket.gethostname(),
            "flush_interval_s": self.flush_interval_s,
            **self.meta,
        }
        self._write_small(META_NAME, json.dumps(meta, indent=1).encode())
        for name in TABLES:
            self._files[name] = open(self.path / (name + RAW_SUFFIX), "ab")
        self._files["__textlog__"] = open(self.path / TEXTLOG_NAME, "ab")
        self._thread = threading.Thread(target=self._run, name="flytrack-recorder", daemon=True)
        self._thread.start()

    def attach(self, name: str, data: bytes) -> None:
        """Store a whole small file (rig file, calibration) in the recording, right away."""
        self._write_small(name, data)

    def append(self, table: str, rows: np.ndarray) -> None:
        """Queue rows for `table`; never blocks. Rows must have the table's dtype exactly."""
        if rows.dtype != TABLES[table]:
            raise TypeError(f"rows for {table} have dtype {rows.dtype}, expected {TABLES[table]}")
        if len(rows):
            self._q.put((table, rows))

    def append_many(self, items: list[tuple[str, np.ndarray]]) -> None:
        """Queue rows for several tables at once (one queue operation for a whole frame)."""
        for table, rows in items:
            if rows.dtype != TABLES[table]:
                raise TypeError(f"rows for {table} have dtype {rows.dtype}, expected {TABLES[table]}")
        items = [(t, r) for t, r in items if len(r)]
        if items:
            self._q.put(items)

    def log(self, message: str, source: str = "host", host_time: float | None = None) -> None:
        t = time.time() if host_time is None else host_time
        self._q.put(("__textlog__", {"host_time": t, "source": source, "message": message}))

    def stop(self, finalize: bool = True) -> Path | None:
        """Drain the queue, close the files and (by default) write the HDF5 file. Returns its path."""
        if self._stopped:
            return self.path / H5_NAME if (self.path / H5_NAME).exists() else None
        self._stopped = True
        if self._thread is not None:
            self._q.put(_STOP)
            self._wake.set()
            self._thread.join()
        for f in self._files.values():
            f.close()
        if self._error is not None:
            raise RuntimeError(f"recording writer failed: {self._error}") from self._error
        if finalize:
            from flytrack_host.recording.finalize import finalize as _finalize

            return _finalize(self.path).h5_path
        return None

    # --- writer thread ------------------------------------------------------------------------
    def _run(self) -> None:
        # Poll the queue every `poll_s` instead of blocking on it: a put then never wakes this
        # thread, so the tracking thread does not lose the GIL to it once per row batch.
        next_flush = time.monotonic() + self.flush_interval_s
        try:
            while True:
                stop = self._wake.wait(min(self.poll_s, max(0.0, next_flush - time.monotonic())))
                done = self._drain()
                if time.monotonic() >= next_flush or done or stop:
                    self._flush()
                    next_flush = time.monotonic() + self.flush_interval_s
                if done:
                    return
        except BaseException as exc:  # keep the error for stop(); never kill the tracker
            self._error = exc
            self.stats.write_errors += 1

    def _drain(self) -> bool:
        """Write everything queued; True when the stop marker was reached."""
        n = 0
        while True:
            try:
                item = self._q.get_nowait()
            except queue.Empty:
                self.stats.max_queue_depth = max(self.stats.max_queue_depth, n)
                return False
            n += 1
            if item is _STOP:
                return True
            if isinstance(item, list):
                for sub in item:
                    self._write(sub)
            else:
                self._write(item)

    def _write(self, item: tuple[str, Any]) -> None:
        name, payload = item
        f = self._files[name]
        if name == "__textlog__":
            line = (json.dumps(payload, ensure_ascii=False) + "\n").encode()
            f.write(line)
            self.stats.log_lines += 1
            self.stats.bytes_written += len(line)
        else:
            data = np.ascontiguousarray(payload).tobytes()
            f.write(data)
            self.stats.rows[name] = self.stats.rows.get(name, 0) + len(payload)
            self.stats.bytes_written += len(data)

    def _flush(self) -> None:
        for f in self._files.values():
            f.flush()
        self.stats.flushes += 1

    def _write_small(self, name: str, data: bytes) -> None:
        tmp = self.path / (name + ".tmp")
        tmp.write_bytes(data)
        os.replace(tmp, self.path / name)
