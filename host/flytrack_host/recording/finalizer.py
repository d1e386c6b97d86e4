"""Finalise the closed parts of a recording in a background process, one at a time, in order.

A process and not a thread: writing HDF5 holds Python's GIL in long C calls (an 8 MB chunk at a
time), which would hold up the tracking thread for milliseconds at a time. The process runs at a lower
priority (nice 10), dies with the host (util.children), and a part whose finalising failed or was cut
keeps its raw files: `Recorder.stop` finalises it again, or `flytrack recording recover` does later.

`poll()` is called by the recorder's writer thread on each of its turns; it never blocks.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import tempfile
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

from flytrack_host.recording.schema import H5_NAME
from flytrack_host.util import children

log = logging.getLogger("flytrack.recording")
NICE = 10
FINALIZE_MAIN = "import sys; from flytrack_host.recording.finalize import main; sys.exit(main())"


def raw_bytes(part: Path) -> int:
    """Bytes of a part's raw files (what finalising it reads)."""
    return sum(p.stat().st_size for p in Path(part).iterdir() if p.is_file() and p.name != H5_NAME
               and not p.name.endswith(".tmp"))


@dataclass
class FinalizerStats:
    parts: int = 0  # finalised in the background
    bytes: int = 0  # raw bytes of those parts
    seconds: float = 0.0  # their processes' wall time, summed
    failures: int = 0
    last_error: str | None = None
    done: list[str] = field(default_factory=list)  # part folder names, in the order they finished


class PartFinalizer:
    def __init__(self, on_done=None) -> None:  # on_done(part, seconds, nbytes, error or None)
        self._todo: deque[Path] = deque()
        self._proc: subprocess.Popen | None = None
        self._current: Path | None = None
        self._started = 0.0
        self._err = None
        self.on_done = on_done
        self.stats = FinalizerStats()

    def submit(self, part: Path) -> None:
        self._todo.append(Path(part))
        self.poll()

    @property
    def busy(self) -> bool:
        """A part is being finalised or waits for it."""
        return self._proc is not None or bool(self._todo)

    def pending(self) -> list[Path]:
        """Parts not finalised by this finalizer yet: the one under way first."""
        return ([self._current] if self._current is not None else []) + list(self._todo)

    def poll(self) -> None:
        if self._proc is not None:
            rc = self._proc.poll()
            if rc is None:
                return
            self._reap(rc)
        if self._todo:
            self._start(self._todo.popleft())

    def _start(self, part: Path) -> None:
        self._err = tempfile.TemporaryFile()
        self._current, self._started = part, time.monotonic()
        try:
            self._proc = children.popen([sys.executable, "-c", FINALIZE_MAIN, str(part)],
                                        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=self._err)
        except OSError as exc:  # cannot start a process (out of memory, too many): stop() does it
            self._proc = None
            self._finish(part, 0.0, f"cannot start the finaliser: {exc}")
            return
        try:
            os.setpriority(os.PRIO_PROCESS, self._proc.pid, NICE)
        except OSError:
            pass

    def _reap(self, rc: int) -> None:
        part, dt = self._current, time.monotonic() - self._started
        assert part is not None
        err = None
        if rc != 0 or not (part / H5_NAME).exists():
            assert self._err is not None
            self._err.seek(0)
            tail = self._err.read()[-2000:].decode(errors="replace").strip().splitlines()
            err = f"exit {rc}: {tail[-1] if tail else 'no message'}"
        self._proc = None
        self._finish(part, dt, err)

    def _finish(self, part: Path, dt: float, err: str | None) -> None:
        if self._err is not None:
            self._err.close()
            self._err = None
        self._current = None
        nbytes = raw_bytes(part) if part.exists() else 0
        if err is None:
            self.stats.parts += 1
            self.stats.bytes += nbytes
            self.stats.seconds += dt
            self.stats.done.append(part.name)
        else:
            self.stats.failures += 1
            self.stats.last_error = f"{part.name}: {err}"
            log.error("recording: finalising %s in the background failed (%s); its raw files are kept and it "
                      "is finalised at stop (or by `flytrack recording recover`)", part, err)
        if self.on_done is not None:
            self.on_done(part, dt, nbytes, err)

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until every submitted part is done (True) or `timeout` passed (False)."""
        end = None if timeout is None else time.monotonic() + timeout
        while self.busy:
            if end is not None and time.monotonic() >= end:
                return False
            self.poll()
            if self._proc is not None:
                try:
                    self._proc.wait(0.05)
                except subprocess.TimeoutExpired:
                    pass
        return True

    def cancel(self) -> list[Path]:
        """Forget the parts not started, end the one under way; returns them all (not finalised)."""
        left = self.pending()
        self._todo.clear()
        if self._proc is not None:
            self._proc.kill()
            self._proc.wait()
            self._proc = None
        if self._err is not None:
            self._err.close()
            self._err = None
        self._current = None
        return left
