"""Crash-safe recording: append-only raw files written by a separate thread.

The tracking thread only puts NumPy arrays on a queue (`append`), which never blocks. A writer thread
takes what is queued every `poll_s` (50 ms), appends its bytes to one raw file per table with plain
`os.write` calls (so the rows are in the kernel at once: a process killed at any moment, even with
SIGKILL, loses nothing written) and `os.fsync`s every `flush_interval_s` (so a power loss loses at
most that interval). `finalize`/`recover` turn the files into HDF5.

Failures are never silent and never grow memory without bound:
- a write that fails (disk full, I/O error) is undone to the file's last whole row (a raw file
  never holds a partial row in its middle), its rows are counted as lost (`stats.write_errors`,
  `stats.dropped_rows`), the first error of an episode is logged at once and kept in `last_error`,
  and the writer goes on (the next writes succeed when space comes back);
- the queue holds at most `max_queue_bytes`: beyond that `append` drops the rows and counts them
  (`stats.dropped_rows`, `stats.queue_bytes` shows the depth); the writer notes every drop in the
  recording's text log once it can, so the recording itself says rows are missing.

With `parts` (a PartPolicy) the folder holds the recording in parts (parts.py): the writer thread
rolls to a new part between two queued items once the part is old or big enough, and a background
process finalises the part it closed, so `stop` finalises the last part only.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.recording.finalizer import PartFinalizer
from flytrack_host.recording.parts import PARTS_FORMAT_VERSION, PartPolicy, part_name
from flytrack_host.recording.rolling import NEW_PART, PartsMixin
from flytrack_host.recording.schema import (
    HEADER_TABLES,
    META_NAME,
    PARTS_NAME,
    RAW_SUFFIX,
    TABLES,
    TEXTLOG_NAME,
    dtype_to_json,
)
from flytrack_host.util import hostclock

FORMAT_VERSION = 1
TEXTLOG_KEY = "__textlog__"
DEFAULT_MAX_QUEUE_BYTES = 256 << 20  # minutes of a big rig's 2D data; a stuck disk must not eat the RAM

log = logging.getLogger("flytrack.recording")

_STOP = object()


def _write_all(fd: int, data: bytes | memoryview) -> None:
    """Write all of `data` to `fd` (os.write may write less than asked). The seam the tests use to
    fake a full disk."""
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


@dataclass
class RecorderStats:
    rows: dict[str, int] = field(default_factory=dict)
    bytes_written: int = 0
    log_lines: int = 0
    flushes: int = 0  # fsyncs
    max_queue_depth: int = 0  # items taken in one turn of the writer
    queue_bytes: int = 0  # bytes queued and not yet written (at the last look)
    max_queue_bytes: int = 0
    write_errors: int = 0
    dropped_rows: dict[str, int] = field(default_factory=dict)  # lost to a full queue or a failed write
    dropped_log_lines: int = 0
    queue_full_drops: int = 0  # rows and lines dropped because the queue was full
    parts: int = 0  # parts started (a recording in parts)
    largest_part_bytes: int = 0  # raw bytes of the largest part (what a part-by-part reader holds)
    roll_errors: int = 0  # new parts that could not be made (the writer went on in the old one)
    parts_finalised_background: int = 0
    finalise_background_s: float = 0.0
    finalise_at_stop_bytes: int = 0  # raw bytes stop() finalised or waited on
    finalise_at_stop_s: float | None = None  # how long that took (None: not stopped, or not finalised)


class Recorder(PartsMixin):
    """Records one run into the folder `path` (created; must not exist yet).

    `on_full`: "drop" (live: `append` never blocks, rows beyond `max_queue_bytes` are dropped and
    counted) or "block" (offline, e.g. re-tracking: `append` waits for room). `parts`: None for one
    folder of raw files, or a PartPolicy for a recording in parts."""

    def __init__(self, path: Path | str, flush_interval_s: float = 1.0, meta: dict[str, Any] | None = None,
                 max_queue_bytes: int = DEFAULT_MAX_QUEUE_BYTES, on_full: str = "drop",
                 parts: PartPolicy | None = None):
        if on_full not in ("drop", "block"):
            raise ValueError(f"on_full must be 'drop' or 'block', not {on_full!r}")
        self.path = Path(path)
        self.flush_interval_s = float(flush_interval_s)
        self.meta = dict(meta or {})
        self.max_queue_bytes = int(max_queue_bytes)
        self.on_full = on_full
        self.stats = RecorderStats()
        self.last_error: str | None = None  # the latest write error, for status lines
        self._q: deque = deque()
        self._in_bytes = 0  # queued so far (producers, under _put_lock)
        self._out_bytes = 0  # taken by the writer (writer thread only)
        self._put_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._fds: dict[str, int] = {}
        self._sizes: dict[str, int] = {}  # bytes of whole rows/lines in each file
        self._unsynced: set[str] = set()
        self._noted_drops: dict[str, int] = {}  # drops already written to the text log
        self._noted_log_drops = 0
        self._last_note = 0.0
        self._failing = False  # inside an episode of write errors (log once per episode)
        self._stopped = False
        self._wake = threading.Event()
        self.poll_s = min(0.05, self.flush_interval_s)
        self.parts = parts
        self.part_index = 0  # the part being written (0: not a recording in parts)
        self._part_dir = self.path  # where the files being written are
        self._part_started = 0.0
        self._part_base = 0  # bytes a new part starts with (its header rows)
        self._part_lock = threading.Lock()  # attach() (any thread) against a roll (writer thread)
        self._attached: dict[str, bytes] = {}  # copied into every new part
        self._header: dict[str, list[bytes]] = {}  # HEADER_TABLES rows written so far, for every new part
        self._roll_retry_at = 0.0
        self._roll_failures = 0  # failed tries to start the next part, in a row
        self._finalizer = (PartFinalizer(on_done=self._part_finalised)
                           if parts is not None and parts.finalize == "process" else None)

    # --- life cycle ---------------------------------------------------------------------------
    def start(self) -> None:
        self.path.mkdir(parents=True, exist_ok=False)
        self._meta = {
            "format": "flytrack-recording",
            "format_version": FORMAT_VERSION,
            "tables": {name: dtype_to_json(dt) for name, dt in TABLES.items()},
            "start_time": hostclock.now(),  # host time (monotonic timeline), as every row's
            "start_wall_time": hostclock.wall(),  # the wall clock then: a label only
            "hostname": socket.gethostname(),
            "flush_interval_s": self.flush_interval_s,
            "max_queue_bytes": self.max_queue_bytes,
            **self.meta,
        }
        if self.parts is None:
            self._write_small(META_NAME, json.dumps(self._meta, indent=1).encode())
            self._fds, self._sizes = self._open_files(self.path)
        else:
            p = self.parts
            about = {"format": "flytrack-recording", "layout": "parts", "parts_format_version": PARTS_FORMAT_VERSION,
                     "part_seconds": p.seconds, "part_bytes": p.bytes, "start_time": self._meta["start_time"],
                     "start_wall_time": self._meta["start_wall_time"], "rig_name": self._meta.get("rig_name")}
            self._write_small(PARTS_NAME, json.dumps(about, indent=1).encode(), self.path)
            self._part_dir = self.path / part_name(1)
            self._fds, self._sizes = self._make_part(self._part_dir, 1)
            self.part_index = self.stats.parts = 1
            self._part_started = time.monotonic()
            self._part_base = sum(self._sizes.values())
        self._fsync_dir(self.path)  # the files exist after a power loss too
        self._thread = threading.Thread(target=self._run, name="flytrack-recorder", daemon=True)
        self._thread.start()

    @staticmethod
    def _write_all(fd: int, data: bytes) -> None:
        _write_all(fd, data)  # (the module's function, looked up at each call: the tests' write seam)

    @staticmethod
    def _open_files(folder: Path) -> tuple[dict[str, int], dict[str, int]]:
        """One append-only file per table and the text log, in `folder`: file descriptors and sizes."""
        fds: dict[str, int] = {}
        try:
            for key, name in [(t, t + RAW_SUFFIX) for t in TABLES] + [(TEXTLOG_KEY, TEXTLOG_NAME)]:
                fds[key] = os.open(folder / name, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        except OSError:
            for fd in fds.values():
                os.close(fd)
            raise
        return fds, {k: os.fstat(fd).st_size for k, fd in fds.items()}

    def attach(self, name: str, data: bytes) -> None:
        """Store a whole small file (rig file, calibration) in the recording, right away (in every part)."""
        with self._part_lock:
            if self.parts is not None:
                self._attached[name] = bytes(data)
            self._write_small(name, data, self._part_dir)

    def append(self, table: str, rows: np.ndarray) -> None:
        """Queue rows for `table`; never blocks (with on_full="drop"). Rows must have the table's
        dtype exactly."""
        if rows.dtype != TABLES[table]:
            raise TypeError(f"rows for {table} have dtype {rows.dtype}, expected {TABLES[table]}")
        if len(rows):
            self._put((table, rows), rows.nbytes)

    def append_many(self, items: list[tuple[str, np.ndarray]]) -> None:
        """Queue rows for several tables at once (one queue operation for a whole frame)."""
        for table, rows in items:
            if rows.dtype != TABLES[table]:
                raise TypeError(f"rows for {table} have dtype {rows.dtype}, expected {TABLES[table]}")
        items = [(t, r) for t, r in items if len(r)]
        if items:
            self._put(items, sum(r.nbytes for _, r in items))

    def log(self, message: str, source: str = "host", host_time: float | None = None) -> None:
        t = hostclock.now() if host_time is None else host_time
        self._put((TEXTLOG_KEY, {"host_time": t, "source": source, "message": message}), 64 + len(message))

    @property
    def queue_bytes(self) -> int:
        return self._in_bytes - self._out_bytes

    def _put(self, item: Any, nbytes: int) -> None:
        if self.on_full == "block":
            while self.queue_bytes + nbytes > self.max_queue_bytes and self.queue_bytes > 0 and not self._stopped:
                time.sleep(0.005)
        with self._put_lock:
            depth = self._in_bytes - self._out_bytes
            if depth + nbytes > self.max_queue_bytes and self.on_full == "drop":
                self._count_dropped(item)
                return
            self._in_bytes += nbytes
            self._q.append((item, nbytes))
        if depth + nbytes > self.stats.max_queue_bytes:
            self.stats.max_queue_bytes = depth + nbytes

    def _count_dropped(self, item: Any) -> None:
        for name, payload in item if isinstance(item, list) else [item]:
            if name == TEXTLOG_KEY:
                self.stats.dropped_log_lines += 1
                self.stats.queue_full_drops += 1
            else:
                self.stats.dropped_rows[name] = self.stats.dropped_rows.get(name, 0) + len(payload)
                self.stats.queue_full_drops += len(payload)

    def stop(self, finalize: bool = True) -> Path | None:
        """Write what is queued, fsync and close the files and (by default) write the HDF5 file.
        Returns its path (a recording in parts: the folder, once every part has its HDF5 file). Rows
        lost to write errors or a full queue are in `stats` and the text log.

        In parts: waits for the part the background finaliser is on, then finalises here whatever part
        has no HDF5 file (the last one; one whose background finalising failed). `stats` says how many
        bytes that was (`finalise_at_stop_bytes`) and how long it took (`finalise_at_stop_s`)."""
        if self._stopped:
            return self._finished_path()
        self._stopped = True
        if self._thread is not None:
            self._q.append((_STOP, 0))
            self._wake.set()
            self._thread.join()
        for fd in self._fds.values():
            os.close(fd)
        self._fds.clear()
        self.stats.largest_part_bytes = max(self.stats.largest_part_bytes, sum(self._sizes.values()))
        if not finalize:
            if self._finalizer is not None:
                self._finalizer.cancel()
            return None
        from flytrack_host.recording.finalize import finalize as _finalize

        t0 = time.monotonic()
        if self.parts is None:
            rep = _finalize(self.path)
            self.stats.finalise_at_stop_bytes = rep.raw_bytes
            self.stats.finalise_at_stop_s = time.monotonic() - t0
            return rep.h5_path
        return self._stop_parts(_finalize, t0)

    # --- writer thread ------------------------------------------------------------------------
    def _run(self) -> None:
        # Poll the queue every `poll_s` instead of blocking on it: a put then never wakes this
        # thread, so the tracking thread does not lose the GIL to it once per row batch.
        next_sync = time.monotonic() + self.flush_interval_s
        while True:
            stop = self._wake.wait(min(self.poll_s, max(0.0, next_sync - time.monotonic())))
            try:
                done = self._drain()
                if self._finalizer is not None:
                    self._finalizer.poll()
                self._note_drops(force=done or stop)
                if time.monotonic() >= next_sync or done or stop:
                    self._sync()
                    next_sync = time.monotonic() + self.flush_interval_s
            except Exception as exc:  # a bug here must not end the recording: count, log, go on
                done = stop
                self._error(f"recording writer: {exc!r}", exc)
            if done:
                return

    def _drain(self) -> bool:
        """Write everything queued (one write per file); True when the stop marker was reached. In parts,
        a new part is started between two items when the part is old or big enough (or asked for)."""
        batches: dict[str, list[Any]] = {}
        pending = 0  # bytes in `batches`
        n = 0
        done = False
        if self.parts is not None and self._part_due(0, 0, by_time=True):
            self._roll()
        while self._q:
            item, nbytes = self._q.popleft()
            self._out_bytes += nbytes
            n += 1
            if item is _STOP:
                done = True
                break
            if item is NEW_PART or (self.parts is not None and self._part_due(pending, nbytes)):
                self._write_batches(batches)
                batches, pending = {}, 0
                self._roll(asked=item is NEW_PART)
                if item is NEW_PART:
                    continue
            for name, payload in item if isinstance(item, list) else [item]:
                batches.setdefault(name, []).append(payload)
            pending += nbytes
        self.stats.max_queue_depth = max(self.stats.max_queue_depth, n)
        self._write_batches(batches)
        self.stats.queue_bytes = self.queue_bytes
        return done

    def _write_batches(self, batches: dict[str, list[Any]]) -> None:
        for name, payloads in batches.items():
            self._write_batch(name, payloads)

    def _write_batch(self, name: str, payloads: list[Any]) -> None:
        if name == TEXTLOG_KEY:
            data = b"".join((json.dumps(p, ensure_ascii=False) + "\n").encode() for p in payloads)
            count = len(payloads)
        else:
            data = b"".join(np.ascontiguousarray(p).tobytes() for p in payloads)
            count = sum(len(p) for p in payloads)
        fd = self._fds[name]
        try:
            _write_all(fd, data)
        except OSError as exc:
            # Undo a partial write: the file keeps whole rows only, so everything after stays aligned.
            try:
                os.ftruncate(fd, self._sizes[name])
            except OSError:
                pass
            self.stats.write_errors += 1
            with self._put_lock:  # producers count their drops in the same dict
                if name == TEXTLOG_KEY:
                    self.stats.dropped_log_lines += count
                else:
                    self.stats.dropped_rows[name] = self.stats.dropped_rows.get(name, 0) + count
            self._error(f"recording: cannot write {name} ({os.strerror(exc.errno) if exc.errno else exc}); "
                        f"{count} {'lines' if name == TEXTLOG_KEY else 'rows'} lost", exc)
            return
        if self._failing:
            self._failing = False
            log.warning("recording: writing again after write errors (%d so far)", self.stats.write_errors)
        self._sizes[name] += len(data)
        self._unsynced.add(name)
        self.stats.bytes_written += len(data)
        if self.parts is not None and name in HEADER_TABLES:
            self._header.setdefault(name, []).append(data)  # every later part starts with them
        if name == TEXTLOG_KEY:
            self.stats.log_lines += count
        else:
            self.stats.rows[name] = self.stats.rows.get(name, 0) + count

    def _error(self, message: str, exc: BaseException) -> None:
        self.last_error = message
        if not self._failing:  # once per episode, at once (not at stop)
            self._failing = True
            log.error("%s", message, exc_info=exc if not isinstance(exc, OSError) else None)

    def _note_drops(self, force: bool = False) -> None:
        """Put drops not yet noted into the text log (directly: the queue may be what is full), at
        most once a second while they go on, and at the end."""
        if not force and time.monotonic() - self._last_note < 1.0:
            return
        st = self.stats
        with self._put_lock:
            snap, snap_lines = dict(st.dropped_rows), st.dropped_log_lines
        seen = self._noted_drops
        new = {k: v - seen.get(k, 0) for k, v in snap.items() if v > seen.get(k, 0)}
        new_lines = snap_lines - self._noted_log_drops
        if not new and not new_lines:
            return
        what = ", ".join(f"{n} {k} rows" for k, n in sorted(new.items()))
        if new_lines:
            what = (what + ", " if what else "") + f"{new_lines} log lines"
        why = []
        if st.queue_full_drops:
            why.append(f"recorder queue full ({self.max_queue_bytes} bytes): {st.queue_full_drops} dropped so far")
        if st.write_errors:
            why.append(f"{st.write_errors} write errors so far, last: {self.last_error}")
        message = f"DATA LOST: {what} not recorded ({'; '.join(why)})"
        if not self._direct_log(message):
            return  # noted on a later turn
        self._noted_drops, self._noted_log_drops = snap, snap_lines
        self._last_note = time.monotonic()
        if not self._failing:
            log.warning("%s", message)

    def _direct_log(self, message: str) -> bool:
        """A line of the recorder's own in the text log, written at once (writer thread: not through the
        queue, which may be what is full). False when it could not be written."""
        fd = self._fds.get(TEXTLOG_KEY)
        if fd is None:
            return False
        line = {"host_time": hostclock.now(), "source": "recorder", "message": message}
        data = (json.dumps(line) + "\n").encode()
        try:
            _write_all(fd, data)
        except OSError:
            try:
                os.ftruncate(fd, self._sizes[TEXTLOG_KEY])
            except OSError:
                pass
            return False
        self._sizes[TEXTLOG_KEY] += len(data)
        self._unsynced.add(TEXTLOG_KEY)
        return True

    def _sync(self) -> None:
        """fsync the files written since the last time (power-loss safety, about once a second)."""
        for name in list(self._unsynced):
            try:
                os.fsync(self._fds[name])
            except OSError as exc:
                if exc.errno != errno.EINVAL:  # EINVAL: a file system that cannot sync (pipes, some FUSE)
                    self.stats.write_errors += 1
                    self._error(f"recording: fsync of {name} failed ({exc})", exc)
                    continue
            self._unsynced.discard(name)
        self.stats.flushes += 1

    @staticmethod
    def _fsync_dir(folder: Path) -> None:
        try:
            fd = os.open(folder, os.O_RDONLY)
        except OSError:
            return
        try:
            os.fsync(fd)
        except OSError:
            pass
        finally:
            os.close(fd)

    def _write_small(self, name: str, data: bytes, folder: Path | None = None) -> None:
        folder = self.path if folder is None else folder
        tmp = folder / (name + ".tmp")
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, folder / name)
