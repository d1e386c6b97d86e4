"""Wing beats live: the simulated tethered fly (200 Hz, a 10 % rise, 20 % noise events) through the real C edge
daemon (`flytrack-edge --wingbeat 1`, played at its recorded pace) over real UDP to `flytrack wingbeat --live`,
scored against the simulation; and the host's bad cases: no edge, malformed datagrams, an edge that never finds
the fly."""

from __future__ import annotations

import csv
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from flytrack_host.cli import app
from flytrack_host.dvs.events.files import EVENT_DTYPE, write_events
from flytrack_host.dvs.wingbeat.live import N_WINGS, WingbeatReceiver, score_live
from flytrack_host.dvs.wingbeat.simulate import FlySimParams, fly_truth
from flytrack_host.protocol import DvsClusters, DvsWingbeat, encode
from flytrack_host.protocol.udp import WINGEDGE_DTYPE


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _receiver_from_csv(path: Path) -> WingbeatReceiver:
    rx = WingbeatReceiver(0, bind="127.0.0.1")
    rx.close()
    with open(path) as fh:
        for r in csv.DictReader(fh):
            if int(r["record"]) < N_WINGS:
                rx.rows.append((int(r["t_us"]), int(r["record"]), float(r["angle_rad"]), float(r["amplitude_rad"]),
                                float(r["frequency_hz"]), float(r["phase_rad"])))
    return rx


def test_simulator_through_the_edge_daemon_over_udp(tmp_path):
    seconds = 1.2  # the manoeuvre (0.8-1.1 s) included
    f, out_csv, png = tmp_path / "fly.aedat4", tmp_path / "live.csv", tmp_path / "live.png"
    r = CliRunner().invoke(app, ["wingbeat", "--simulate", str(seconds), "--live", str(f), "--csv", str(out_csv),
                                 "--plot", str(png)])
    assert r.exit_code == 0, r.output
    assert "the edge finished the file" in r.output and "0 malformed" in r.output and "fly found" in r.output
    assert png.stat().st_size > 10_000
    # the command prints the live scores and the file path's on the same file, side by side
    assert "live, edge C EKF: wing 1 against the simulation" in r.output
    assert "file, host Python EKF: wing 1 against the simulation" in r.output
    rx = _receiver_from_csv(out_csv)
    s = rx.series()
    # one datagram every 5 ms of event time, all six records once the fly is found (after the 0.1 s window)
    t = s[0][:, 0]
    assert 0.95 * (seconds - 0.1) / 0.005 <= len(t) <= seconds / 0.005 + 2
    assert np.all(np.diff(t)[:-1] == 5000)
    per_record = np.bincount([int(r["record"]) for r in csv.DictReader(open(out_csv))])
    assert list(per_record) == [len(t)] * 6  # the CSV holds the edges' records too
    truth = fly_truth(FlySimParams(duration_s=seconds))  # what the command simulated
    scores = score_live(rx, truth)
    for sc in scores:
        print(f"live wing {sc.wing}: {sc.beats} estimates, frequency error {sc.freq_err_pct_mean:.3f} % (max "
              f"{sc.freq_err_pct_max:.2f} %, jitter {sc.freq_jitter_pct:.3f} %), amplitude error "
              f"{sc.amp_err_pct_mean:.2f} % (max {sc.amp_err_pct_max:.2f} %)")
        assert sc.beats > 150
        assert sc.freq_err_pct_mean < 0.5  # measured 0.19-0.25 %; the goal is 1 %
        assert sc.freq_err_pct_max < 2.0  # during the rise the estimate trails the truth by ~10 ms
        assert sc.amp_err_pct_mean < 4.0  # measured 1.9-2.8 %; the goal is 5 %
    # the rise is followed: the last 0.05 s read 220 Hz within 0.5 %
    for w in (0, 1):
        late = s[w][s[w][:, 0] > (seconds - 0.05) * 1e6, 3]
        assert np.all(np.abs(late / 220.0 - 1) < 0.005)


def test_no_edge_is_a_timeout_with_a_hint():
    port = _free_port()
    t0 = time.monotonic()
    r = CliRunner().invoke(app, ["wingbeat", "--live", "--port", str(port), "--timeout", "0.5"])
    assert r.exit_code == 2
    assert f"no datagram from an edge on UDP port {port} in 0.5 s" in r.output and "--wingbeat 1" in r.output
    assert time.monotonic() - t0 < 20


def _wingbeat(seq: int, t_us: int, freq: float = 200.0, n: int = 6) -> bytes:
    e = np.zeros(n, WINGEDGE_DTYPE)
    e["edge_id"] = np.arange(n)
    e["angle"], e["amplitude"], e["frequency"], e["phase"] = 1.6, 1.0, freq, 0.5
    return encode(DvsWingbeat(camera_index=0, seq=seq, t_us=t_us, edges=e))


def _bad_datagrams() -> list[bytes]:
    good = _wingbeat(1, 1000)
    nan = bytearray(good)
    nan[8 + 24 + 4:8 + 24 + 8] = np.array([np.nan], "<f4").tobytes()  # record 0's angle
    return [b"hello", good[:20], good[:-3], bytes(nan), b"XX" + good[2:]]


