"""The recorder under faults: a failing disk is reported at once and never corrupts a table, the
queue is bounded (drops counted and written into the recording), files are fsynced every flush
interval (GitHub issue 5, A4 and A7). The full disk is real: a 4 MB tmpfs mounted by the test and filled
with a ballast file (root only; skipped with the reason otherwise). A hanging disk is the one fault that
is simulated, at the write seam `writer._write_all`."""

from __future__ import annotations

import errno
import logging
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from flytrack_host.pipeline import HostPipeline
from flytrack_host.recording import Recorder, load_recording
from flytrack_host.recording import writer as writer_mod
from flytrack_host.recording.schema import DATA2D
from flytrack_host.util.testing import small_tmpfs


def _rows(start: int, n: int) -> np.ndarray:
    r = np.zeros(n, dtype=DATA2D)
    r["trigger_frame"] = np.arange(start, start + n)
    r["x_dist"] = r["trigger_frame"] * 0.5
    return r


def _wait(cond, timeout: float = 3.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.01)
    return cond()


@pytest.fixture
def small_disk(tmp_path):
    """A 4 MB tmpfs (finalising wants 1 MB of slack)."""
    with small_tmpfs(tmp_path / "small", "4m") as mnt:
        yield mnt


def _fill(disk, leave: int = 0) -> Path:
    """Fill the file system with a ballast file, then give back `leave` bytes (tmpfs frees whole pages)."""
    ballast = disk / "ballast"
    fd = os.open(ballast, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    try:
        for chunk in (1 << 16, 4096, 1):
            block = b"\0" * chunk
            while True:
                try:
                    if os.write(fd, block) < chunk:
                        break
                except OSError as e:
                    assert e.errno == errno.ENOSPC
                    break
        if leave:
            os.ftruncate(fd, max(0, os.fstat(fd).st_size - leave))
    finally:
        os.close(fd)
    return ballast


def test_disk_full_is_reported_at_once_and_the_table_stays_whole(small_disk, caplog):
    rec = Recorder(small_disk / "r", flush_interval_s=0.05)
    rec.start()
    with caplog.at_level(logging.WARNING, logger="flytrack.recording"):
        for k in range(10):
            rec.append("data2d_distorted", _rows(k, 1))
        assert _wait(lambda: rec.stats.rows.get("data2d_distorted") == 10)
        assert _wait(lambda: rec.queue_bytes == 0)
        # One page free: the rows that follow fill it, one write stops part-way through a row, then every
        # write fails.
        ballast = _fill(small_disk, leave=4096)
        for k in range(10, 200):
            rec.append("data2d_distorted", _rows(k, 1))
            if k % 10 == 0:
                time.sleep(0.01)  # several writer turns, several failed writes
        # Surfaced while running, not at stop():
        assert _wait(lambda: rec.stats.write_errors >= 2)
        assert _wait(lambda: rec.stats.rows["data2d_distorted"] + rec.stats.dropped_rows["data2d_distorted"] == 200)
        assert "No space left" in (rec.last_error or "")
        errors = [r for r in caplog.records if r.name == "flytrack.recording" and r.levelno >= logging.ERROR]
        back_again = [r for r in caplog.records if r.name == "flytrack.recording"
                      and r.getMessage().startswith("recording: writing again after write errors")]
        # Logged once per episode, not once per write. An episode ends when a write succeeds: on a loaded
        # host the writer takes bigger batches, and a small one may still fit in room a rolled-back write
        # gave back (seen: 3 episodes, 129 rows in 3 failed writes, at load 10).
        # (the last batch may have fitted: then the episodes all ended, as many recoveries as errors)
        assert len(errors) >= 1 and len(errors) - len(back_again) in (0, 1)
        assert len(errors) <= rec.stats.write_errors
        ballast.unlink()
        for k in range(200, 210):
            rec.append("data2d_distorted", _rows(k, 1))
        h5 = rec.stop()
    assert h5 is not None
    back = load_recording(small_disk / "r")
    frames = back.table("data2d_distorted")["trigger_frame"].tolist()
    kept = frames[:-10]
    # Everything before the disk filled and after it was freed is there; in between, some rows fitted (in the
    # freed page, or in room a rolled-back write gave back) and the rest are counted as lost. A row cut by
    # the full disk was undone, so every row is whole, in order and aligned.
    assert frames[-10:] == list(range(200, 210)) and kept[:10] == list(range(10))
    assert 10 < len(kept) < 200 and kept == sorted(set(kept))
    d2 = back.table("data2d_distorted")
    assert np.allclose(d2["x_dist"], d2["trigger_frame"] * 0.5)
    lost = [r["message"] for r in back.textlog if r["message"].startswith("DATA LOST")]
    assert sum(int(m.split()[2]) for m in lost) == 200 - len(kept) and all("data2d_distorted rows" in m for m in lost)
    assert "No space left" in lost[0]


def test_queue_is_bounded_and_drops_are_recorded(tmp_path, monkeypatch):
    gate = threading.Event()
    real = writer_mod._write_all

    def stuck(fd, data):  # a disk that hangs until the gate opens
        gate.wait(5.0)
        return real(fd, data)

    monkeypatch.setattr(writer_mod, "_write_all", stuck)
    row_bytes = DATA2D.itemsize
    rec = Recorder(tmp_path / "r", flush_interval_s=0.05, max_queue_bytes=50 * row_bytes)
    rec.start()
    rec.append("data2d_distorted", _rows(0, 1))
    assert _wait(lambda: rec.queue_bytes == 0)  # the writer took it and hangs in the write
    for k in range(1, 201):
        rec.append("data2d_distorted", _rows(k, 1))  # never blocks
    assert rec.queue_bytes <= 50 * row_bytes
    assert rec.stats.dropped_rows["data2d_distorted"] == 150
    assert rec.stats.max_queue_bytes <= 50 * row_bytes
    gate.set()
    rec.stop()
    back = load_recording(tmp_path / "r")
    assert back.table("data2d_distorted")["trigger_frame"].tolist() == list(range(51))
    assert any(r["message"].startswith("DATA LOST: 150 data2d_distorted rows") and "queue full" in r["message"]
               for r in back.textlog)


def test_files_are_fsynced_every_flush_interval(tmp_path, monkeypatch):
    synced: list[tuple[float, int]] = []
    real_fsync = os.fsync

    def fsync(fd):
        synced.append((time.monotonic(), fd))
        return real_fsync(fd)

    monkeypatch.setattr(writer_mod.os, "fsync", fsync)
    rec = Recorder(tmp_path / "r", flush_interval_s=0.1)
    rec.start()
    fd = rec._fds["data2d_distorted"]
    t0 = time.monotonic()
    for k in range(40):
        rec.append("data2d_distorted", _rows(k, 1))
        time.sleep(0.01)
    times = [t - t0 for t, f in synced if f == fd]
    rec.stop(finalize=False)
    assert len(times) >= 2, times  # while running (not only at stop), about every 0.1 s
    assert times[0] < 0.35


def test_pipeline_status_shows_write_errors_and_goes_on(helpers, small_disk):
    fps = 200.0
    pipe = HostPipeline(helpers.make_rig(2, fps=fps), cameras={0: None, 1: None}, tracker_factory=helpers.factory,
                        recording_path=small_disk / "r", bind="127.0.0.1:0", keep_results=True)
    pipe.start()
    assert "rec queue" in pipe.status_line()
    assert _wait(lambda: pipe.recorder.queue_bytes == 0)
    ballast = _fill(small_disk)
    edges = [helpers.EdgeSim(i, pipe.address, edge_trigger=True) for i in range(2)]
    try:
        t0 = time.monotonic()
        for k in range(40):
            for e in edges:
                e.send(k)
            time.sleep(max(0.0, t0 + (k + 1) / fps - time.monotonic()))
        assert _wait(lambda: pipe.recorder.stats.write_errors > 0)
        status = pipe.status_line()
        running = pipe.running
        ballast.unlink()  # room again for the tables written from here on and the final file
    finally:
        summary = pipe.stop()
    assert running and "WRITE ERRORS" in status and "No space left" in status and "LOST" in status
    assert summary["frames_tracked"] == 40
    assert summary["recorder"]["write_errors"] > 0
    rec = load_recording(summary["recording"])
    d2 = summary["recorder"]["dropped_rows"]
    assert d2.get("data2d_distorted", 0) > 0
    # Nothing silently lost: every 2D row is either in the recording or counted as dropped.
    assert len(rec.table("data2d_distorted")) + d2["data2d_distorted"] == 2 * 2 * 40
    estimates = sum(len(r.estimates) for r in pipe.results)
    assert estimates >= 30
    assert len(rec.table("kalman_estimates")) + d2.get("kalman_estimates", 0) == estimates
    assert any(r["message"].startswith("DATA LOST") for r in rec.textlog)
