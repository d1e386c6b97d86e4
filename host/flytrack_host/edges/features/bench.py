"""`make bench-edge`: the C feature extractor against a fair OpenCV pipeline and the read floor.

For 640x480 and 2048x2048 8-bit frames with 0, 1 and 10 moving targets on a noisy textured background,
on one core (cv2.setNumThreads(1)), on the same frames:

- the C library, timed per frame in C (libflytrack_features_bench: the monotonic clock around the very
  ft_fx_process the host loads, no foreign-call overhead);
- OpenCV written the way a user who knows it would write the same detector: one cv2.inRange of the
  frame against the per-pixel low/high thresholds, an early exit when cv2.countNonZero says every
  pixel is background, else cv2.findContours (outer contours) to locate the regions, and connected
  components and moments only inside each region's bounding box; the background
  (cv2.accumulateWeighted of the frame and its square) and the thresholds (cv2 arithmetic) are
  refreshed every bg_update_interval frames, as in C;
- the floor: one read pass over the frame (an OR of its bytes in 64-byte vectors, timed in C the same
  way), the least any detector that looks at every pixel must spend.

Two cache states, each the same for the C path and its floor:
- hot: the frame is read once (untimed) just before each timed call, so it is in cache;
- ring: the frames come round a ring of buffers larger than the caches (--ring-mb, default 128 MB;
  L3 here is 32 MB), each touched again only a whole ring later, so it comes from memory, as a frame
  a camera has just written by DMA. The C path, its floor and OpenCV take turns along the ring, and
  the C vs OpenCV ratio is taken here (both read the frame from memory), and so is the goal's ratio
  to the floor, which places the C path against the memory-bandwidth limit. The in-cache ratio, against
  the cache's bandwidth, is printed on a line of its own.

Where the in-cache time goes: the C path is also timed, hot and interleaved with the others, with the
background update turned off (bg_update_interval 0: the same frames against the background taken at the
start; the timed path's model, updated ten times over the repeating frames, has partly learned where
the targets pass, so at 640x480 with 10 targets the path without updates tests about 8% more
candidates: its targets' share is a little high and the update's a little low), so
that each row splits into the floor, the rest of the scan, the spread update and the targets' own work
(per target: the no-update figure less that of the same frame size without targets, over the count).
This is a breakdown only: every headline figure and ratio keeps the update every 200 frames.

Every figure is the mean over a whole number of background-update intervals (so the periodic update is
paid in it), with the P99 and the longest frame; the paths are interleaved one interval at a time so that
load from elsewhere falls on all alike. Five rounds replay the same frames (400 at 640x480, 200 at 2048x2048), and each
frame position counts with its best round: on a shared machine a frame preempted by another job in one
round is not preempted in all five (the raw means over all rounds are in the JSON). The bench checks
that both pipelines find the same centroids (to 1e-3 px) before it times them. BENCH_JSON=PATH (or
--json PATH) writes the figures.
"""

from __future__ import annotations

import argparse
import ctypes
import dataclasses
import json
import os
import platform
import sys
import time

import cv2
import numpy as np

from flytrack_host.edges.features import ExtractorParams, FeatureExtractor
from flytrack_host.util.native import NativeLibraryError, load_library

CASES = [(640, 480, 0), (640, 480, 1), (640, 480, 10), (2048, 2048, 0), (2048, 2048, 1), (2048, 2048, 10)]
CENTROID_TOL_PX = 1e-3


def make_frames(w: int, h: int, n_targets: int, count: int, seed: int = 1) -> tuple[np.ndarray, list]:
    rng = np.random.default_rng(seed)
    bg = cv2.GaussianBlur(rng.uniform(30, 140, (h, w)).astype(np.float32), (0, 0), 3)
    frames = []
    pos = rng.uniform([20, 20], [w - 20, h - 20], (n_targets, 2))
    vel = rng.uniform(-3, 3, (n_targets, 2))
    for _ in range(count):
        img = bg + rng.normal(0, 2.0, (h, w)).astype(np.float32)
        for (x, y) in pos:
            x0, x1, y0, y1 = int(x) - 8, int(x) + 9, int(y) - 8, int(y) + 9
            yy, xx = np.mgrid[y0:y1, x0:x1]
            img[y0:y1, x0:x1] += 120 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 2.0 ** 2))
        pos += vel
        bounce = (pos < 20) | (pos > np.array([w - 20, h - 20]))
        vel[bounce] *= -1
        pos = np.clip(pos, 20, [w - 21, h - 21])
        frames.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return np.clip(np.rint(bg), 0, 255).astype(np.uint8), frames


