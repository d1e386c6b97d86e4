"""flytrack-edge with event sources (--source events | dvs128), plain and ASan + UBSan builds: an
event file goes out as DVS_CLUSTERS slices (protocol/SPEC.md 1.6) whose times match the slicing of
the file's events, STATUS counts every event; a damaged file sends every event before the damage
and exits 3 naming the offset; no DVS128 is a clear error. The DVS128 USB path itself (split words,
wrap/reset, garbage, unplug/replug) is tested in C through its seam (edge_dvs_source)."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import numpy as np

from flytrack_host.events import EVENT_DTYPE, EventFileError, read_events, write_events
from flytrack_host.protocol import DvsClusters, EdgeStatus

from .conftest import free_udp_port


def events(n: int, seed: int = 0, span_us: int = 200_000) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(0, span_us, n)) + 5000
    ev["x"] = rng.integers(0, 128, n)
    ev["y"] = rng.integers(0, 128, n)
    ev["p"] = rng.integers(0, 2, n)
    return ev


def slices(t: np.ndarray, slice_us: int) -> list[tuple[int, int]]:
    """(first, last) event time of each slice: a slice ends before the first event >= its start +
    slice_us (the daemon's rule)."""
    out, start, last = [], None, None
    for v in t.tolist():
        if start is not None and v - start >= slice_us:
            out.append((start, last))
            start = None
        if start is None:
            start = v
        last = v
    if start is not None:
        out.append((start, last))
    return out


def run(binary: Path, receiver, path: Path, *extra: str, timeout: float = 60) -> tuple[int, str]:
    args = [str(binary), "--source", "events", "--input", str(path), "--host", "127.0.0.1",
            "--port", str(receiver.port), "--control-port", str(free_udp_port()), "--camera-index", "3",
            *extra]
    p = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + timeout
    while p.poll() is None and time.monotonic() < deadline:
        receiver.poll(0.05)
    if p.poll() is None:
        p.kill()
    _, err = p.communicate()
    receiver.poll(0.3)
    return p.returncode, err


def test_event_file_goes_out_in_slices(edge_any: Path, receiver, tmp_path: Path, no_sanitizer_report) -> None:
    ev = events(60_000)
    path = tmp_path / "rec.aedat4"
    write_events(path, ev, 128, 128)
    rc, err = run(edge_any, receiver, path, "--realtime", "0", "--slice-us", "1000")
    no_sanitizer_report(err)
    assert rc == 0, err
    got = [m for m in receiver.messages if isinstance(m, DvsClusters)]
    assert [(m.t_start_us, m.t_end_us) for m in got] == slices(ev["t"], 1000)
    assert all(m.camera_index == 3 and m.n_clusters == 0 for m in got)  # no tracker yet (issue 13)
    seqs = [m.seq for m in got]
    assert seqs == sorted(seqs)
    last = [m for m in receiver.messages if isinstance(m, EdgeStatus)][-1]
    assert (last.frames_seen, last.frames_dropped, last.width, last.height) == (len(ev), 0, 128, 128)
    assert last.state == 3  # STOPPED: the file ended


def test_realtime_file_keeps_its_pace(edge_bin: Path, receiver, tmp_path: Path) -> None:
    ev = events(5_000, seed=1, span_us=600_000)
    path = tmp_path / "rec.raw"
    write_events(path, ev, 128, 128)  # EVT 3.0
    t0 = time.monotonic()
    rc, err = run(edge_bin, receiver, path, "--slice-us", "5000")
    elapsed = time.monotonic() - t0
    assert rc == 0, err
    got = [m for m in receiver.messages if isinstance(m, DvsClusters)]
    assert [(m.t_start_us, m.t_end_us) for m in got] == slices(ev["t"], 5000)
    span = (int(ev["t"][-1]) - int(ev["t"][0])) / 1e6
    assert elapsed >= 0.9 * span  # played at the recorded pace, not at once


def test_damaged_file_sends_what_came_before(edge_any: Path, receiver, tmp_path: Path, no_sanitizer_report) -> None:
    ev = events(100_000, seed=2)
    path = tmp_path / "rec.aedat4"
    write_events(path, ev, 128, 128, compression="zstd")
    data = path.read_bytes()
    cut = tmp_path / "cut.aedat4"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    try:
        read_events(cut)
        raise AssertionError("the cut file read cleanly")
    except EventFileError as exc:
        before, offset = exc.events, exc.offset
    rc, err = run(edge_any, receiver, cut, "--realtime", "0")
    no_sanitizer_report(err)
    assert rc == 3
    assert f"at byte {offset}" in err and "truncated file" in err
    last = [m for m in receiver.messages if isinstance(m, EdgeStatus)][-1]
    assert last.state == 2 and last.frames_seen == len(before) > 0  # ERROR, every event before
    assert "truncated" in last.last_error
    got = [m for m in receiver.messages if isinstance(m, DvsClusters)]
    assert got[-1].t_end_us == int(before["t"][-1])


def test_bad_event_sources_are_clear_errors(edge_bin: Path, receiver, tmp_path: Path) -> None:
    rc, err = run(edge_bin, receiver, tmp_path / "missing.aedat4")
    assert rc == 3 and "cannot open" in err
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"no event file here")
    rc, err = run(edge_bin, receiver, junk)
    assert rc == 3 and "unknown event file format" in err
    rc, err = run(edge_bin, receiver, junk, "--event-format", "evt5")
    assert rc == 2 and "unknown event format" in err
    p = subprocess.run([str(edge_bin), "--source", "dvs128", "--control-port", "0", "--port",
                        str(receiver.port)], capture_output=True, text=True, timeout=30)
    # no DVS128 on this machine (or no USB at all)
    assert p.returncode == 3 and ("no DVS128 (USB 152a:8400) found" in p.stderr or "libusb" in p.stderr)


