"""What a recording promises whoever reads it, and what the recorder promises the program that feeds
it: the folder's layout and meta.json, the text log's lines, exact counts of what was written and of
what was dropped (and why, in the recording itself), "block" mode losing nothing, a second stop. These
tests feed the writer directly (no pipeline), so each is fast and deterministic: queue accounting is
checked on a recorder whose writer thread has not started yet."""

from __future__ import annotations

import errno
import json
import os
import socket
import stat
import threading

import h5py
import numpy as np
import pytest

from flytrack_host.recording import Recorder, finalize, load_recording
from flytrack_host.recording.finalize import RecordingError, read_meta, read_raw_table, read_raw_textlog
from flytrack_host.recording.schema import DATA2D, LATENCY, TABLES, dtype_to_json
from flytrack_host.util import hostclock


def _rows(start: int, n: int) -> np.ndarray:
    r = np.zeros(n, dtype=DATA2D)
    r["trigger_frame"] = np.arange(start, start + n)
    r["x_dist"] = r["trigger_frame"] * 0.25
    r["cam_received_timestamp"] = 1000.0 + r["trigger_frame"] * 0.01
    return r


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def test_a_new_recording_says_what_it_is(tmp_path) -> None:
    folder = tmp_path / "day1" / "fly3"  # parents are made
    rec = Recorder(folder, meta={"rig_name": "arena", "fps": 100.0})
    t_before, wall_before = hostclock.now(), hostclock.wall()
    rec.start()
    t_after = hostclock.now()
    try:
        meta = json.loads((folder / "meta.json").read_text())
        assert meta["format"] == "flytrack-recording" and meta["format_version"] == 1
        assert meta["tables"] == {name: dtype_to_json(dt) for name, dt in TABLES.items()}
        assert t_before <= meta["start_time"] <= t_after  # on the host timeline of every row
        assert abs(meta["start_wall_time"] - wall_before) < 60.0
        assert meta["hostname"] == socket.gethostname()
        assert meta["flush_interval_s"] == 1.0  # the default: a power loss loses at most a second
        assert meta["max_queue_bytes"] == 256 << 20
        assert meta["rig_name"] == "arena" and meta["fps"] == 100.0
        assert read_meta(folder) == meta
        # one append-only file per table and the text log, readable by the lab's other accounts
        for name in TABLES:
            st = os.stat(folder / f"{name}.bin")
            assert st.st_size == 0 and stat.S_IMODE(st.st_mode) == 0o644 & ~_umask()
        assert (folder / "textlog.jsonl").exists()
        writer = [t for t in threading.enumerate() if t.name == "flytrack-recorder"]
        assert len(writer) == 1 and writer[0].daemon  # a crashed program still exits
    finally:
        rec.stop(finalize=False)
    with pytest.raises(FileExistsError):  # a recording is never written into another one
        Recorder(folder).start()


def test_text_log_lines_keep_time_source_and_message(tmp_path) -> None:
    rec = Recorder(tmp_path / "r", flush_interval_s=0.05)
    rec.start()
    rec.log("camera 2 late", source="sync", host_time=12.5)
    t0 = hostclock.now()
    rec.log("plain line")
    t1 = hostclock.now()
    rec.stop(finalize=False)
    lines, dropped = read_raw_textlog(tmp_path / "r")
    assert dropped == 0 and rec.stats.log_lines == 2
    assert lines[0] == {"host_time": 12.5, "source": "sync", "message": "camera 2 late"}
    assert lines[1]["source"] == "host" and lines[1]["message"] == "plain line"
    assert t0 <= lines[1]["host_time"] <= t1


