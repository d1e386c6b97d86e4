"""CPU cost of the simavr harness paced in real time (the simulated rig's trigger).

Runs the firmware at 100 fps (paced, with clock queries at 10 Hz as a trigger session makes them)
and prints the harness's CPU use from /proc/PID/stat (utime + stime) over the run:

    .venv/bin/python firmware/avr_trigger/harness/bench_pacing.py [--seconds 4] [--fps 100]
"""

from __future__ import annotations

import argparse
import os
import time

from flytrack_host.trigger import simulator
from flytrack_host.trigger.device import TriggerDevice


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--fps", type=float, default=100.0)
    ap.add_argument("--query-hz", type=float, default=10.0)
    ap.add_argument("--harness", default=None, help="harness binary (default: the build's)")
    args = ap.parse_args()
    if not simulator.tools_available():
        raise SystemExit("avr-gcc / simavr not installed: nothing to measure")
    harness, elf = simulator.build()
    with simulator.SimulatedTrigger(elf=elf, harness=args.harness or harness, realtime=True) as sim:
        dev = TriggerDevice(sim.pty, reset_wait_s=0)
        fps = dev.set_rate(args.fps)
        dev.start()
        time.sleep(0.3)
        c0, w0 = cpu_seconds(sim.proc.pid), time.monotonic()
        queries = 0
        while time.monotonic() - w0 < args.seconds:
            dev.query_clock()
            queries += 1
            time.sleep(1.0 / args.query_hz)
        c1, w1 = cpu_seconds(sim.proc.pid), time.monotonic()
        dev.stop()
        dev.close()
    print(f"simavr harness paced at {fps:g} fps, {queries} clock queries in {w1 - w0:.1f} s: "
          f"{100 * (c1 - c0) / (w1 - w0):.1f} % of a core (utime+stime); "
          f"clock model residual {dev.model.residual_s * 1e6:.1f} us")


if __name__ == "__main__":
    main()
