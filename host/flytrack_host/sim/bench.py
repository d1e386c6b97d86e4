"""Benchmark of the simulated cameras: frames rendered per second on one core.

The demo needs cameras x fps frames a second (5 x 100 = 500 at the defaults; 11 x 200 = 2200 for the
stress run); this prints how many one core makes, with the renderer's defaults, at 640 x 480.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from flytrack_host.sim.flight import Arena, simulate_flight
from flytrack_host.sim.render import CameraRenderer, RenderParams
from flytrack_host.sim.rig import make_cameras


def bench(cameras: int, animals: int, fps: float, seconds: float) -> dict[str, float]:
    gt = simulate_flight(animals, seconds, fps, seed=1)
    cams = make_cameras(cameras, Arena(), seed=1)
    rs = [CameraRenderer(c, RenderParams(), seed=i) for i, c in enumerate(cams)]
    for r in rs:  # warm the background cache
        r.render(0.0, gt.pos[0], gt.axis[0], gt.body_length_m, gt.body_width_m)
    t0 = time.perf_counter()
    c0 = time.process_time()  # CPU time too: on a shared machine the wall clock mostly measures the others
    n = 0
    for k in range(gt.n_frames):
        for r in rs:
            r.render(gt.t[k], gt.pos[k], gt.axis[k], gt.body_length_m, gt.body_width_m)
            n += 1
    dt = time.perf_counter() - t0
    cpu = time.process_time() - c0
    need = cameras * fps
    return {"cameras": cameras, "animals": animals, "fps": fps, "frames": n, "seconds": dt,
            "frames_per_s": n / dt, "needed_frames_per_s": need, "realtime_factor": n / dt / need,
            "ms_per_frame": dt / n * 1e3, "cpu_ms_per_frame": cpu / n * 1e3}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--seconds", type=float, default=2.0)
    a = ap.parse_args()
    rows = [bench(5, 3, 100.0, a.seconds), bench(11, 10, 200.0, a.seconds / 2)]
    print("simulated camera rendering (640x480, one core):")
    for r in rows:
        print(f"  {r['cameras']:2d} cams x {r['fps']:.0f} fps, {r['animals']:2d} animals: "
              f"{r['frames_per_s']:7.0f} frames/s ({r['ms_per_frame']:.3f} ms/frame, "
              f"CPU {r['cpu_ms_per_frame']:.3f} ms), "
              f"need {r['needed_frames_per_s']:.0f}/s -> {r['realtime_factor']:.1f}x real time")
    if a.json:
        a.json.write_text(json.dumps({"sim_render": rows}, indent=1))


if __name__ == "__main__":
    main()