def test_stats_count_exactly_what_was_written(tmp_path) -> None:
    folder = tmp_path / "r"
    rec = Recorder(folder, flush_interval_s=0.05)
    rec.start()
    assert rec.last_error is None
    sizes = [3, 7, 1]
    start = 0
    for n in sizes:
        rec.append("data2d_distorted", _rows(start, n))
        start += n
    lat = np.zeros(4, dtype=LATENCY)
    rec.append_many([("latency", lat), ("kalman_estimates", np.zeros(0, TABLES["kalman_estimates"]))])
    rec.log("one")
    rec.stop(finalize=False)
    st = rec.stats
    assert st.rows == {"data2d_distorted": 11, "latency": 4}  # an empty array writes nothing
    assert st.log_lines == 1 and st.write_errors == 0 and st.flushes >= 1
    assert st.dropped_rows == {} and st.dropped_log_lines == 0 and st.queue_full_drops == 0
    on_disk = sum(p.stat().st_size for p in folder.iterdir() if p.suffix in (".bin", ".jsonl"))
    assert st.bytes_written == on_disk == 11 * DATA2D.itemsize + 4 * LATENCY.itemsize + (
        folder / "textlog.jsonl").stat().st_size
    assert rec.queue_bytes == 0 and st.queue_bytes == 0  # everything handed over was written
    assert 1 <= st.max_queue_depth <= len(sizes) + 3
    assert 7 * DATA2D.itemsize <= st.max_queue_bytes <= 11 * DATA2D.itemsize + 4 * LATENCY.itemsize + 64 + 3
    rows, partial = read_raw_table(folder, "data2d_distorted", DATA2D)
    assert partial == 0 and rows["trigger_frame"].tolist() == list(range(11))
    assert rec.last_error is None


def test_a_healthy_recording_logs_no_warning(tmp_path, caplog) -> None:
    rec = Recorder(tmp_path / "r", flush_interval_s=0.05)
    with caplog.at_level("WARNING", logger="flytrack.recording"):
        rec.start()
        rec.append("data2d_distorted", _rows(0, 5))
        rec.stop(finalize=False)
    assert not caplog.records


