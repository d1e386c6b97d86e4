"""`make bench-events`, section 2: the event algorithms' throughput on one core, side by side with
dv-processing's BackgroundActivityNoiseFilter on the same events in the same run.

The stream: two 4 px blobs crossing a 346 x 260 sensor (the DVXplorer/DAVIS346 size) at 400 k events/s
with uniform noise at 100 k events/s, cut into 10 ms batches as an edge gets them. Rows:
- background-activity filter alone (2 ms window), ours and dv-processing's: the same algorithm;
- ours, the whole edge chain: background activity + refractory + hot pixel, then the cluster tracker
  with its Kalman filters (what flytrack-edge runs per slice).
Batches are prepared before timing (dv-processing's as EventStores read from an AEDAT 4 file, ours as
NumPy arrays); each figure is events in / CPU seconds (time.process_time, one thread), mean of repeats.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from datetime import timedelta
from pathlib import Path

import numpy as np

from flytrack_host.dvs.events import EVENT_DTYPE, write_events
from flytrack_host.dvs.events.algos import ClusterTracker, NoiseFilter

W, H = 346, 260


def stream(seconds: float, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n, nn = int(seconds * 400e3), int(seconds * 100e3)
    t = np.sort(rng.uniform(0, seconds * 1e6, n))
    k = rng.integers(0, 2, n)
    start = np.array([[20.0, 40.0], [320.0, 60.0]])
    vel = np.array([[150.0, 90.0], [-150.0, 90.0]])
    period = 2.0  # s: the blobs bounce back and forth so they stay on the sensor
    phase = (t * 1e-6) % period
    tri = np.where(phase < period / 2, phase, period - phase)
    pos = start[k] + vel[k] * tri[:, None] + rng.normal(0, 2.0, (n, 2))
    ev = np.zeros(n + nn, EVENT_DTYPE)
    ev["t"] = np.r_[t, rng.uniform(0, seconds * 1e6, nn)].astype(np.int64)
    ev["x"] = np.r_[np.clip(np.round(pos[:, 0]), 0, W - 1), rng.integers(0, W, nn)]
    ev["y"] = np.r_[np.clip(np.round(pos[:, 1]), 0, H - 1), rng.integers(0, H, nn)]
    ev["p"] = rng.integers(0, 2, n + nn)
    return ev[np.argsort(ev["t"], kind="stable")]


def _batches(ev: np.ndarray, us: int = 10_000) -> list[np.ndarray]:
    edges = np.searchsorted(ev["t"], np.arange(ev["t"][0], ev["t"][-1] + us, us))
    return [ev[a:b] for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]


def algos_section(args: argparse.Namespace) -> dict:
    seconds = max(1.0, args.events / 500e3)
    ev = stream(seconds)
    batches = _batches(ev)
    n = len(ev)
    print(f"\nevent algorithms: {n:,} events ({seconds:.0f} s of two blobs + noise on {W}x{H}), 10 ms batches, "
          f"one core, mean of {args.repeats}")
    try:
        import dv_processing as dv
    except ImportError:  # a peer missing is said, not hidden
        dv = None
        print("  dv-processing is not installed: no peer row")
    dv_batches = []
    if dv is not None:
        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / "bench.aedat4"
            write_events(path, ev, width=W, height=H)
            rec = dv.io.MonoCameraRecording(str(path))
            while rec.isRunning():
                b = rec.getNextEventBatch()
                if b is None:
                    break
                dv_batches.append(b)

    work: list[np.ndarray] = []  # fresh copies of the batches before each timed run (filtered in place)

    def ours_ba() -> int:
        nf = NoiseFilter(W, H, refractory_us=0, hot_pixel_count=0)
        return sum(len(nf.apply(b, inplace=True)) for b in work)

    def ours_chain() -> int:
        nf, ct = NoiseFilter(W, H), ClusterTracker(W, H)
        kept = 0
        for b in work:
            f = nf.apply(b, inplace=True)
            ct.feed(f)
            ct.clusters(int(b["t"][-1]))
            kept += len(f)
        return kept

    def dv_ba() -> int:
        filt = dv.noise.BackgroundActivityNoiseFilter((W, H), backgroundActivityDuration=timedelta(milliseconds=2))
        kept = 0
        for b in dv_batches:
            filt.accept(b)
            kept += filt.generateEvents().size()
        return kept

    rows = {"ours: background activity": ours_ba, "ours: whole chain + cluster tracker": ours_chain}
    if dv_batches:
        rows["dv-processing: background activity"] = dv_ba
    kept = {}
    for k, fn in rows.items():  # warm-up, and what each keeps
        work[:] = [b.copy() for b in batches]
        kept[k] = fn()
    times: dict[str, list[float]] = {k: [] for k in rows}
    for _ in range(args.repeats):
        for k, fn in rows.items():
            work[:] = [b.copy() for b in batches]
            t0 = time.process_time()
            fn()
            times[k].append(time.process_time() - t0)
    rate = {k: n / float(np.mean(v)) for k, v in times.items()}
    out: dict = {"events": n}
    for k in rows:
        out[k] = {"events_per_s": round(rate[k]), "kept": kept[k]}
        print(f"  {k:<38}{rate[k] / 1e6:8.1f} M events/s   kept {kept[k]:,}")
    if "dv-processing: background activity" in rate:
        r = rate["ours: background activity"] / rate["dv-processing: background activity"]
        out["ba_ratio_vs_dv"] = round(r, 2)
        print(f"  background activity, ours / dv-processing: {r:.2f}x; whole chain: "
              f"{rate['ours: whole chain + cluster tracker'] / 1e6:.1f} M events/s (goal >= 20)")
    return out