def test_stdin_stream_is_taken_as_it_arrives(edge_any: Path, receiver, tmp_path: Path, no_sanitizer_report) -> None:
    # a producer writing EVT 3.0 to the daemon's stdin: the events that came are sent while it waits
    # for more (STATUS goes on meanwhile), and the end of the stream ends the daemon
    ev = events(40_000, seed=3)
    path = tmp_path / "live.raw"
    write_events(path, ev, 128, 128)
    data = path.read_bytes()
    header = data.index(b"% end\n") + 6
    half = header + ((len(data) - header) // 2 // 2) * 2 + 1  # an odd cut: inside a word
    part = tmp_path / "part.raw"
    part.write_bytes(data[: half - 1])
    first = len(read_events(part))
    args = [str(edge_any), "--source", "events", "--input", "-", "--realtime", "0", "--host", "127.0.0.1",
            "--port", str(receiver.port), "--control-port", str(free_udp_port()), "--status-interval-ms", "100"]
    p = subprocess.Popen(args, stdin=subprocess.PIPE, stderr=subprocess.PIPE, text=False)
    try:
        p.stdin.write(data[:half])
        p.stdin.flush()
        seen = receiver.wait_for(lambda m: isinstance(m, EdgeStatus) and m.frames_seen == first, timeout=30)
        assert seen, "the events of the first half were not taken while the stream stayed open"
        n_status = sum(isinstance(m, EdgeStatus) for m in receiver.messages)
        time.sleep(0.3)
        receiver.poll(0.1)
        assert sum(isinstance(m, EdgeStatus) for m in receiver.messages) > n_status  # heartbeat goes on
        p.stdin.write(data[half:])
        p.stdin.close()
        rc = p.wait(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    err = p.stderr.read().decode()
    no_sanitizer_report(err)
    assert rc == 0, err
    receiver.poll(0.3)
    last = [m for m in receiver.messages if isinstance(m, EdgeStatus)][-1]
    assert last.frames_seen == len(ev) and last.state == 3
    got = [m for m in receiver.messages if isinstance(m, DvsClusters)]
    assert got[0].t_start_us == int(ev["t"][0]) and got[-1].t_end_us == int(ev["t"][-1])