def test_a_full_queue_drops_counts_and_says_so_in_the_recording(tmp_path) -> None:
    """The writer has not started yet, so nothing leaves the queue: every byte is accounted for."""
    folder = tmp_path / "r"
    rec = Recorder(folder, max_queue_bytes=1000, on_full="drop", flush_interval_s=0.05)
    rec.log("a" * 100)  # a log line counts 64 bytes plus its text
    assert rec.queue_bytes == 164
    big = _rows(0, 1000 // DATA2D.itemsize + 1)
    rec.append("data2d_distorted", big)  # more than the room left: dropped, counted per row
    rec.append_many([("data2d_distorted", big), ("latency", np.zeros(2, LATENCY))])
    assert rec.stats.dropped_rows == {"data2d_distorted": 2 * len(big), "latency": 2}
    assert rec.stats.queue_full_drops == 2 * len(big) + 2
    rec.log("b" * 900)  # 164 + 964 > 1000: dropped
    rec.log("d" * 900)
    assert rec.stats.dropped_log_lines == 2 and rec.stats.queue_full_drops == 2 * len(big) + 4
    rec.log("c" * 10)  # 164 + 74 fits
    assert rec.queue_bytes == 164 + 74
    assert rec.stats.max_queue_bytes == 164 + 74  # the deepest the queue got (drops never queued)
    rec.start()
    rec.stop(finalize=False)
    lines, _ = read_raw_textlog(folder)
    assert [x["message"] for x in lines[:2]] == ["a" * 100, "c" * 10]
    note = [x for x in lines if x["source"] == "recorder"]
    assert len(note) == 1
    assert note[0]["message"] == (
        f"DATA LOST: {2 * len(big)} data2d_distorted rows, 2 latency rows, 2 log lines not recorded "
        f"(recorder queue full (1000 bytes): {4 + 2 * len(big)} dropped so far)")
    assert rec.queue_bytes == 0 and rec.stats.log_lines == 2
    assert rec.stats.max_queue_depth >= 2  # both lines queued before the writer started: one turn


def test_block_mode_waits_for_room_and_loses_nothing(tmp_path) -> None:
    """Offline (re-tracking) the producer waits instead of dropping: the queue never holds more than
    its bound (unless one item alone is bigger, which then goes through alone)."""
    folder = tmp_path / "r"
    limit = 10 * DATA2D.itemsize
    rec = Recorder(folder, max_queue_bytes=limit, on_full="block", flush_interval_s=0.05)
    rec.poll_s = 0.002  # a quick writer: 60 waits for it stay short
    rec.start()
    for k in range(60):
        rec.append("data2d_distorted", _rows(5 * k, 5))
    rec.append("data2d_distorted", _rows(300, 25))  # alone bigger than the bound: not a deadlock
    rec.stop(finalize=False)
    rows, _ = read_raw_table(folder, "data2d_distorted", DATA2D)
    assert rows["trigger_frame"].tolist() == list(range(325))
    assert rec.stats.dropped_rows == {} and rec.stats.queue_full_drops == 0
    assert rec.stats.max_queue_bytes <= max(limit, 25 * DATA2D.itemsize)
    assert rec.stats.max_queue_bytes <= limit or rec.stats.max_queue_bytes == 25 * DATA2D.itemsize


def test_bad_arguments_are_clear(tmp_path) -> None:
    with pytest.raises(ValueError, match="^on_full must be 'drop' or 'block', not 'wait'$"):
        Recorder(tmp_path / "r", on_full="wait")
    rec = Recorder(tmp_path / "r", on_full="block")
    with pytest.raises(TypeError, match=r"^rows for latency have dtype \[.*\], expected \[.*\]$"):
        rec.append("latency", _rows(0, 1))
    with pytest.raises(TypeError, match=r"^rows for data2d_distorted have dtype \[.*\], expected \[.*\]$"):
        rec.append_many([("data2d_distorted", np.zeros(1, LATENCY))])


def test_stop_twice_gives_the_same_file(tmp_path) -> None:
    rec = Recorder(tmp_path / "r", flush_interval_s=0.05, meta={"fps": 50.0})
    rec.start()
    rec.append("data2d_distorted", _rows(0, 4))
    h5 = rec.stop()
    assert h5 == tmp_path / "r" / "recording.h5" and h5.exists()
    assert rec.stop() == h5 and rec.queue_bytes == 0
    assert len(load_recording(h5).table("data2d_distorted")) == 4
    raw = Recorder(tmp_path / "raw", flush_interval_s=0.05)
    raw.start()
    assert raw.stop(finalize=False) is None and raw.stop() is None  # not finalised: nothing to give


# ---- finalising ----------------------------------------------------------------------------------------


def test_finalize_keeps_meta_files_and_the_latest_time(tmp_path) -> None:
    folder = tmp_path / "r"
    rec = Recorder(folder, flush_interval_s=0.05, meta={"rig_name": "arena", "fps": 100.0})
    rec.start()
    rec.attach("rig.toml", b"[rig]\nname = 'arena'\n")
    rec.attach("calibration.xml", b"<cal/>")
    rec.attach("background_2.png", b"\x89PNG")
    rec.append("data2d_distorted", _rows(0, 30))  # cam_received_timestamp up to 1000.29
    lat = np.zeros(3, LATENCY)
    lat["trigger_time"] = [5.0, 5.01, 5.02]
    lat["last_arrival"] = lat["trigger_time"] + 0.002
    lat["estimate_time"] = [5.003, np.nan, 5.025]
    rec.append("latency", lat)
    rec.log("hello", host_time=999.0)
    rec.stop(finalize=False)
    (folder / "calibration.xml.tmp").write_bytes(b"half")  # a file being written: not kept
    (folder / "notes.txt").write_bytes(b"not the recording's")
    report = finalize(folder)
    assert report.h5_path == folder / "recording.h5"
    assert report.rows["data2d_distorted"] == 30 and report.rows["latency"] == 3
    assert report.partial_bytes_dropped == {} and report.log_lines == 1 and report.log_lines_dropped == 0
    assert report.last_host_time == pytest.approx(1000.29)  # the latest time in any table
    with h5py.File(report.h5_path, "r") as h5:
        assert sorted(h5["files"]) == ["background_2.png", "calibration.xml", "rig.toml"]
        assert bytes(h5["files"]["calibration.xml"][...]) == b"<cal/>"
        assert json.loads(h5.attrs["rig_name"]) == "arena" and json.loads(h5.attrs["format_version"]) == 1
        assert "tables" not in h5.attrs
        assert json.loads(h5.attrs["recovered_partial_bytes"]) == {}
        tl = h5["textlog"][...]
        assert tl["host_time"].tolist() == [999.0] and tl["message"][0].decode() == "hello"
        g = h5["latency_histogram"]
        assert int(g["counts"][...].sum()) == 2  # the NaN estimate is not a latency
        assert len(g["edges_ms"]) == len(g["counts"]) + 1
    rec2 = load_recording(report.h5_path)
    assert rec2.calibration == ("calibration.xml", b"<cal/>") and rec2.fps == 100.0


def test_finalize_drops_a_cut_row_and_a_cut_line_and_counts_them(tmp_path) -> None:
    folder = tmp_path / "r"
    rec = Recorder(folder, flush_interval_s=0.05)
    rec.start()
    rec.append("data2d_distorted", _rows(0, 6))
    rec.log("whole line")
    rec.stop(finalize=False)
    with open(folder / "data2d_distorted.bin", "ab") as f:
        f.write(b"\x07" * 11)  # a row cut by a crash
    with open(folder / "textlog.jsonl", "ab") as f:
        f.write(b'{"host_time": 3.0, "sou')  # a line cut by a crash
    out = tmp_path / "elsewhere" / "r.h5"
    out.parent.mkdir()
    report = finalize(folder, out)  # e.g. to another disk
    assert report.h5_path == out and out.exists() and not (folder / "recording.h5").exists()
    assert report.rows["data2d_distorted"] == 6 and report.partial_bytes_dropped == {"data2d_distorted": 11}
    assert report.log_lines == 1 and report.log_lines_dropped == 1
    assert not out.with_name(out.name + ".tmp").exists()
    with h5py.File(out, "r") as h5:
        assert json.loads(h5.attrs["recovered_partial_bytes"]) == {"data2d_distorted": 11}
        assert h5["data2d_distorted"]["trigger_frame"].tolist() == list(range(6))


def test_a_folder_that_is_not_a_recording_is_named(tmp_path) -> None:
    with pytest.raises(RecordingError, match=rf"^{tmp_path}: no meta.json; this is not a FlyTrack recording folder$"):
        read_meta(tmp_path)
    assert read_raw_textlog(tmp_path) == ([], 0)  # no text log: nothing, nothing dropped
    (tmp_path / "meta.json").write_text("{not json")
    with pytest.raises(RecordingError, match=rf"^{tmp_path}/meta.json: unreadable \(Expecting"):
        finalize(tmp_path)
    empty, partial = read_raw_table(tmp_path, "latency", LATENCY)  # a table never written: empty
    assert len(empty) == 0 and partial == 0 and empty.dtype == LATENCY


def test_write_errors_are_counted_exactly_said_once_and_noted_in_the_recording(tmp_path, caplog) -> None:
    """Two files of a running recording are pointed at /dev/full (a real ENOSPC from the kernel):
    each failed write is one write error, its rows or lines are lost and counted, the first error of
    the episode is logged at once with what was lost; once the files are back, writing goes on, that is
    said, and the recording's text log says what was lost and why."""
    folder = tmp_path / "r"
    rec = Recorder(folder, flush_interval_s=0.05)
    rec.start()
    real = {k: rec._fds[k] for k in ("data2d_distorted", "__textlog__")}
    full = os.open("/dev/full", os.O_WRONLY)
    try:
        with caplog.at_level("WARNING", logger="flytrack.recording"):
            rec._fds["data2d_distorted"] = full
            rec.append("data2d_distorted", _rows(0, 3))
            assert _wait(lambda: rec.stats.write_errors == 1)
            assert rec.stats.dropped_rows == {"data2d_distorted": 3}
            assert rec.last_error == "recording: cannot write data2d_distorted (No space left on device); 3 rows lost"
            rec._fds["__textlog__"] = full
            rec.log("first")
            rec.log("second")
            assert _wait(lambda: rec.stats.dropped_log_lines == 2)
            assert rec.last_error == "recording: cannot write __textlog__ (No space left on device); 2 lines lost"
            rec._fds.update(real)  # the disk has room again
            rec.append("data2d_distorted", _rows(3, 4))
            assert _wait(lambda: rec.stats.rows.get("data2d_distorted") == 4)
            rec.stop(finalize=False)
    finally:
        os.close(full)
    st = rec.stats
    assert st.write_errors == 2 and st.dropped_rows == {"data2d_distorted": 3} and st.dropped_log_lines == 2
    assert st.queue_full_drops == 0
    msgs = [(r.levelname, r.getMessage()) for r in caplog.records if r.name == "flytrack.recording"]
    assert msgs[0] == ("ERROR", "recording: cannot write data2d_distorted (No space left on device); 3 rows lost")
    assert ("WARNING", "recording: writing again after write errors (2 so far)") in msgs
    assert sum(level == "ERROR" for level, _ in msgs) == 1  # one episode, logged once
    rows, partial = read_raw_table(folder, "data2d_distorted", DATA2D)
    assert partial == 0 and rows["trigger_frame"].tolist() == [3, 4, 5, 6]
    lines, _ = read_raw_textlog(folder)
    notes = [x["message"] for x in lines if x["source"] == "recorder"]
    assert notes and notes[-1].startswith("DATA LOST: ")
    assert "2 write errors so far, last: recording: cannot " in notes[-1]
    assert sum(int(n.split()[2]) for n in notes if "data2d_distorted rows" in n) == 3
    assert all(isinstance(x["host_time"], float) for x in lines)


def _wait(cond, timeout: float = 10.0) -> bool:
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.005)
    return cond()


