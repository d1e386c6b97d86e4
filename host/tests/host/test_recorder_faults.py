"""The recorder under faults: a failing disk is reported at once and never corrupts a table, the
queue is bounded (drops counted and written into the recording), files are fsynced every flush
interval (GitHub issue 5, A4 and A7). The full disk is faked at the one write seam
(`writer._write_all`): this machine has no small file system to fill."""

from __future__ import annotations

import errno
import logging
import os
import threading
import time

import numpy as np

from flytrack_host.pipeline import HostPipeline
from flytrack_host.recording import Recorder, load_recording
from flytrack_host.recording import writer as writer_mod
from flytrack_host.recording.schema import DATA2D


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


class _FullDisk:
    """Fails writes to one file with ENOSPC while `on`, after writing part of the data (as a disk
    filling up mid-write does)."""

    def __init__(self, real):
        self.real = real
        self.on = False
        self.fd: int | None = None
        self.failures = 0

    def __call__(self, fd, data):
        if self.on and fd == self.fd:
            self.failures += 1
            half = memoryview(data)[: max(1, len(data) // 2 + 3)]  # not a whole number of rows
            os.write(fd, half)
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return self.real(fd, data)


def test_disk_full_is_reported_at_once_and_the_table_stays_whole(tmp_path, monkeypatch, caplog):
    disk = _FullDisk(writer_mod._write_all)
    monkeypatch.setattr(writer_mod, "_write_all", disk)
    rec = Recorder(tmp_path / "r", flush_interval_s=0.05)
    rec.start()
    disk.fd = rec._fds["data2d_distorted"]
    with caplog.at_level(logging.ERROR, logger="flytrack.recording"):
        for k in range(10):
            rec.append("data2d_distorted", _rows(k, 1))
        assert _wait(lambda: rec.stats.rows.get("data2d_distorted") == 10)
        disk.on = True
        for k in range(10, 20):
            rec.append("data2d_distorted", _rows(k, 1))
            time.sleep(0.01)  # several writer turns, several failed writes
        # Surfaced while running, not at stop():
        assert _wait(lambda: sum(rec.stats.dropped_rows.values()) == 10)
        assert rec.stats.write_errors >= 2 and disk.failures == rec.stats.write_errors
        assert "No space left" in (rec.last_error or "")
        errors = [r for r in caplog.records if r.name == "flytrack.recording" and r.levelno >= logging.ERROR]
        assert len(errors) == 1  # logged once per episode, not once per write
        disk.on = False
        for k in range(20, 30):
            rec.append("data2d_distorted", _rows(k, 1))
        h5 = rec.stop()
    assert h5 is not None
    back = load_recording(tmp_path / "r")
    d2 = back.table("data2d_distorted")
    # The partial writes were undone: the rows around the failure are intact and aligned.
    assert d2["trigger_frame"].tolist() == list(range(10)) + list(range(20, 30))
    assert np.allclose(d2["x_dist"], d2["trigger_frame"] * 0.5)
    lost = [r["message"] for r in back.textlog if r["message"].startswith("DATA LOST")]
    assert sum(int(m.split()[2]) for m in lost) == 10 and all("data2d_distorted rows" in m for m in lost)
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


def test_pipeline_status_shows_write_errors_and_goes_on(helpers, tmp_path, monkeypatch):
    disk = _FullDisk(writer_mod._write_all)
    monkeypatch.setattr(writer_mod, "_write_all", disk)
    fps = 200.0
    pipe = HostPipeline(helpers.make_rig(2, fps=fps), cameras={0: None, 1: None}, tracker_factory=helpers.factory,
                        recording_path=tmp_path / "r", bind="127.0.0.1:0", keep_results=True)
    pipe.start()
    assert "rec queue" in pipe.status_line()
    disk.fd = pipe.recorder._fds["data2d_distorted"]
    disk.on = True
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
    finally:
        summary = pipe.stop()
    assert running and "WRITE ERRORS" in status and "No space left" in status and "LOST" in status
    assert summary["frames_tracked"] == 40
    assert summary["recorder"]["write_errors"] > 0
    assert summary["recorder"]["dropped_rows"]["data2d_distorted"] == 2 * 2 * 40
    rec = load_recording(summary["recording"])
    assert len(rec.table("kalman_estimates")) == 40  # the other tables were written
    assert any(r["message"].startswith("DATA LOST") for r in rec.textlog)