class OpenCVPipeline:
    """The same detector (polarity both) written idiomatically with OpenCV, single-threaded.

    A pixel x is a candidate when x > hi or x < lo, hi = floor(mean + T), lo = ceil(mean - T),
    T = max(diff_threshold, n_sigma * std): exactly the library's rule (features.c). A region's
    centre is the moment centroid of the weights |x - mean| - cut over its pixels with |x - mean| >= cut,
    cut = max(clear_fraction * peak, despeckle_threshold, diff_threshold).
    """

    def __init__(self, bg: np.ndarray, p: ExtractorParams) -> None:
        self.p = p
        self.mean = bg.astype(np.float32)
        self.sq = cv2.multiply(self.mean, self.mean)
        self.n = 0
        self.npix = bg.size
        self._refresh()

    def _refresh(self) -> None:
        var = cv2.max(cv2.subtract(self.sq, cv2.multiply(self.mean, self.mean)), 0.0)
        t = cv2.max(cv2.multiply(cv2.sqrt(var), float(self.p.n_sigma)), float(self.p.diff_threshold))
        # hi = floor(min(mean + T, 255)); lo = ceil(max(mean - T, 0)): truncation is floor here (>= 0).
        self.hi8 = cv2.min(cv2.add(self.mean, t), 255.0).astype(np.uint8)
        dn = cv2.max(cv2.subtract(self.mean, t), 0.0)
        lo = dn.astype(np.uint8)
        self.lo8 = cv2.add(lo, cv2.compare(lo.astype(np.float32), dn, cv2.CMP_LT) // 255)

    def process(self, frame: np.ndarray) -> list[tuple[float, float]]:
        out: list[tuple[float, float]] = []
        background = cv2.inRange(frame, self.lo8, self.hi8)  # 255 where lo <= x <= hi
        if cv2.countNonZero(background) < self.npix:  # else: nothing to look at, the common case
            cand = cv2.bitwise_not(background)
            # Outer contours locate each region cheaply (labelling the whole frame costs ~100x more);
            # labels and moments are then computed inside each region's bounding box only.
            contours, _ = cv2.findContours(cand, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            for c in contours:
                x, y, w, h = cv2.boundingRect(c)
                px, py = c[0, 0]
                out.append(self._region(frame, cand, x, y, w, h, int(px) - x, int(py) - y))
        self.n += 1
        if self.n % self.p.bg_update_interval == 0:
            cv2.accumulateWeighted(frame, self.mean, self.p.alpha)
            cv2.accumulateWeighted(cv2.multiply(frame, frame, dtype=cv2.CV_32F), self.sq, self.p.alpha)
            self._refresh()
        return out

    def _region(self, frame, cand, x, y, w, h, px, py) -> tuple[float, float]:  # noqa: ANN001
        """Centroid of the region holding (px, py) (box-relative), within its bounding box."""
        roi = cand[y:y + h, x:x + w]
        # Another region may reach into the box: keep the component of the contour's own pixel.
        _, labels = cv2.connectedComponents(roi, connectivity=8)
        inside = labels == labels[py, px]
        d = cv2.absdiff(frame[y:y + h, x:x + w].astype(np.float32), self.mean[y:y + h, x:x + w])
        d[~inside] = 0
        beta = float(d.max())
        cut = max(self.p.clear_fraction * beta, self.p.despeckle_threshold, self.p.diff_threshold)
        m = cv2.moments(cv2.max(cv2.subtract(d, cut), 0.0))
        if m["m00"] > 0:
            return x + m["m10"] / m["m00"], y + m["m01"] / m["m00"]
        peak = cv2.minMaxLoc(d)[3]  # every kept pixel sits at the cut: C reports the peak
        return float(x + peak[0]), float(y + peak[1])


def check_same_centroids(fx: FeatureExtractor, cvp: OpenCVPipeline, frames: list[np.ndarray]) -> float:
    """Runs both on the frames; raises if they disagree. Returns the worst centroid difference (px)."""
    worst = 0.0
    for i, f in enumerate(frames):
        r = fx.process(f)
        c_pts = sorted(zip(r.points["x_dist"].tolist(), r.points["y_dist"].tolist(), strict=True))
        cv_pts = sorted(cvp.process(f))
        if len(c_pts) != len(cv_pts):
            raise AssertionError(f"frame {i}: C found {len(c_pts)} points, OpenCV {len(cv_pts)}")
        for a, b in zip(c_pts, cv_pts, strict=True):
            worst = max(worst, abs(a[0] - b[0]), abs(a[1] - b[1]))
    if worst > CENTROID_TOL_PX:
        raise AssertionError(f"C and OpenCV centroids differ by {worst:.2e} px (> {CENTROID_TOL_PX})")
    return worst


def _stats(ns: np.ndarray | list[int]) -> dict[str, float]:
    us = np.asarray(ns, dtype=np.float64) / 1000.0
    mean = float(np.mean(us))
    return {"mean_us": mean, "median_us": float(np.median(us)), "p99_us": float(np.percentile(us, 99)),
            "max_us": float(np.max(us)), "fps": 1e6 / mean, "frames": len(us)}


def _time(fn, frames: list, n: int) -> list[int]:  # noqa: ANN001
    ns = []
    for i in range(n):
        f = frames[i % len(frames)]
        t0 = time.perf_counter_ns()
        fn(f)
        ns.append(time.perf_counter_ns() - t0)
    return ns


class CTimer:
    """libflytrack_features_bench: the C path and the read floor timed per frame in C."""

    def __init__(self) -> None:
        lib = load_library("flytrack_features_bench", "edge/feature_extractor", "benchmark helper library")
        P = ctypes.POINTER
        vp, sz = ctypes.c_void_p, ctypes.c_size_t
        lib.ft_bench_time_process.restype = ctypes.c_int
        lib.ft_bench_time_process.argtypes = [vp, vp, vp, P(vp), sz, sz, sz, sz, ctypes.c_int, P(ctypes.c_uint64)]
        lib.ft_bench_time_read.restype = None
        lib.ft_bench_time_read.argtypes = [P(vp), sz, sz, sz, sz, ctypes.c_int, P(ctypes.c_uint64)]
        self.lib = lib

    @staticmethod
    def ptrs(frames: list[np.ndarray]) -> ctypes.Array:
        return (ctypes.c_void_p * len(frames))(*[f.ctypes.data for f in frames])

    def process(self, fx: FeatureExtractor, ptrs: ctypes.Array, start: int, count: int, warm: bool) -> np.ndarray:
        ns = np.zeros(count, np.uint64)
        proc = ctypes.cast(fx._lib.ft_fx_process, ctypes.c_void_p)
        out = ns.ctypes.data_as(ctypes.POINTER(ctypes.c_uint64))
        rc = self.lib.ft_bench_time_process(proc, fx._h, ctypes.byref(fx._res), ptrs, len(ptrs), start, count,
                                            fx.frame_bytes, int(warm), out)
        if rc:
            raise RuntimeError(f"ft_fx_process failed: {rc}")
        return ns

    def read(self, ptrs: ctypes.Array, nbytes: int, start: int, count: int, warm: bool) -> np.ndarray:
        ns = np.zeros(count, np.uint64)
        self.lib.ft_bench_time_read(ptrs, len(ptrs), start, count, nbytes, int(warm),
                                    ns.ctypes.data_as(ctypes.POINTER(ctypes.c_uint64)))
        return ns


def run(quick: bool = False, ring_mb: float = 128.0) -> dict:
    cv2.setNumThreads(1)
    params = ExtractorParams()
    iv = params.bg_update_interval
    timer = CTimer()
    load_before = os.getloadavg()
    results = []
    for w, h, nt in CASES:
        big = w * h > 1_000_000
        # Rounds of whole update intervals (so the periodic update is paid in each round's mean).
        per_round = 1 if big else 2
        n_rounds = 2 if quick else 5
        bg, frames = make_frames(w, h, nt, 16 if big else 32)
        fx = FeatureExtractor(w, h, params=params)
        fx.process(bg)
        cvp = OpenCVPipeline(bg, params)
        worst = check_same_centroids(fx, cvp, frames)
        npts = float(np.median([fx.process(f).total_points for f in frames]))
        fx.close()
        # The ring: a whole number of copies of the frame sequence, at least ring_mb in all, so that
        # buffer j holds frame j % len(frames) and the ring keeps the frames' order.
        nf = len(frames)
        copies = max(1, -(-int(ring_mb * 2**20) // (nf * frames[0].nbytes)))
        ring = [frames[j % nf].copy() for j in range(nf * copies)]
        hot_p, ring_p = CTimer.ptrs(frames), CTimer.ptrs(ring)
        # Each timed path starts just after taking the background: the same point of the update cycle.
        fx_hot, fx_ring = FeatureExtractor(w, h, params=params), FeatureExtractor(w, h, params=params)
        fx_hot.process(bg)
        fx_ring.process(bg)
        # The breakdown only: the same path without the background update.
        fx_nu = FeatureExtractor(w, h, params=dataclasses.replace(params, bg_update_interval=0))
        fx_nu.process(bg)
        cvp = OpenCVPipeline(bg, params)
        # Rounds of whole update intervals; in each, the paths take turns one interval at a time. Each
        # round replays the same frame sequence from its start, so that frame position i does the same
        # work in every round (the background update included, at the interval's last frame).
        rounds: dict[str, list[np.ndarray]] = {k: [] for k in ("ch", "fh", "cr", "fr", "cv", "cn")}
        base = 0  # along the ring (a multiple of nf: ring buffer base + i holds frame i % nf)
        step = -(-3 * iv // nf) * nf
        for _ in range(n_rounds):
            got: dict[str, list] = {k: [] for k in rounds}
            for k in range(per_round):
                at = k * iv
                got["ch"].append(timer.process(fx_hot, hot_p, at, iv, warm=True))
                got["fh"].append(timer.read(hot_p, frames[0].nbytes, at, iv, warm=True))
                got["cn"].append(timer.process(fx_nu, hot_p, at, iv, warm=True))
                got["cr"].append(timer.process(fx_ring, ring_p, base + at, iv, warm=False))
                base = (base + step) % len(ring)
                got["fr"].append(timer.read(ring_p, frames[0].nbytes, base + at, iv, warm=False))
                base = (base + step) % len(ring)
                cv_frames = [ring[(base + at + i) % len(ring)] for i in range(iv)]
                got["cv"].append(np.asarray(_time(cvp.process, cv_frames, iv), np.uint64))
                base = (base + step) % len(ring)
            for key, parts in got.items():
                rounds[key].append(np.concatenate(parts))
        fx_hot.close()
        fx_ring.close()
        fx_nu.close()
        # Per frame position, the best of the rounds (a frame preempted by another job in one round is
        # not in all of them), then the mean over the positions: the updates stay in it. The raw
        # figures over all rounds, preemptions included, are kept in the JSON.
        stats = {}
        for key, rs in rounds.items():
            st = _stats(np.min(np.stack(rs), axis=0))
            raw = _stats(np.concatenate(rs))
            st["raw_mean_us"], st["raw_p99_us"], st["rounds"] = raw["mean_us"], raw["p99_us"], len(rs)
            stats[key] = st
        c_hot, fl_hot, c_ring, fl_ring, o = stats["ch"], stats["fh"], stats["cr"], stats["fr"], stats["cv"]
        results.append({
            "width": w, "height": h, "targets": nt, "points_found_median": npts,
            "centroid_max_diff_px": worst, "ring_buffers": len(ring),
            "ring_mb": len(ring) * frames[0].nbytes / 2**20,
            "c_hot": c_hot, "c_hot_no_update": stats["cn"], "read_floor_hot": fl_hot,
            "c_ring": c_ring, "read_floor_ring": fl_ring,
            "opencv_ring": o,
            "speedup_vs_opencv": o["mean_us"] / c_ring["mean_us"],
            "c_over_floor_hot": c_hot["mean_us"] / fl_hot["mean_us"],
            "c_over_floor_ring": c_ring["mean_us"] / fl_ring["mean_us"],
        })
        del ring
    return {
        "benchmark": "edge feature extraction, one core, mean per frame including background updates",
        "cpu": platform.processor() or platform.machine(),
        "opencv": cv2.__version__,
        "bg_update_interval": iv,
        "load_avg_1min": [load_before[0], os.getloadavg()[0]],
        "results": results,
    }


def print_breakdown(results: list[dict]) -> None:
    """Where each in-cache mean goes: floor, the rest of the scan, the spread update, the targets."""
    print("where the C hot mean goes (us per frame): read floor + rest of the scan with no target + targets' "
          "own work + background update (C hot less C hot without updates)")
    empty = {r["width"]: r["c_hot_no_update"]["mean_us"] for r in results if r["targets"] == 0}
    for r in results:
        nu, fl = r["c_hot_no_update"]["mean_us"], r["read_floor_hot"]["mean_us"]
        scan0 = empty.get(r["width"], nu)
        tgt = nu - scan0
        per = f" ({tgt / r['targets']:.2f} per target)" if r["targets"] else ""
        print(f"{r['width']:>5}x{r['height']:<4} {r['targets']:>3}: {r['c_hot']['mean_us']:6.1f} = floor {fl:5.1f} "
              f"+ scan {scan0 - fl:+5.1f} + targets {tgt:5.1f}{per} + update {r['c_hot']['mean_us'] - nu:4.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=os.environ.get("BENCH_JSON") or None, help="write figures here")
    ap.add_argument("--quick", action="store_true", help="fewer frames")
    ap.add_argument("--ring-mb", type=float, default=128.0,
                    help="size of the ring of frame buffers (more than the last-level cache)")
    args = ap.parse_args()
    if args.ring_mb <= 0:
        raise SystemExit("--ring-mb must be > 0")
    try:
        fig = run(args.quick, args.ring_mb)
    except NativeLibraryError as exc:  # a library not built: one line, exit 2
        print(f"bench-edge: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    la = fig["load_avg_1min"]
    nr = fig["results"][0]["c_hot"]["rounds"]
    print("mean / P99 us per frame over whole background-update intervals (the updates included), each frame "
          f"position's best of {nr} rounds; one core; same centroids checked (max diff shown); load average "
          f"{la[0]:.1f} -> {la[1]:.1f}")
    print("hot: frame read just before (in cache); ring: frames from memory, round a ring of "
          f"{fig['results'][0]['ring_mb']:.0f}+ MB; C vs OpenCV on the ring (same cache state)")
    print(f"{'frame':>10} {'tgt':>3} {'dpx':>6} | {'C hot':>13} {'floor':>5} {'C/fl':>5} | "
          f"{'C ring':>13} {'floor':>5} {'C/fl':>5} | {'OpenCV ring':>15} {'cv/C':>5}")
    for r in fig["results"]:
        ch, fh, cr, fr, o = r["c_hot"], r["read_floor_hot"], r["c_ring"], r["read_floor_ring"], r["opencv_ring"]
        print(f"{r['width']:>5}x{r['height']:<4} {r['targets']:>3} {r['centroid_max_diff_px']:>6.0e} | "
              f"{ch['mean_us']:>6.1f} /{ch['p99_us']:>6.1f} {fh['mean_us']:>5.1f} {r['c_over_floor_hot']:>4.2f}x | "
              f"{cr['mean_us']:>6.1f} /{cr['p99_us']:>6.1f} {fr['mean_us']:>5.1f} {r['c_over_floor_ring']:>4.2f}x | "
              f"{o['mean_us']:>7.1f} /{o['p99_us']:>7.1f} {r['speedup_vs_opencv']:>4.1f}x")
    # The longest frame: where the periodic background update shows (spread over the frames after it).
    print("longest frame (best of the rounds) us, C hot / C ring: " + "; ".join(
        f"{r['width']}x{r['height']} {r['targets']}: {r['c_hot']['max_us']:.0f} / {r['c_ring']['max_us']:.0f}"
        for r in fig["results"]))
    print_breakdown(fig["results"])
    worst_cv = min(r["speedup_vs_opencv"] for r in fig["results"])
    worst_hot = max(r["c_over_floor_hot"] for r in fig["results"])
    worst_ring = max(r["c_over_floor_ring"] for r in fig["results"])
    def met(ok: bool) -> str:
        return "met" if ok else "NOT met"

    hot_over = [r for r in fig["results"] if r["c_over_floor_hot"] > 2]
    print(f"goals: >= 3x the OpenCV pipeline at every size and target count (worst {worst_cv:.1f}x: "
          f"{met(worst_cv >= 3)}); within 2x of the read floor at the memory-bandwidth limit, frames "
          f"from memory as a camera's DMA leaves them (ring, worst {worst_ring:.2f}x: {met(worst_ring <= 2)})")
    # In cache the floor is the cache's bandwidth, not memory's (L2 at 640x480): a few microseconds,
    # against which each target's own work and the spread update weigh more. Printed, not hidden.
    print(f"in cache (hot: the floor is the cache's bandwidth, not memory's): worst {worst_hot:.2f}x"
          + ("; above 2x: " + ", ".join(f"{r['width']}x{r['height']} with {r['targets']} targets "
                                       f"{r['c_over_floor_hot']:.2f}x" for r in hot_over) if hot_over else
             "; within 2x everywhere"))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(fig, fh, indent=2)
        print(f"figures written to {args.json}")


if __name__ == "__main__":
    main()
