"""Benchmark: what the live outputs cost the tracking thread, in the real pipeline.

The host pipeline runs live over loopback UDP with the real tracker (11 cameras x 10 targets, 100 fps by
default; the edges are a forked process, as on a rig). Its sinks are timed where they run, on the
tracking thread, in three runs side by side:

- `ours`: the event stream (LiveServer: /events for Braid clients, the page's state) and the VR pose
  stream (200 Hz UDP), with 10 Braid clients and 1 page connected from another process;
- `sync`: the obvious way to do it, the peer: encode the frame's Braid events on the tracking thread
  and write them to the same 10 clients' sockets there;
- `none`: no live output (the tracking thread's own "tracking" latency as the baseline).

Printed per run: the sinks' time per frame (mean including every frame, P50, P99, max), the pipeline's
trigger->estimate "tracking" part (which also shows what the other threads take from the tracking
thread through the GIL), and, for the clients, trigger -> EndOfFrame received.

    .venv/bin/python -m flytrack_host.pipeline.bench_live [--seconds 4] [--cameras 11] [--targets 10] [--clients 10]
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import os
import re
import resource
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.intake.sync import FixedRateClock
from flytrack_host.live import braid
from flytrack_host.live.pose import PoseClient, PoseStream
from flytrack_host.live.web import browser as browser_mod
from flytrack_host.live.web.server import LiveServer, calibration_xml_of
from flytrack_host.pipeline import HostPipeline
from flytrack_host.protocol.udp import FeatureFrame, encode_features
from flytrack_host.rig import parse_rig
from flytrack_host.tracking.synthetic import make_scenario
from flytrack_host.tracking.types import FrameResult
from flytrack_host.util import hostclock
from flytrack_host.util.children import tied

_EOF = re.compile(rb'"EndOfFrame":(\d+)')
_UI = re.compile(rb'event: state\ndata: \{"time":[^,]+,"final":(?:true|false),"frame":(-?\d+),'
                 rb'.*?"last_estimate_time":([0-9.eE+-]+|null)')


class TimedSinks:
    """The measured sinks behind one sink: times their on_frame calls together, per frame."""

    def __init__(self, sinks: list[Any]):
        self.sinks = sinks
        self.times: list[float] = []

    def on_frame(self, result: FrameResult, frame_time: float, estimate_time: float) -> None:
        t0 = time.perf_counter()
        for s in self.sinks:
            s.on_frame(result, frame_time, estimate_time)
        self.times.append(time.perf_counter() - t0)

    def close(self) -> None:
        for s in self.sinks:
            s.close()


class SyncBraidSink:
    """The peer: Braid events encoded and written to every client socket on the tracking thread."""

    def __init__(self, socks: list[socket.socket]):
        self.socks = socks

    def on_frame(self, result: FrameResult, frame_time: float, estimate_time: float) -> None:
        data = braid.encode_frame(result, frame_time)
        for s in self.socks:
            s.sendall(data)

    def close(self) -> None:
        for s in self.socks:
            s.close()


def send_all(plan: list, dest: tuple[str, int], t_start: float, fps: float) -> None:
    socks: dict[int, socket.socket] = {}
    while hostclock.now() < t_start:
        time.sleep(0.001)
    for frame, cam, dg in plan:
        wait = t_start + frame / fps - hostclock.now()
        if wait > 0:
            time.sleep(wait)
        sock = socks.get(cam) or socks.setdefault(cam, socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
        sock.sendto(dg, dest)


def _client(sock: socket.socket, out: list, page: bool = False) -> None:
    """Reads until the server ends the stream. Braid: (frame, received) per EndOfFrame. Page:
    (frame, received, its estimate time) per state whose frame is new."""
    buf = b""
    last_frame = None
    while True:
        try:
            chunk = sock.recv(1 << 20)
        except OSError:
            break
        if not chunk:
            break
        now = hostclock.now()
        buf += chunk
        cut = buf.rfind(b"\n\n")  # events end with a blank line; TCP may split anywhere
        if cut >= 0:
            if page:
                for m in _UI.finditer(buf, 0, cut):
                    f = int(m.group(1))
                    if f != last_frame and m.group(2) != b"null":
                        out.append((f, now, float(m.group(2))))
                        last_frame = f
            else:
                out.extend((int(m.group(1)), now) for m in _EOF.finditer(buf, 0, cut))
            buf = buf[cut + 2:]


def clients_process(addr: tuple[str, int] | None, n: int, conn: Any, page: bool, listen_port: int | None) -> None:
    """n Braid clients (+1 page) in their own process: connect, then read until the server ends.
    With listen_port, accept n connections instead (the peer writes to them)."""
    socks = []
    if listen_port is not None:
        srv = socket.socket()
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind(("127.0.0.1", listen_port))
        srv.listen(n)
        conn.send(("ready", 0))
        socks = [srv.accept()[0] for _ in range(n)]
    pose_ages: list[float] = []
    pose_thread = None
    if listen_port is None:
        assert addr is not None
        for i in range(n + (1 if page else 0)):
            s = socket.create_connection(addr)
            path = "/ui/events" if i == n else "/events"
            s.sendall(f"GET {path} HTTP/1.0\r\nAccept: text/event-stream\r\n\r\n".encode())
            socks.append(s)
        # The pose stream's receiver lives here too, not in the measured host process.
        pose_client = PoseClient(0)

        def read_pose() -> None:
            for m in pose_client.messages(2.0):
                if not m.no_object:
                    pose_ages.append(m.age_s)

        pose_thread = threading.Thread(target=read_pose, daemon=True)
        pose_thread.start()
        conn.send(("ready", pose_client.port))
    results: list[list] = [[] for _ in socks]
    threads = [threading.Thread(target=_client, args=(s, r, i == n), daemon=True)
               for i, (s, r) in enumerate(zip(socks, results, strict=True))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if pose_thread is not None:
        pose_thread.join(5)
    conn.send((results, pose_ages))


def run_once(mode: str, a: argparse.Namespace, sc: Any, plan: list) -> dict[str, Any]:
    t_start = hostclock.now() + 1.5
    rig = parse_rig({
        "name": "bench", "trigger": {"kind": "software", "fps": a.fps},
        "host": {"listen": "127.0.0.1:7000", "live_subscribers": []},
        "cameras": [{"name": f"cam{i}", "index": i, "edge": "127.0.0.1"} for i in sc.cameras],
    })
    ctx = mp.get_context("fork")
    cctx = mp.get_context("spawn")  # the clients' process starts clean (this one has threads running)
    parent, child = cctx.Pipe()
    proc = None
    timed = None
    pose = None
    br = None
    page_js = None
    with tempfile.TemporaryDirectory() as d:
        pipe = HostPipeline(rig, sc.cameras, clock=FixedRateClock(a.fps, start_time=t_start),
                            recording_path=Path(d) / "bench.flytrack", bind="127.0.0.1:0")
        if mode == "ours":
            server = LiveServer("127.0.0.1", 0, calibration_xml=calibration_xml_of(pipe), poll_s=a.poll_ms / 1e3)
            server.start()
            server.state.pipe = pipe
            proc = cctx.Process(target=tied(clients_process),
                                args=(("127.0.0.1", server.port), a.clients, child, not a.no_page, None))
            proc.start()
            _, pose_port = parent.recv()
            pose = PoseStream([("127.0.0.1", pose_port)], rate_hz=200.0, lock="all", start=not a.no_pose)
            timed = TimedSinks([server, pose])
            end = time.monotonic() + 10
            while server.clients.count() < a.clients + (0 if a.no_page else 1) and time.monotonic() < end:
                time.sleep(0.01)
            if a.browser and browser_mod.missing() is None:
                # The page itself in chromium (its own processes): what it measures is what a user sees.
                br = browser_mod.Browser()
                br.driver.get(server.url)
        elif mode == "sync":
            lp = _free_port()
            proc = cctx.Process(target=tied(clients_process), args=(None, a.clients, child, False, lp))
            proc.start()
            parent.recv()
            socks = [socket.create_connection(("127.0.0.1", lp)) for _ in range(a.clients)]
            timed = TimedSinks([SyncBraidSink(socks)])
        if timed is not None:
            pipe.sinks.append(timed)
        ru0 = resource.getrusage(resource.RUSAGE_SELF)
        w0 = time.monotonic()
        pipe.start()
        sender = ctx.Process(target=tied(send_all), args=(plan, pipe.address, t_start, a.fps))
        sender.start()
        sender.join()
        time.sleep(0.2)
        if br is not None:
            page_js = br.js("return [window.flytrack.updateTimes, window.flytrack.delays]")
            br.close()
        threads_cpu = _thread_cpu()
        if a.verbose:
            print(f"  {mode}: CPU s per thread: {threads_cpu}")
        summary = pipe.stop()  # closes the sinks: the clients see their streams end
        ru1 = resource.getrusage(resource.RUSAGE_SELF)
        wall = time.monotonic() - w0
    client_lat: list[float] = []
    page_rows: list = []
    pose_ages: list[float] = []
    if proc is not None:
        got, pose_ages = parent.recv() if parent.poll(20) else ([], [])
        proc.join(5)
        page_rows = got[a.clients] if len(got) > a.clients else []
        got = got[:a.clients]
        for per_client in got:
            client_lat += [t - (t_start + f / a.fps) for f, t in per_client]
        if got and a.verbose:
            worst = sorted(((t - (t_start + f / a.fps)) * 1e3, f) for f, t in got[0])[-8:]
            print(f"  {mode}: worst client-0 frames (ms, frame): {[(round(x), f) for x, f in worst]}")
    pose_n = 0
    pose_age = float("nan")
    if pose is not None:
        pose_n = len(pose_ages)
        pose_age = float(np.median(pose_ages)) * 1e3 if pose_ages else float("nan")
    lat = summary["latency"]
    t = np.asarray(timed.times if timed else [], dtype=float) * 1e6
    out: dict[str, Any] = {
        "mode": mode, "frames_tracked": summary["frames_tracked"],
        "tracking_p50_ms": lat.get("tracking_p50_ms"), "tracking_p99_ms": lat.get("tracking_p99_ms"),
        "sink_frames": int(t.size), "sink_errors": summary.get("sink_errors", 0),
        # CPU of the whole host process (tracking, receiver, recorder, and the outputs) over the run
        "host_cpu_pct": 100.0 * (ru1.ru_utime + ru1.ru_stime - ru0.ru_utime - ru0.ru_stime) / wall,
        # the outputs' own threads (their whole life: set-up, 1.5 s before the trigger, the run)
        "publisher_cpu_pct": 100.0 * threads_cpu.get("flytrack-web-publish", 0.0) / wall,
        "pose_cpu_pct": 100.0 * threads_cpu.get("flytrack-pose", 0.0) / wall,
    }
    if t.size:
        out.update(sink_mean_us=float(t.mean()), sink_p50_us=float(np.median(t)),
                   sink_p99_us=float(np.percentile(t, 99)), sink_max_us=float(t.max()))
    if client_lat:
        c = np.asarray(client_lat) * 1e3
        out.update(client_eof=int(c.size), client_p50_ms=float(np.median(c)), client_p99_ms=float(np.percentile(c, 99)))
    if mode == "ours" and len(page_rows) > 2:
        # The page's stream: new states a second while frames came, and estimate -> state received.
        d = np.asarray([t - e for _, t, e in page_rows]) * 1e3
        span = page_rows[-1][1] - page_rows[0][1]
        out.update(page_updates_per_s=(len(page_rows) - 1) / span if span > 0 else float("nan"),
                   page_delay_p50_ms=float(np.median(d)), page_delay_p99_ms=float(np.percentile(d, 99)))
    if page_js and len(page_js[0]) > 2 and page_js[1]:
        times, delays = np.asarray(page_js[0]), np.asarray(page_js[1]) * 1e3
        out.update(browser_updates_per_s=(times.size - 1) / (times[-1] - times[0]),
                   browser_delay_p50_ms=float(np.median(delays)), browser_delay_p99_ms=float(np.percentile(delays, 99)))
    if mode == "ours":
        st = server.stats()
        out.update(dropped_slow=st["clients_dropped_slow"], pose_datagrams_received=pose_n,
                   pose_age_p50_ms=pose_age, pose_ticks=pose.stats.ticks, pose_late_ticks=pose.stats.late_ticks,
                   ui_snapshots=st["ui_snapshots"])
    return out


def _thread_cpu() -> dict[str, float]:
    """CPU seconds of each live thread of this process (Linux /proc), by thread name."""
    out: dict[str, float] = {}
    for t in threading.enumerate():
        try:
            f = Path(f"/proc/self/task/{t.native_id}/stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, TypeError):
            continue
        out[t.name] = round(out.get(t.name, 0.0) + (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK"), 2)
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--cameras", type=int, default=11)
    ap.add_argument("--targets", type=int, default=10)
    ap.add_argument("--fps", type=float, default=100.0)
    ap.add_argument("--clients", type=int, default=10)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--no-pose", action="store_true", help="Leave the pose sender thread out (to see its share).")
    ap.add_argument("--no-page", action="store_true", help="No page client (to see its share).")
    ap.add_argument("--rounds", type=int, default=2, help="Rounds of the modes, interleaved.")
    ap.add_argument("--modes", default="ours,sync,none", help="Which runs, comma separated.")
    ap.add_argument("--poll-ms", type=float, default=5.0, help="The publisher's poll period (LiveServer poll_s).")
    ap.add_argument("--browser", action="store_true", help="Also load the page in chromium during 'ours'.")
    ap.add_argument("--verbose", action="store_true", help="Print the worst frames of the first client.")
    a = ap.parse_args(argv)
    sc = make_scenario(n_cameras=a.cameras, n_targets=a.targets, duration_s=a.seconds, fps=a.fps, seed=5)
    plan = []
    seq = dict.fromkeys(sc.cameras, 0)
    for b in sc.bundles:
        for cam, pts in b.detections.items():
            ff = FeatureFrame(camera_index=cam, seq=seq[cam], camera_frame=b.trigger_frame,
                              trigger_frame=b.trigger_frame, total_points=len(pts), points=pts)
            for dg in encode_features(ff):
                plan.append((b.trigger_frame, cam, dg))
                seq[cam] += 1
    # Rounds interleave the modes, so a burst of load from elsewhere on the machine hits all of them.
    runs = [run_once(m, a, sc, plan) | {"round": k} for k in range(a.rounds) for m in a.modes.split(",")]
    print(f"live outputs on the tracking thread: {a.cameras} cameras x {a.targets} targets, {a.fps:g} fps, "
          f"{len(sc.bundles)} frames, real tracker over loopback UDP, {a.clients} Braid clients (+1 page, "
          f"+ pose at 200 Hz for 'ours') in another process")
    print(f"{'run':8} {'host CPU':>8} {'sink mean':>10} {'P50':>8} {'P99':>8} {'max':>9} {'tracking P50/P99':>18} "
          f"{'client P50/P99 (trigger->EndOfFrame)':>38}")
    for r in runs:
        sink = (f"{r['sink_mean_us']:8.1f}us {r['sink_p50_us']:6.1f}us {r['sink_p99_us']:6.1f}us "
                f"{r['sink_max_us']:7.0f}us") if r.get("sink_frames") else f"{'-':>10} {'-':>8} {'-':>8} {'-':>9}"
        trk = f"{r['tracking_p50_ms']:.2f}/{r['tracking_p99_ms']:.2f} ms" if r.get("tracking_p50_ms") else "-"
        cl = (f"{r['client_p50_ms']:.2f}/{r['client_p99_ms']:.2f} ms ({r['client_eof']} frames)"
              if r.get("client_eof") else "-")
        print(f"{r['mode'] + ' ' + str(r['round'] + 1):8} {r['host_cpu_pct']:7.0f}% {sink} {trk:>18} {cl:>38}")
    def mean_of(mode: str, key: str) -> float:
        v = [r[key] for r in runs if r["mode"] == mode and r.get(key) is not None]
        return float(np.mean(v)) if v else float("nan")

    o, sy = mean_of("ours", "sink_mean_us"), mean_of("sync", "sink_mean_us")
    ours = next((r for r in runs if r["mode"] == "ours"), {})
    if math.isfinite(o) and math.isfinite(sy):
        print(f"time added to the tracking thread per frame (mean over every frame of {a.rounds} rounds): "
              f"ours {o:.1f} us (goal < 50 us), synchronous peer {sy:.1f} us: {sy / o:.0f}x less with ours")
        print(f"tracking part P50 (mean of rounds): ours {mean_of('ours', 'tracking_p50_ms'):.2f} ms, "
              f"sync {mean_of('sync', 'tracking_p50_ms'):.2f} ms, none {mean_of('none', 'tracking_p50_ms'):.2f} ms; "
              f"client trigger->EndOfFrame P50: ours {mean_of('ours', 'client_p50_ms'):.2f} ms, "
              f"sync {mean_of('sync', 'client_p50_ms'):.2f} ms")
        print(f"host process CPU (mean of rounds, % of one core): ours {mean_of('ours', 'host_cpu_pct'):.0f}%, "
              f"sync {mean_of('sync', 'host_cpu_pct'):.0f}%, none {mean_of('none', 'host_cpu_pct'):.0f}%; "
              f"ours' threads: publisher {mean_of('ours', 'publisher_cpu_pct'):.1f}%, "
              f"pose {mean_of('ours', 'pose_cpu_pct'):.1f}%")
        print(f"page stream at {a.cameras} cameras x {a.targets} targets: {mean_of('ours', 'page_updates_per_s'):.1f} "
              f"new states/s, estimate -> state received P50 {mean_of('ours', 'page_delay_p50_ms'):.1f} ms, "
              f"P99 {mean_of('ours', 'page_delay_p99_ms'):.1f} ms (goals >= 10/s, < 100 ms)")
        if any("browser_updates_per_s" in r for r in runs):
            print(f"the page in chromium at {a.cameras} x {a.targets}: {mean_of('ours', 'browser_updates_per_s'):.1f} "
                  f"updates/s (incl. the run's end), estimate -> drawn P50 "
                  f"{mean_of('ours', 'browser_delay_p50_ms'):.1f} ms, "
                  f"P99 {mean_of('ours', 'browser_delay_p99_ms'):.1f} ms")
        print(f"ours: {ours.get('dropped_slow', 0)} clients dropped; pose {ours.get('pose_ticks', 0)} ticks "
              f"({ours.get('pose_late_ticks', 0)} late), {ours.get('pose_datagrams_received', 0)} object datagrams "
              f"received, estimate age P50 {ours.get('pose_age_p50_ms', float('nan')):.1f} ms; "
              f"{ours.get('ui_snapshots', 0)} page snapshots")
    if a.json:
        a.json.write_text(json.dumps({"web_outputs": runs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
