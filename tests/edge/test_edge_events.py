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
import pytest

from flytrack_host.dvs.events import EVENT_DTYPE, EventFileError, read_events, write_events
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


def blob_events(seconds: float = 0.2, seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 3 px blob crossing a 128x128 sensor from (20, 30) at (+300, +200) px/s, 200 k events/s, plus
    uniform noise at 20 k events/s. Returns events, start and velocity."""
    rng = np.random.default_rng(seed)
    start, vel = np.array([20.0, 30.0]), np.array([300.0, 200.0])
    n, nn = int(seconds * 200e3), int(seconds * 20e3)
    t = np.sort(rng.uniform(0, seconds * 1e6, n))
    pos = start + vel * (t[:, None] * 1e-6) + rng.normal(0, 1.5, (n, 2))
    ev = np.empty(n + nn, EVENT_DTYPE)
    ev["t"] = np.r_[t, rng.uniform(0, seconds * 1e6, nn)].astype(np.int64) + 5000
    ev["x"] = np.r_[np.clip(np.round(pos[:, 0]), 0, 127), rng.integers(0, 128, nn)]
    ev["y"] = np.r_[np.clip(np.round(pos[:, 1]), 0, 127), rng.integers(0, 128, nn)]
    ev["p"] = rng.integers(0, 2, n + nn)
    return ev[np.argsort(ev["t"], kind="stable")], start, vel


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
    assert all(m.camera_index == 3 for m in got)
    # Uniform events at 300 k/s (dense enough to pass the noise filter): at most the tracker's 10
    # clusters a slice, all on the sensor (a real blob is tracked in test_the_daemon_tracks_a_blob...).
    assert all(m.n_clusters <= 10 for m in got)
    assert all(np.all((m.clusters["x"] >= 0) & (m.clusters["x"] < 128)) for m in got)
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


def test_the_daemon_tracks_a_blob_in_its_clusters(edge_any: Path, receiver, tmp_path: Path,
                                                  no_sanitizer_report) -> None:
    """The edge's event algorithms end to end: noise filter, cluster tracker and Kalman filter in
    flytrack-edge, out as DVS_CLUSTERS over UDP, on a blob of known path."""
    ev, start, vel = blob_events()
    path = tmp_path / "blob.aedat4"
    write_events(path, ev, 128, 128)
    rc, err = run(edge_any, receiver, path, "--realtime", "0", "--slice-us", "5000")
    no_sanitizer_report(err)
    assert rc == 0, err
    got = [m for m in receiver.messages if isinstance(m, DvsClusters)]
    late = [m for m in got if m.t_end_us > 45_000]
    assert len(late) > 20 and all(m.n_clusters == 1 for m in late), [m.n_clusters for m in late]
    err_px = []
    for m in late:
        c = m.clusters[0]
        truth = start + vel * ((m.t_end_us - 5000) * 1e-6)
        err_px.append(np.hypot(c["x"] - truth[0], c["y"] - truth[1]))
        assert abs(c["vx"] - vel[0]) < 60 and abs(c["vy"] - vel[1]) < 60, (c["vx"], c["vy"])
    assert np.median(err_px) < 1.5, np.median(err_px)
    assert len({int(m.clusters[0]["id"]) for m in late}) == 1  # one track for the one animal


def _evt2_with_syncs(ev: np.ndarray, sync_us: np.ndarray, width: int = 128, height: int = 128) -> bytes:
    """An EVT 2.0 stream: the events, with an EXT_TRIGGER word at each sync time (in time order)."""
    from flytrack_host.sim.dvs import Evt2Encoder, evt2_header

    enc = Evt2Encoder()
    out = [evt2_header(width, height)]
    i = 0
    for s in sync_us.tolist():
        j = int(np.searchsorted(ev["t"], s, side="right"))
        out.append(enc.encode(ev[i:j], sync_us=s))
        i = j
    out.append(enc.encode(ev[i:]))
    return b"".join(out)


def test_slices_are_stamped_with_trigger_frames_from_sync_events(edge_any: Path, receiver, tmp_path: Path,
                                                                  no_sanitizer_report) -> None:
    """SPEC 1.6: sync events at every trigger pulse (10 ms; pulses 20-22 missed by the sensor) give each
    slice its trigger frame; slices are cut at the syncs, so those are stated exactly at a frame; each
    cluster carries its Kalman filter's covariance, and the blob's true place is within it."""
    ev, start, vel = blob_events(seconds=0.3)
    t0 = 5000 + 3000  # trigger frame 0 at 8 ms of sensor time
    frames = np.array([k for k in range(30) if k not in (20, 21, 22)])
    path = tmp_path / "blob.raw"
    path.write_bytes(_evt2_with_syncs(ev, t0 + 10_000 * frames))
    rc, err = run(edge_any, receiver, path, "--realtime", "0", "--slice-us", "5000", "--event-format", "evt2")
    no_sanitizer_report(err)
    assert rc == 0, err
    got = [m for m in receiver.messages if isinstance(m, DvsClusters)]
    synced = [m for m in got if m.synced]
    # (a file is read ahead, so even the slices before the first sync get a stamp, extrapolated)
    assert len(synced) >= 50
    for m in synced:
        assert m.frame_period_us == pytest.approx(10_000.0, rel=1e-6)
        assert m.trigger_frame == pytest.approx((m.t_end_us - t0) / 10_000, abs=1e-6), m  # the gap counted
    at_sync = {round(m.trigger_frame, 9) for m in synced if (m.t_end_us - t0) % 10_000 == 0}
    assert set(range(2, 30)) - {20, 21, 22} <= at_sync  # a slice ends at every sync seen
    assert max(m.syncs for m in got) == len(frames)
    nees = []
    for m in synced:
        if m.n_clusters != 1:
            continue
        c = m.clusters[0]
        assert c["var_x"] > 0 and c["var_y"] > 0 and c["cov_xy"] ** 2 <= c["var_x"] * c["var_y"]
        e = np.array([c["x"], c["y"]]) - (start + vel * ((m.t_end_us - 5000) * 1e-6))
        S = np.array([[c["var_x"], c["cov_xy"]], [c["cov_xy"], c["var_y"]]], dtype=np.float64)
        nees.append(float(e @ np.linalg.solve(S, e)))
    assert len(nees) > 40
    assert np.median(nees) < 6.0, np.median(nees)  # the covariance is about the error's size (2 if exact)


def test_a_dvs128_in_the_simulated_rig_gives_clusters_with_its_support_options(edge_bin: Path, receiver,
                                                                                tmp_path: Path) -> None:
    """A 128 x 128 sensor sees an animal with s = 346/128 times fewer, sparser events than the class of
    sensor the library defaults suit: with the defaults the edge reports no cluster at the trigger
    frames; with the rig's options (sim.run.dvs_support_options) it does, near the animal's place."""
    from flytrack_host.sim.dvs import DvsRenderer, evt2_header, make_dvs_cameras, render_stream
    from flytrack_host.sim.flight import Arena, simulate_flight
    from flytrack_host.sim.run import dvs_support_options

    arena = Arena()
    gt = simulate_flight(2, 1.5, 100.0, seed=0, arena=arena)
    cam = make_dvs_cameras(1, arena, 0, "dvs128")[0]
    r = DvsRenderer(cam, seed=7)
    chunks = render_stream(r, gt)

    path = tmp_path / "dvs128.raw"
    path.write_bytes(evt2_header(cam.width, cam.height) + b"".join(c for c, _ in chunks))
    found = {}
    for name, extra in (("defaults", []), ("options", dvs_support_options(cam.width, cam.height))):
        receiver.messages.clear()
        rc, err = run(edge_bin, receiver, path, "--realtime", "0", "--slice-us", "5000", "--event-format", "evt2",
                      *extra)
        assert rc == 0, err
        at_frames = [m for m in receiver.messages if isinstance(m, DvsClusters) and m.synced
                     and abs(m.trigger_frame - round(m.trigger_frame)) < 1e-6 and m.n_clusters]
        errs = []
        for m in at_frames:
            f = int(round(m.trigger_frame))
            if 0 <= f < gt.n_frames:
                uv = cam.project(gt.pos[f])
                errs += [float(np.min(np.hypot(uv[:, 0] - c["x"], uv[:, 1] - c["y"]))) for c in m.clusters]
        found[name] = (len(at_frames), float(np.median(errs)) if errs else np.inf)
    print(f"DVS128 frames with a cluster (of 150), median px from the animal: {found}")
    # trigger frames whose slice, cut at the frame's sync event, holds a cluster (of 150)
    assert found["defaults"][0] < 10, found  # measured: 0
    assert found["options"][0] > 40, found  # measured: 59
    assert found["options"][1] < 1.0, found  # median px from the animal (measured 0.43)


def test_event_edge_control_allow_list_as_the_frame_edge(edge_any: Path, receiver, tmp_path: Path,
                                                           no_sanitizer_report) -> None:
    """The event-camera daemon takes CONTROL from the same senders as the frame daemon
    (edge_config_default_control; here --control-allow 127.0.0.2) and, as it, says a dropped sender
    once in its log and in STATUS, answers an allowed one, logs malformed CONTROL, counts both at exit."""
    import socket

    from flytrack_host.protocol import AckStatus, Command, Control, ControlAck, decode_datagram, encode

    cport = free_udp_port()
    args = [str(edge_any), "--source", "events", "--input", "-", "--realtime", "0", "--host", "127.0.0.1",
            "--port", str(receiver.port), "--control-port", str(cport), "--status-interval-ms", "100",
            "--control-allow", "127.0.0.2"]
    path = tmp_path / "live.raw"
    write_events(path, events(2000, seed=4), 128, 128)
    p = subprocess.Popen(args, stdin=subprocess.PIPE, stderr=subprocess.PIPE)
    assert p.stdin is not None
    p.stdin.write(path.read_bytes())  # the stream stays open: the daemon runs on, waiting for more
    p.stdin.flush()
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other.bind(("127.0.0.2", 0))
    other.settimeout(10.0)
    try:
        assert receiver.wait_for(lambda m: isinstance(m, EdgeStatus), timeout=30), "no STATUS from the edge"
        for rid in (1, 2, 3):  # from 127.0.0.1, the receiver: not listed
            receiver.send(encode(Control(request_id=rid, camera_index=0xFFFF, command=int(Command.STOP))), cport)
        st = receiver.wait_for(lambda m: isinstance(m, EdgeStatus) and "not in --control-allow" in m.last_error,
                               10.0)
        assert st and "127.0.0.1" in st[0].last_error
        other.sendto(b"\x00garbage", ("127.0.0.1", cport))  # malformed, from an allowed sender
        other.sendto(encode(Control(request_id=4, camera_index=0xFFFF, command=int(Command.SET_PARAM),
                                    param="slice_us", value=2000.0)), ("127.0.0.1", cport))
        ack = decode_datagram(other.recvfrom(2048)[0])
        assert isinstance(ack, ControlAck) and ack.request_id == 4 and ack.status == AckStatus.OK
        assert not [m for m in receiver.messages if isinstance(m, ControlAck)]  # the dropped ones: no answer
    finally:
        other.close()
        if p.stdin:
            p.stdin.close()
        rc = p.wait(timeout=30)
    err = p.stderr.read().decode() if p.stderr else ""
    no_sanitizer_report(err)
    assert rc == 0, err
    assert err.count("not in --control-allow (further ones are only counted)") == 1
    assert "malformed CONTROL from 127.0.0.2" in err
    assert "3 datagrams from senders not in --control-allow dropped, 1 malformed" in err