def test_malformed_datagrams_are_counted_and_lose_nothing(tmp_path):
    path = tmp_path / "rows.csv"
    rx = WingbeatReceiver(0, bind="127.0.0.1", csv_path=path)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        dest = ("127.0.0.1", rx.port)
        tx.sendto(_wingbeat(1, 5000), dest)
        for b in _bad_datagrams():
            tx.sendto(b, dest)
        tx.sendto(encode(DvsClusters(camera_index=0, seq=2, t_start_us=0, t_end_us=1)), dest)
        tx.sendto(_wingbeat(6, 10000), dest)  # seq 3, 4, 5 never came
        deadline = time.monotonic() + 5
        while rx.counts.datagrams < 8 and time.monotonic() < deadline:
            rx.poll(0.1)
    finally:
        tx.close()
        rx.close()
    c = rx.counts
    assert c.datagrams == 8 and c.wingbeat == 2 and c.malformed == 5 and c.other == 1 and c.lost == 3
    assert c.errors == {"TRUNCATED": 2, "LENGTH_MISMATCH": 1, "NOT_FINITE": 1, "BAD_MAGIC": 1}
    assert c.other_types == {"DvsClusters": 1}
    assert "TRUNCATED" in rx.first_error
    rows = list(csv.DictReader(open(path)))
    assert len(rows) == 12 and {r["t_us"] for r in rows} == {"5000", "10000"}


def test_live_listener_stops_after_seconds_and_writes_what_came(tmp_path):
    port = _free_port()
    stop = threading.Event()

    def edge() -> None:  # a stand-in edge on real UDP: 200 Hz rising to 210 Hz, with garbage in between
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            seq, t = 0, 0
            while not stop.is_set():
                seq += 1
                t += 5000
                s.sendto(_wingbeat(seq, t, 200.0 + t * 1e-5), ("127.0.0.1", port))
                if seq % 20 == 0:
                    s.sendto(b"garbage", ("127.0.0.1", port))
                time.sleep(0.005)

    th = threading.Thread(target=edge, daemon=True)
    th.start()
    try:
        out_csv, png = tmp_path / "l.csv", tmp_path / "l.png"
        r = CliRunner().invoke(app, ["wingbeat", "--live", "--port", str(port), "--seconds", "1.0", "--csv",
                                     str(out_csv), "--plot", str(png)])
    finally:
        stop.set()
        th.join(5)
    assert r.exit_code == 0, r.output
    assert "--seconds 1 reached" in r.output
    n = int(r.output.split("--seconds 1 reached: ")[1].split(" DVS_WINGBEAT")[0])
    bad = int(r.output.split(" STATUS, ")[1].split(" malformed")[0])
    assert n >= 20 and bad >= 1 and bad == pytest.approx(n / 20, abs=2)
    rows = list(csv.DictReader(open(out_csv)))
    assert len(rows) == 6 * n
    assert png.is_file()


def test_edge_that_never_finds_the_fly_says_why(tmp_path):
    rng = np.random.default_rng(2)
    ev = np.zeros(35_000, EVENT_DTYPE)  # 0.35 s of uniform noise: no beating wing
    ev["t"] = np.sort(rng.integers(0, 350_000, len(ev)))
    ev["x"], ev["y"], ev["p"] = rng.integers(0, 128, len(ev)), rng.integers(0, 128, len(ev)), rng.integers(0, 2,
                                                                                                          len(ev))
    f = tmp_path / "noise.aedat4"
    write_events(f, ev, width=128, height=128)
    r = CliRunner().invoke(app, ["wingbeat", "--live", str(f), "--csv", str(tmp_path / "n.csv")])
    assert r.exit_code == 2
    assert "the edge never found the fly" in r.output and "no beating wing in view" in r.output
    assert (tmp_path / "n.csv").is_file()  # what came is written all the same


def test_live_needs_an_event_file_the_edge_reads(tmp_path):
    r = CliRunner().invoke(app, ["wingbeat", "--simulate", "0.3", "--live", str(tmp_path / "f.npy")])
    assert r.exit_code == 2 and "not .npy" in r.output
    r = CliRunner().invoke(app, ["wingbeat", "--live", str(tmp_path / "missing.aedat4")])
    assert r.exit_code == 2 and "no such event file" in r.output
    r = CliRunner().invoke(app, ["wingbeat"])
    assert r.exit_code == 2 and "--live" in r.output
    r = CliRunner().invoke(app, ["wingbeat", "--live", "--method", "wra"])
    assert r.exit_code == 2 and "the edge runs the EKF" in r.output
    f = tmp_path / "x.aedat4"
    write_events(f, np.zeros(10, EVENT_DTYPE), width=128, height=128)
    r = CliRunner().invoke(app, ["wingbeat", "--live", str(f), "--harmonics", "6"])
    assert r.exit_code == 2 and "at most 4" in r.output


def test_ctrl_c_stops_the_listener_and_writes_what_came(tmp_path):
    import signal
    import subprocess
    import sys

    port = _free_port()
    out_csv = tmp_path / "c.csv"
    # SIGINT as a terminal gives it: a suite started in the background of a script has SIGINT ignored,
    # which children inherit, and Python then installs no KeyboardInterrupt handler (seen: the
    # listener ran on to its 10 s silence time-out instead of stopping).
    p = subprocess.Popen([sys.executable, "-m", "flytrack_host.cli", "wingbeat", "--live", "--port", str(port),
                          "--csv", str(out_csv)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        assert "listening for DVS_WINGBEAT" in p.stdout.readline()  # bound: datagrams from now on are taken
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for i in range(1, 41):
                s.sendto(_wingbeat(i, i * 5000), ("127.0.0.1", port))
                time.sleep(0.002)
        time.sleep(1.6)  # the CSV is flushed every second while running: a killed run keeps what came
        assert len(list(csv.DictReader(open(out_csv)))) == 40 * 6
        p.send_signal(signal.SIGINT)
        out, _ = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, out
    assert "interrupted: 40 DVS_WINGBEAT" in out and "Traceback" not in out
    assert len(list(csv.DictReader(open(out_csv)))) == 40 * 6
