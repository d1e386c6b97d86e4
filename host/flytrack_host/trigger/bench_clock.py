"""Benchmark: the trigger clock model against a crystal that is off (make bench-trigger-clock).

The firmware runs paced in simavr with its crystal +37 ppm off and drifting by 0.5 ppm/s; the host
queries its clock over the pty every 10 ms for --seconds. The queries are then fitted by the clock
model three ways and scored against the harness's truth (flytrack_host.trigger.crystal):
- "robust": the model's default filter (no round trip shorter than the wire; the tightest round
  trip of each group of 1/keep_fraction queries; half the unexplained latency to each way);
- "every query": the same placement, no delay filter (keep_fraction 1);
- per window: the robust fit over consecutive --window seconds (the gain a live model has).
Over the whole run a straight line cannot follow a rate that drifts 0.5 ppm/s (20 ppm in 40 s: the
line is off the curve by ~100 us at its ends), so the windows are the figure that counts.
Printed: gain error against the true rate (ppm), the fit's own standard error, the number of
queries used and their span, each trigger edge's host time error (mean, sd, worst, us), and the
load average (the round trips scatter with the load).

Run: python -m flytrack_host.trigger.bench_clock [--seconds 40] [--window 10] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np

from .clock_model import ClockModel
from .crystal import record_crystal_run, score_fit, score_windows
from .device import FIRMWARE_BAUD, clock_link_timing
from .simulator import build


def robust_model(keep_fraction: float = 0.1) -> ClockModel:
    return ClockModel(window=100_000, max_rtt_s=0.05, keep_fraction=keep_fraction,
                      link=clock_link_timing(FIRMWARE_BAUD))


def _row(name: str, f: dict[str, float]) -> str:
    return (f"{name:<34} {f['queries']:>7.0f} {f['used']:>5.0f} {f['span_s']:>6.1f} {f['gain_err_ppm']:>+10.3f} "
            f"{f['gain_se_ppm']:>8.3f} {f['edge_mean_us']:>+8.1f} {f['edge_sd_us']:>7.1f} {f['edge_max_us']:>8.1f} "
            f"{f['sim_behind_max_ms']:>13.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=40.0, help="length of the paced run")
    ap.add_argument("--window", type=float, default=10.0, help="seconds of queries per windowed fit")
    ap.add_argument("--ppm", type=float, default=37.0)
    ap.add_argument("--drift", type=float, default=0.5, help="ppm per second")
    ap.add_argument("--keep", type=float, default=0.1, help="keep_fraction of the robust fit")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--save-run", type=Path, default=None, help="write the raw queries and truth (.npz)")
    args = ap.parse_args()
    harness, elf = build()
    load0 = os.getloadavg()[0]
    run = record_crystal_run(args.seconds, args.ppm, args.drift, elf=elf, harness=harness)
    load1 = os.getloadavg()[0]
    if args.save_run:
        np.savez(args.save_run, **{k: v for k, v in vars(run).items()})
    rtt = (run.host_t1 - run.host_t0) * 1e3
    print(f"crystal {args.ppm:+g} ppm drifting {args.drift:g} ppm/s; {len(rtt)} clock queries over "
          f"{run.host_t1[-1] - run.host_t0[0]:.1f} s; round trip median {np.median(rtt):.2f} ms, P90 "
          f"{np.percentile(rtt, 90):.2f} ms, max {rtt.max():.2f} ms (wire alone "
          f"{clock_link_timing(FIRMWARE_BAUD).min_rtt_s * 1e3:.2f} ms); load average {load0:.1f} -> {load1:.1f}; "
          f"harness at nice -5: {run.priority_raised}; simulator behind the wall clock (its truth void) in "
          f"{np.mean(run.sim_behind_s > 0) * 100:.1f} % of queries, by up to {run.sim_behind_s.max() * 1e3:.2f} ms; "
          f"{run.timeouts} replies later than 2 s (lost)")
    print(f"{'fit':<34} {'queries':>7} {'used':>5} {'span s':>6} {'gain err ppm':>10} {'se ppm':>8} "
          f"{'edge mean us':>8} {'sd us':>7} {'worst us':>8} {'sim behind ms':>13}")
    whole = score_fit(run, robust_model(args.keep))
    every = score_fit(run, robust_model(1.0))
    print(_row("robust, whole run (drift curves it)", whole))
    print(_row("every query (no delay filter)", every))
    wins = score_windows(run, lambda: robust_model(args.keep), args.window)
    for i, w in enumerate(wins):
        print(_row(f"robust, {args.window:g} s window {i + 1}", w))
    g = np.abs([w["gain_err_ppm"] for w in wins]) if wins else np.array([np.nan])
    print(f"robust over {len(wins)} windows of {args.window:g} s: |gain error| median {np.median(g):.3f} ppm, "
          f"worst {g.max():.3f} ppm (goal 1 ppm); whole run {whole['gain_err_ppm']:+.3f} ppm "
          f"(se {whole['gain_se_ppm']:.3f}) vs {every['gain_err_ppm']:+.3f} ppm (se {every['gain_se_ppm']:.3f}) "
          f"with every query")
    if args.json:
        args.json.write_text(json.dumps({"bench-trigger-clock": {
            "ppm": args.ppm, "drift_ppm_per_s": args.drift, "load_average": [load0, load1],
            "robust_whole": whole, "every_query_whole": every, "robust_windows": wins}}, indent=2) + "\n")


if __name__ == "__main__":
    main()
