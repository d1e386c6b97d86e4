#!/usr/bin/env python3
"""A closed-loop stimulus: a virtual post held at a fixed distance ahead of the animal.

It reads FlyTrack's VR pose stream (UDP, `flytrack_host.live.pose`), takes the animal's heading
from its horizontal velocity, and places the post `--distance` metres ahead of it at the animal's
height, every pose (200 a second by default). A real stimulus program would draw the post there; this
one prints where it is, a few times a second, and a summary at the end.

Against the simulated rig:

    .venv/bin/flytrack demo --seconds 20 --pose 127.0.0.1:7300 --pose-lead-ms 10 &
    .venv/bin/python examples/virtual_post.py --port 7300 --seconds 15

With a live rig: `flytrack run RIG --pose HOST:7300` and this program on the display computer.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

from flytrack_host.live.pose import PoseClient

MIN_SPEED = 0.05  # m/s: slower than this, the heading is kept (a hovering animal has none)


def post_position(pos: tuple[float, float, float], vel: tuple[float, float, float], distance: float,
                  heading: float | None) -> tuple[tuple[float, float, float], float | None]:
    """(post x, y, z), heading used (radians, None when still unknown)."""
    vx, vy = vel[0], vel[1]
    if math.hypot(vx, vy) >= MIN_SPEED:
        heading = math.atan2(vy, vx)
    if heading is None:
        return (math.nan, math.nan, math.nan), None
    return (pos[0] + distance * math.cos(heading), pos[1] + distance * math.sin(heading), pos[2]), heading


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--port", type=int, default=7300, help="UDP port the pose stream is sent to")
    ap.add_argument("--host", default="127.0.0.1", help="address to listen on")
    ap.add_argument("--distance", type=float, default=0.05, help="post distance ahead of the animal, m")
    ap.add_argument("--seconds", type=float, default=None,
                    help="stop this long after the first pose (default: Ctrl-C)")
    ap.add_argument("--wait", type=float, default=120.0,
                    help="give up (exit 2) when no pose came within this long of the start; 0 = wait for ever")
    ap.add_argument("--print-hz", type=float, default=4.0, help="status lines per second")
    ap.add_argument("--json", action="store_true", help="print every post update as a JSON line")
    a = ap.parse_args(argv)
    try:
        client = PoseClient(a.port, a.host)
    except OSError as exc:
        print(f"error: cannot listen on {a.host}:{a.port}: {exc}", file=sys.stderr)
        return 2
    heading: float | None = None
    n = n_posts = n_none = 0
    ages: list[float] = []
    # --seconds counts from the first pose: the rig (a demo still starting, a run not yet triggered) may
    # start sending well after this program started.
    started = time.monotonic()
    t0: float | None = None
    last_print = 0.0
    try:
        while t0 is None or a.seconds is None or time.monotonic() - t0 < a.seconds:
            m = client.recv(timeout=0.5)
            if m is None:
                if t0 is None and a.wait > 0 and time.monotonic() - started > a.wait:
                    print(f"error: no pose datagram on {a.host}:{a.port} within {a.wait:.0f} s "
                          f"(is the rig sending to it? flytrack run/demo --pose {a.host}:{a.port})",
                          file=sys.stderr)
                    return 2
                continue
            if t0 is None:
                t0 = time.monotonic()
            n += 1
            if m.no_object:
                n_none += 1
                heading = None  # the animal is gone: the next one starts afresh
                continue
            post, heading = post_position(m.position, m.velocity, a.distance, heading)
            ages.append(m.age_s)
            if heading is None:
                continue
            n_posts += 1
            if a.json:
                print(json.dumps({"obj_id": m.obj_id, "frame": m.trigger_frame, "animal": m.position,
                                  "velocity": m.velocity, "post": post, "age_s": m.age_s}), flush=True)
            elif time.monotonic() - last_print >= 1.0 / a.print_hz:
                last_print = time.monotonic()
                print(f"obj {m.obj_id} frame {m.trigger_frame}: animal ({m.position[0]:+.3f}, {m.position[1]:+.3f}, "
                      f"{m.position[2]:+.3f}) m, post ({post[0]:+.3f}, {post[1]:+.3f}, {post[2]:+.3f}) m, "
                      f"estimate age {m.age_s * 1e3:.1f} ms", flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        client.close()
    dt = max(time.monotonic() - (t0 if t0 is not None else started), 1e-9)
    ages.sort()
    age = f"{ages[len(ages) // 2] * 1e3:.1f} ms" if ages else "-"
    print(f"summary: {n} poses in {dt:.1f} s ({n / dt:.0f}/s), {n_posts} post updates, {n_none} without an "
          f"animal, {client.stats.malformed} malformed; estimate age P50 {age}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
