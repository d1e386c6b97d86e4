"""`make bench-edge`: the C feature extractor against an OpenCV-Python pipeline, same frames, one run.

For 640x480 and 2048x2048 8-bit frames with 0, 1 and 10 moving targets on a noisy textured background,
prints median and 99th-percentile microseconds per frame and frames per second on one core, for the
C library (called through ctypes, so the figures include the call overhead) and for OpenCV doing the
same steps (cv2.absdiff, per-pixel threshold with cv2.compare, cv2.connectedComponentsWithStats,
cv2.moments per region, background update with cv2.accumulateWeighted every 200 frames).
BENCH_JSON=PATH (or --json PATH) writes the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import cv2
import numpy as np

from flytrack_host.features import ExtractorParams, FeatureExtractor

CASES = [(640, 480, 0), (640, 480, 1), (640, 480, 10), (2048, 2048, 0), (2048, 2048, 1), (2048, 2048, 10)]


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
    """What a user would otherwise write with OpenCV: the same steps, single-threaded."""

    def __init__(self, bg: np.ndarray, p: ExtractorParams) -> None:
        self.p = p
        self.mean = bg.astype(np.float32)
        self.sq = self.mean * self.mean
        self.n = 0
        self._refresh()

    def _refresh(self) -> None:
        std = np.sqrt(np.maximum(self.sq - self.mean * self.mean, 0))
        thr = np.maximum(self.p.n_sigma * std, self.p.diff_threshold)
        self.thr8 = np.clip(np.floor(thr), 0, 255).astype(np.uint8)
        self.bg8 = np.clip(np.rint(self.mean), 0, 255).astype(np.uint8)

    def process(self, frame: np.ndarray) -> list[tuple[float, float]]:
        diff = cv2.absdiff(frame, self.bg8)
        mask = cv2.compare(diff, self.thr8, cv2.CMP_GT)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        out = []
        for k in range(1, n):
            x, y, w, h, _area = stats[k]
            roi = diff[y:y + h, x:x + w].astype(np.float32)
            inside = labels[y:y + h, x:x + w] == k
            beta = float(roi[inside].max())
            cut = max(self.p.clear_fraction * beta, self.p.diff_threshold)
            wts = np.where(inside & (roi >= cut), roi - cut, 0).astype(np.float32)
            m = cv2.moments(wts)
            if m["m00"] > 0:
                out.append((x + m["m10"] / m["m00"], y + m["m01"] / m["m00"]))
        self.n += 1
        if self.n % self.p.bg_update_interval == 0:
            f = frame.astype(np.float32)
            cv2.accumulateWeighted(f, self.mean, self.p.alpha)
            cv2.accumulateWeighted(f * f, self.sq, self.p.alpha)
            self._refresh()
        return out


def _stats(ns: list[int]) -> dict[str, float]:
    us = np.asarray(ns, dtype=np.float64) / 1000.0
    med = float(np.median(us))
    return {"median_us": med, "p99_us": float(np.percentile(us, 99)), "fps": 1e6 / med, "frames": len(us)}


def run(quick: bool = False) -> dict:
    cv2.setNumThreads(1)
    results = []
    for w, h, nt in CASES:
        big = w * h > 1_000_000
        n_c = (150 if big else 1500) if quick else (400 if big else 4000)
        n_cv = (20 if big else 150) if quick else (60 if big else 600)
        bg, frames = make_frames(w, h, nt, 16 if big else 32)
        params = ExtractorParams()
        fx = FeatureExtractor(w, h, params=params)
        fx.process(bg)
        npts = []
        for f in frames:  # warm-up, and check the targets are found
            npts.append(fx.process(f).total_points)
        c_ns = []
        for i in range(n_c):
            f = frames[i % len(frames)]
            t0 = time.perf_counter_ns()
            fx.process_raw(f)
            c_ns.append(time.perf_counter_ns() - t0)
        cvp = OpenCVPipeline(bg, params)
        cv_pts = [len(cvp.process(f)) for f in frames]
        cv_ns = []
        for i in range(n_cv):
            f = frames[i % len(frames)]
            t0 = time.perf_counter_ns()
            cvp.process(f)
            cv_ns.append(time.perf_counter_ns() - t0)
        c, o = _stats(c_ns), _stats(cv_ns)
        results.append({
            "width": w, "height": h, "targets": nt,
            "points_found_median": float(np.median(npts)), "opencv_points_median": float(np.median(cv_pts)),
            "c": c, "opencv": o, "speedup_median": o["median_us"] / c["median_us"],
        })
    return {
        "benchmark": "edge feature extraction, one core",
        "cpu": platform.processor() or platform.machine(),
        "opencv": cv2.__version__,
        "results": results,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=os.environ.get("BENCH_JSON") or None, help="write figures here")
    ap.add_argument("--quick", action="store_true", help="fewer frames")
    args = ap.parse_args()
    fig = run(args.quick)
    print(f"{'frame':>10} {'tgt':>3} {'pts':>4} | {'C med us':>9} {'C p99 us':>9} {'C fps':>8} | "
          f"{'cv med us':>9} {'cv p99 us':>9} {'cv fps':>7} | {'C/cv':>6}")
    for r in fig["results"]:
        c, o = r["c"], r["opencv"]
        print(f"{r['width']:>5}x{r['height']:<4} {r['targets']:>3} {r['points_found_median']:>4.0f} | "
              f"{c['median_us']:>9.1f} {c['p99_us']:>9.1f} {c['fps']:>8.0f} | "
              f"{o['median_us']:>9.1f} {o['p99_us']:>9.1f} {o['fps']:>7.0f} | {r['speedup_median']:>5.1f}x")
    goal = next(r for r in fig["results"] if r["width"] == 640 and r["targets"] == 10)
    print(f"goal 640x480: >= 2000 fps on one core (10 targets: {goal['c']['fps']:.0f} fps), "
          f">= 5x OpenCV (10 targets: {goal['speedup_median']:.1f}x)")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(fig, fh, indent=2)
        print(f"figures written to {args.json}")


if __name__ == "__main__":
    main()
