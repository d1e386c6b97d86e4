"""The writer's side of a recording in parts (parts.py): a new part between two queued items, the
closed part handed to the background finaliser, and what stop() still has to finalise.

A mixin of `writer.Recorder` (its writer thread calls `_part_due` and `_roll`; nothing here runs on
the thread that appends rows).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from flytrack_host.recording.finalizer import raw_bytes
from flytrack_host.recording.parts import part_dirs, part_name
from flytrack_host.recording.schema import H5_NAME, META_NAME, TABLES
from flytrack_host.util import hostclock

log = logging.getLogger("flytrack.recording")
ROLL_RETRY_S = 5.0  # a new part that could not be made (a full disk) is tried again this much later
NEW_PART = object()  # queued by new_part(): the writer starts a new part there


class PartsMixin:
    """Needs the Recorder's state: path, parts, part_index, stats, _part_dir, _part_started, _part_base,
    _part_lock, _attached, _header, _meta, _roll_retry_at, _finalizer, _fds, _sizes, _unsynced, _q,
    _put_lock; and its _open_files, _write_all, _write_small, _fsync_dir, _sync, _note_drops, _direct_log,
    _error."""

    def _make_part(self, folder: Path, index: int) -> tuple[dict[str, int], dict[str, int]]:
        """A new part: its folder, meta.json, the attached files, the raw files with the header rows so far.
        On failure nothing of it is left (so it can be tried again); a folder a failed try left is replaced."""
        if folder.exists() and not (folder / META_NAME).exists():
            shutil.rmtree(folder)
        folder.mkdir(exist_ok=False)
        fds: dict[str, int] = {}
        try:
            carried = {name: sum(len(b) for b in chunks) // TABLES[name].itemsize
                       for name, chunks in self._header.items()}
            meta = {**self._meta, "part": index, "part_start_time": hostclock.now(),
                    "part_start_wall_time": hostclock.wall(), "carried_rows": carried}
            self._write_small(META_NAME, json.dumps(meta, indent=1).encode(), folder)
            for name, data in self._attached.items():
                self._write_small(name, data, folder)
            fds, sizes = self._open_files(folder)
            for name, chunks in self._header.items():
                data = b"".join(chunks)
                self._write_all(fds[name], data)
                sizes[name] += len(data)
            for fd in fds.values():
                os.fsync(fd)
            self._fsync_dir(folder)
            self._fsync_dir(folder.parent)
            return fds, sizes
        except BaseException:
            for fd in fds.values():
                os.close(fd)
            shutil.rmtree(folder, ignore_errors=True)
            raise

    def new_part(self) -> None:
        """Start a new part after what is queued so far (a recording in parts; e.g. a re-track mirrors
        its source's parts)."""
        if self.parts is None:
            raise RuntimeError("new_part: this recorder does not record in parts")
        with self._put_lock:
            self._q.append((NEW_PART, 0))

    def _payload(self) -> int:
        """Bytes written to the part being written, beyond what it started with."""
        return sum(self._sizes.values()) - self._part_base

    def _part_due(self, pending: int, nbytes: int, by_time: bool = False) -> bool:
        """Time for a new part: before an item of `nbytes` that would take the part (its `pending` bytes
        not written yet included) past its size, or (`by_time`) once it is old enough; never for an empty
        part, nor while a failed roll waits to be tried again."""
        p = self.parts
        assert p is not None
        have = self._payload() + pending
        if have <= 0 or time.monotonic() < self._roll_retry_at:
            return False
        if by_time:
            return p.seconds is not None and time.monotonic() - self._part_started >= p.seconds
        return p.bytes is not None and have + nbytes > p.bytes

    def _roll(self, asked: bool = False) -> bool:
        """Close the part being written (its files synced) and go on in a new one; the closed part goes
        to the background finaliser. A new part that cannot be made (a full disk) is counted and logged,
        the writer goes on in the old part and tries again ROLL_RETRY_S later: nothing is lost."""
        if self._payload() <= 0 and not asked:
            return False
        old_dir, index = self._part_dir, self.part_index + 1
        self._note_drops(force=True)  # in the part the drops happened in
        try:
            with self._part_lock:
                new_dir = self.path / part_name(index)
                fds, sizes = self._make_part(new_dir, index)
                self._part_dir = new_dir
        except OSError as exc:
            self.stats.roll_errors += 1
            self._roll_retry_at = time.monotonic() + ROLL_RETRY_S
            self.last_error = (f"recording: cannot start part {index} ({os.strerror(exc.errno) if exc.errno else exc});"
                               f" going on in {old_dir.name}, trying again every {ROLL_RETRY_S:g} s")
            if self._roll_failures == 0:  # once per episode
                log.error("%s", self.last_error)
            self._roll_failures += 1
            return False
        if self._roll_failures:
            log.warning("recording: part %d started after %d failed tries", index, self._roll_failures)
            self._roll_failures = 0
        self._sync()
        closed = sum(self._sizes.values())
        age = time.monotonic() - self._part_started
        for fd in self._fds.values():
            os.close(fd)
        self._fds, self._sizes, self._unsynced = fds, sizes, set()
        self._part_base = sum(sizes.values())
        self.part_index = self.stats.parts = index
        self._part_started = time.monotonic()
        self.stats.largest_part_bytes = max(self.stats.largest_part_bytes, closed)
        self._direct_log(f"part {index} started: {old_dir.name} closed after {age:.1f} s, "
                         f"{closed / 1e6:.1f} MB{' (asked for)' if asked else ''}")
        if self._finalizer is not None:
            self._finalizer.submit(old_dir)
        return True

    def _part_finalised(self, part: Path, seconds: float, nbytes: int, error: str | None) -> None:
        if error is None:
            self.stats.parts_finalised_background += 1
            self.stats.finalise_background_s += seconds
            msg = f"{part.name} finalised in the background: {nbytes / 1e6:.1f} MB in {seconds:.1f} s"
        else:
            msg = f"{part.name}: finalising in the background failed ({error}); finalised at stop instead"
        self._direct_log(msg)

    def _stop_parts(self, _finalize: Callable[[Path], Any], t0: float) -> Path:
        """stop(), in parts: wait for the background finaliser, finalise what has no HDF5 file."""
        waited: list[Path] = []
        if self._finalizer is not None:  # the part under way (and any waiting): stop waits for them
            waited = self._finalizer.pending()
            self.stats.finalise_at_stop_bytes = sum(raw_bytes(p) for p in waited if p.exists())
            self._finalizer.wait()
        first_error: BaseException | None = None
        for part in part_dirs(self.path):
            if (part / H5_NAME).exists():
                continue
            try:
                rep = _finalize(part)
                if part not in waited:  # (counted already)
                    self.stats.finalise_at_stop_bytes += rep.raw_bytes
            except Exception as exc:  # the others still get finalised; the raw files stay for `recover`
                first_error = first_error or exc
        self.stats.finalise_at_stop_s = time.monotonic() - t0
        if first_error is not None:
            raise first_error
        return self.path

    def _finished_path(self) -> Path | None:
        if self.parts is None:
            return self.path / H5_NAME if (self.path / H5_NAME).exists() else None
        parts = part_dirs(self.path)
        return self.path if parts and all((p / H5_NAME).exists() for p in parts) else None
