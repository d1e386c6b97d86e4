"""`make bench-wingbeat`: the wing-beat tracker's throughput on one core, the edge's C tracker
(edge/events/algos/wingbeat.c) side by side with the host's Python EKF (analysis.track_wings, method "ekf") on
the same simulated events in the same run, with the same algorithm and parameters (2 harmonics, 4 events per
update, initialisation included). Also the whole daemon, `flytrack-edge --wingbeat 1 --realtime 0`, on the
same events from an AEDAT 4 file (decoding, tracking, a DVS_WINGBEAT every 5 ms over UDP): its CPU time.

Each figure is events in / CPU seconds (time.process_time for the in-process trackers, the child's rusage for
the daemon), mean over repeats; the C tracker gets the events in 10 ms batches, as the daemon does. The
accuracy of both against the simulation is printed too (they agree beat for beat).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from flytrack_host.dvs.wingbeat.analysis import WingbeatResult, WingTrack, _combine, score_wings, track_wings
from flytrack_host.dvs.wingbeat.native import NativeWingbeat, edge_beats
from flytrack_host.dvs.wingbeat.simulate import FlySimParams, simulate_tethered_fly


def _c_run(ev: np.ndarray, batches: list[tuple[int, int]]) -> tuple[float, np.ndarray, NativeWingbeat]:
    tr = NativeWingbeat(128, 128)
    out = []
    t0 = time.process_time()
    for a, b in batches:
        out.append(tr.feed(ev[a:b]))
    return time.process_time() - t0, np.concatenate(out), tr


def _daemon_cpu(ev: np.ndarray) -> tuple[float, int] | None:
    from flytrack_host.dvs.events import write_events
    from flytrack_host.util.native import NativeLibraryError, find_edge_binary

    try:
        binary = find_edge_binary()
    except NativeLibraryError as exc:
        print(f"  daemon: skipped ({exc})")
        return None
    with tempfile.TemporaryDirectory() as d, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        path = Path(d) / "fly.aedat4"
        write_events(path, ev, width=128, height=128)
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
        rx.bind(("127.0.0.1", 0))
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        subprocess.run([str(binary), "--source", "events", "--input", str(path), "--wingbeat", "1", "--realtime",
                        "0", "--host", "127.0.0.1", "--port", str(rx.getsockname()[1]), "--control-port", "0"],
                       check=True, capture_output=True, timeout=300)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        rx.settimeout(0.2)
        got = 0
        try:
            while True:
                rx.recv(65536)
                got += 1
        except TimeoutError:
            pass
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), got


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=2.0, help="simulated recording length (default 2)")
    ap.add_argument("--repeats", type=int, default=5, help="runs of the C tracker (the Python one runs once)")
    ap.add_argument("--json", default=os.environ.get("BENCH_JSON") or None, help="write figures here")
    args = ap.parse_args(argv)
    ev, truth = simulate_tethered_fly(FlySimParams(duration_s=args.seconds))
    n = len(ev)
    edges = np.searchsorted(ev["t"], np.arange(ev["t"][0], ev["t"][-1] + 10_000, 10_000))
    batches = [(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]
    print(f"wing-beat tracking: {n:,} events ({args.seconds:g} s of a simulated 200 Hz tethered fly, 20 % noise, "
          f"{n / args.seconds / 1e3:.0f} k events/s), EKF with 2 harmonics, 4 events per update, one core")
    c_times = []
    for _ in range(args.repeats):
        dt, beats, tr = _c_run(ev, batches)
        c_times.append(dt)
    c_rate = n / np.mean(c_times)
    t0 = time.process_time()
    py = track_wings(ev, "ekf")
    py_s = time.process_time() - t0
    py_rate = n / py_s
    wings = [WingTrack(w, {}, _combine(edge_beats(beats, w, 0), edge_beats(beats, w, 1))) for w in (0, 1)]
    cres = WingbeatResult("ekf", py.geometry, py.start_freq_hz, wings, n, py.events_in_roi, 0.0)
    print(f"  {'':38s} {'M events/s':>11s} {'freq err %':>11s} {'amp err %':>10s}")
    fig: dict = {"events": n, "seconds": args.seconds}
    for name, rate, res, key in (("C tracker (edge/events/algos/wingbeat.c)", c_rate, cres, "c"),
                                 ("Python EKF (flytrack_host.dvs.wingbeat)", py_rate, py, "python")):
        sc = score_wings(res, truth.freq_at, truth.amplitude_at)
        fe = max(s.freq_err_pct_mean for s in sc)
        ae = max(s.amp_err_pct_mean for s in sc)
        print(f"  {name:38s} {rate / 1e6:11.2f} {fe:11.3f} {ae:10.2f}")
        fig[key] = {"events_per_s": rate, "freq_err_pct_worst_wing": fe, "amp_err_pct_worst_wing": ae}
    ratio = c_rate / py_rate
    print(f"  C / Python: {ratio:.1f}x (C mean of {args.repeats} runs: {np.mean(c_times) * 1e3:.1f} ms; Python "
          f"{py_s:.2f} s)")
    fig["c_over_python"] = ratio
    d = _daemon_cpu(ev)
    if d is not None:
        cpu, got = d
        print(f"  flytrack-edge --wingbeat 1 --realtime 0 (AEDAT 4 decode + tracker + {got} datagrams over UDP): "
              f"{cpu:.3f} s CPU, {n / cpu / 1e6:.2f} M events/s")
        fig["daemon"] = {"cpu_s": cpu, "events_per_s": n / cpu, "datagrams": got}
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"bench-wingbeat": fig}, fh, indent=2)
        print(f"figures written to {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