def test_finalize_reads_every_time_column_and_every_whole_log_line(tmp_path) -> None:
    from flytrack_host.recording.schema import CAMERA_STATUS, TRIGGER_CLOCK

    folder = tmp_path / "r"
    rec = Recorder(folder, flush_interval_s=0.05)
    rec.start()
    rec.stop(finalize=False)
    latest = {}
    for table, dt, col, t in (("camera_status", CAMERA_STATUS, "host_time", 2000.0),
                              ("trigger_clock_info", TRIGGER_CLOCK, "stop_timestamp", 3000.0),
                              ("latency", LATENCY, "estimate_time", 4000.0)):
        r = np.zeros(2, dt)
        r[col] = [t - 1.0, t]
        with open(folder / f"{table}.bin", "ab") as f:
            f.write(r.tobytes())
        latest[table] = t
        assert finalize(folder).last_host_time == t  # each table's own time column counts
        (folder / "recording.h5").unlink()
    with open(folder / "textlog.jsonl", "ab") as f:
        f.write(b'{"host_time": 1.0}\n\n{"host_time": 2.0, "source": "edge", "message": "m"}\n{"cut\n{"cut2\n')
    report = finalize(folder)
    assert report.log_lines == 2 and report.log_lines_dropped == 2  # a blank line is no line; both cut ones count
    with h5py.File(report.h5_path, "r") as h5:
        tl = h5["textlog"][...]
        assert [(x["source"].decode(), x["message"].decode()) for x in tl] == [("", ""), ("edge", "m")]


def test_finalize_onto_a_full_disk_says_how_much_is_needed_and_leaves_nothing(tmp_path) -> None:
    import shutil

    from flytrack_host.util.testing import small_tmpfs

    folder = tmp_path / "r"
    rec = Recorder(folder, flush_interval_s=0.05)
    rec.start()
    rec.append("data2d_distorted", _rows(0, 30000))  # ~3.4 MB
    rec.stop(finalize=False)
    (folder / "calibration.xml.tmp").write_bytes(bytes(5 << 20))  # a half-written file: not copied
    need = sum(p.stat().st_size for p in folder.iterdir() if p.suffix != ".tmp") + (1 << 20)
    with small_tmpfs(tmp_path / "small", "2m") as disk:
        free = shutil.disk_usage(disk).free
        with pytest.raises(OSError) as exc:
            finalize(folder, disk / "r.h5")
        assert exc.value.errno == errno.ENOSPC
        assert exc.value.strerror == (f"not enough space: about {need / 1e6:.1f} MB needed, {free / 1e6:.1f} MB "
                                      f"free on the disk of {disk} (the disk is full)")
        assert list(disk.iterdir()) == []  # no half file
    assert finalize(folder).rows["data2d_distorted"] == 30000  # the raw files are all still there
