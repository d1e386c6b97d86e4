"""Benchmark: the host data path live over loopback UDP with the real tracker.

A synthetic scenario (seed 000's arena, 5 cameras, 2 flies, 100 fps) is sent frame by frame by five
UDP senders paced like a trigger; the pipeline receives, synchronises, tracks, sends live datagrams
and records. The trigger clock is the pacing clock, so "total" latency is trigger -> estimate as in
seed 000 §5 (minus exposure and extraction, which the simulated edges do not have).

    .venv/bin/python tests/host/bench_pipeline.py [--seconds 5] [--cameras 5] [--targets 2] [--fps 100]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import socket
import sys
import tempfile
import time
from pathlib import Path

from flytrack_host.intake.sync import FixedRateClock
from flytrack_host.live.udp import LiveClient
from flytrack_host.pipeline import HostPipeline
from flytrack_host.protocol.udp import FeatureFrame, encode_features
from flytrack_host.rig import parse_rig
from flytrack_host.tracking.synthetic import make_scenario


def send_all(plan: list, dest: tuple[str, int], t_start: float, fps: float) -> None:
    socks: dict[int, socket.socket] = {}
    while time.time() < t_start:
        time.sleep(0.001)
    for frame, cam, dg in plan:
        wait = t_start + frame / fps - time.time()  # this frame's trigger; the edges send at once
        if wait > 0:
            time.sleep(wait)
        sock = socks.get(cam) or socks.setdefault(cam, socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
        sock.sendto(dg, dest)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--cameras", type=int, default=5)
    ap.add_argument("--targets", type=int, default=2)
    ap.add_argument("--fps", type=float, default=100.0)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    sc = make_scenario(n_cameras=a.cameras, n_targets=a.targets, duration_s=a.seconds, fps=a.fps, seed=5)
    client = LiveClient(0)
    rig = parse_rig({
        "name": "bench", "trigger": {"kind": "software", "fps": a.fps},
        "host": {"listen": "127.0.0.1:7000", "live_subscribers": [f"127.0.0.1:{client.port}"]},
        "cameras": [{"name": f"cam{i}", "index": i, "edge": "127.0.0.1"} for i in sc.cameras],
    })
    # Encode every datagram before the run: (frame, camera, bytes).
    plan = []
    seq = dict.fromkeys(sc.cameras, 0)
    for b in sc.bundles:
        for cam, pts in b.detections.items():
            ff = FeatureFrame(camera_index=cam, seq=seq[cam], camera_frame=b.trigger_frame,
                              trigger_frame=b.trigger_frame, total_points=len(pts), points=pts)
            for dg in encode_features(ff):
                plan.append((b.trigger_frame, cam, dg))
                seq[cam] += 1
    t_start = time.time() + 1.0
    with tempfile.TemporaryDirectory() as d:
        pipe = HostPipeline(rig, sc.cameras, clock=FixedRateClock(a.fps, start_time=t_start),
                            recording_path=Path(d) / "bench.flytrack", bind="127.0.0.1:0")
        pipe.start()
        # The edges are another process (as on a real rig), so they do not share the GIL with the host.
        sender = mp.get_context("fork").Process(target=send_all, args=(plan, pipe.address, t_start, a.fps))
        sender.start()
        sender.join()
        time.sleep(0.1)
        live = list(client.frames(timeout=0.2))
        summary = pipe.stop()
    client.close()
    lat = summary["latency"]
    print(f"host pipeline, {a.cameras} cameras, {a.targets} targets, {a.fps:g} fps, {len(sc.bundles)} frames "
          f"over loopback UDP with the real tracker:")
    print(f"  frames tracked {summary['frames_tracked']}, bundles complete {summary['bundles_complete']}, "
          f"closed at deadline {summary['bundles_deadline']}, live frames received {len(live)}")
    print("  " + summary["latency_text"].replace("\n", "\n  "))
    if a.json:
        a.json.write_text(json.dumps({"host_pipeline_latency": lat, "frames_tracked": summary["frames_tracked"],
                                      "live_frames": len(live)}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
