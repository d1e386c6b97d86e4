"""`make bench-edge`: the C feature extractor against a fair OpenCV pipeline, same frames, one run.

For 640x480 and 2048x2048 8-bit frames with 0, 1 and 10 moving targets on a noisy textured background,
on one core (cv2.setNumThreads(1)), three things are timed on the same frames:

- the C library (called through ctypes, so the figures include the call overhead);
- OpenCV written the way a user who knows it would write the same detector: one cv2.inRange of the
  frame against the per-pixel low/high thresholds, an early exit when cv2.countNonZero says every
  pixel is background, else cv2.findContours (outer contours) to locate the regions, and connected
  components and moments only inside each region's bounding box; the background
  (cv2.accumulateWeighted of the frame and its square) and the thresholds (cv2 arithmetic) are
  refreshed every bg_update_interval frames, as in C;
- the floor: one read pass over the frame (np.bitwise_or.reduce over its 64-bit words, vectorised),
  the least any detector that looks at every pixel must spend.

Every figure is the mean over a whole number of background-update intervals (so the periodic update is
paid in it), with the P99. The bench checks that both pipelines find the same centroids (to 1e-3 px)
before it times them. BENCH_JSON=PATH (or --json PATH) writes the figures.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import platform
import time

import cv2
import numpy as np

from flytrack_host.features import ExtractorParams, FeatureExtractor

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


def _stats(ns: list[int]) -> dict[str, float]:
    us = np.asarray(ns, dtype=np.float64) / 1000.0
    mean = float(np.mean(us))
    return {"mean_us": mean, "median_us": float(np.median(us)), "p99_us": float(np.percentile(us, 99)),
            "fps": 1e6 / mean, "frames": len(us)}


def _c_call(fx: FeatureExtractor):  # noqa: ANN202
    """fx.process_raw without its Python argument checks: the C call through ctypes alone, so that the
    C figure, like the floor's, carries only a foreign-call overhead (about 1 us)."""
    proc, h, nbytes, res = fx._lib.ft_fx_process, fx._h, fx.frame_bytes, ctypes.byref(fx._res)

    def call(ptr: int) -> int:  # the frame's address, taken before timing
        return proc(h, ptr, nbytes, res)

    return call


def _time(fn, frames: list, n: int) -> list[int]:  # noqa: ANN001
    ns = []
    for i in range(n):
        f = frames[i % len(frames)]
        t0 = time.perf_counter_ns()
        fn(f)
        ns.append(time.perf_counter_ns() - t0)
    return ns


def run(quick: bool = False) -> dict:
    cv2.setNumThreads(1)
    params = ExtractorParams()
    iv = params.bg_update_interval
    results = []
    for w, h, nt in CASES:
        big = w * h > 1_000_000
        n = iv * ((1 if quick else 2) if big else (2 if quick else 10))  # whole update intervals
        bg, frames = make_frames(w, h, nt, 16 if big else 32)
        fx = FeatureExtractor(w, h, params=params)
        fx.process(bg)
        cvp = OpenCVPipeline(bg, params)
        worst = check_same_centroids(fx, cvp, frames)
        npts = float(np.median([fx.process(f).total_points for f in frames]))
        # Both start their timed run at the same point of the update cycle (just after an update).
        fx.close()
        fx = FeatureExtractor(w, h, params=params)
        fx.process(bg)
        cvp = OpenCVPipeline(bg, params)
        # Interleaved one update interval at a time, so that load from elsewhere on a shared machine
        # falls on all three alike; each keeps its own place in the frame sequence.
        c_ns, cv_ns, fl_ns = [], [], []
        ptrs = [f.ctypes.data for f in frames]
        call = _c_call(fx)
        words = [f.reshape(-1).view(np.uint64) for f in frames]
        for k in range(n // iv):
            chunk = range(k * iv, (k + 1) * iv)
            c_ns += _time(call, [ptrs[i % len(ptrs)] for i in chunk], iv)
            cv_ns += _time(cvp.process, [frames[i % len(frames)] for i in chunk], iv)
            fl_ns += _time(np.bitwise_or.reduce, [words[i % len(words)] for i in chunk], iv)
        c, o, fl = _stats(c_ns), _stats(cv_ns), _stats(fl_ns)
        fx.close()
        results.append({
            "width": w, "height": h, "targets": nt, "points_found_median": npts,
            "centroid_max_diff_px": worst, "c": c, "opencv": o, "read_floor": fl,
            "speedup_vs_opencv": o["mean_us"] / c["mean_us"], "c_over_floor": c["mean_us"] / fl["mean_us"],
        })
    return {
        "benchmark": "edge feature extraction, one core, mean per frame including background updates",
        "cpu": platform.processor() or platform.machine(),
        "opencv": cv2.__version__,
        "bg_update_interval": iv,
        "results": results,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=os.environ.get("BENCH_JSON") or None, help="write figures here")
    ap.add_argument("--quick", action="store_true", help="fewer frames")
    args = ap.parse_args()
    fig = run(args.quick)
    print("mean and P99 us per frame over whole background-update intervals; one core; "
          "same centroids checked (max diff shown)")
    print(f"{'frame':>10} {'tgt':>3} {'pts':>4} {'dpx':>7} | {'C mean':>7} {'C p99':>7} {'C fps':>7} | "
          f"{'cv mean':>8} {'cv p99':>8} | {'floor':>6} | {'C/cv':>6} {'C/floor':>7}")
    for r in fig["results"]:
        c, o, fl = r["c"], r["opencv"], r["read_floor"]
        print(f"{r['width']:>5}x{r['height']:<4} {r['targets']:>3} {r['points_found_median']:>4.0f} "
              f"{r['centroid_max_diff_px']:>7.0e} | {c['mean_us']:>7.1f} {c['p99_us']:>7.1f} {c['fps']:>7.0f} | "
              f"{o['mean_us']:>8.1f} {o['p99_us']:>8.1f} | {fl['mean_us']:>6.1f} | "
              f"{r['speedup_vs_opencv']:>5.1f}x {r['c_over_floor']:>6.2f}x")
    worst_cv = min(r["speedup_vs_opencv"] for r in fig["results"])
    worst_fl = max(r["c_over_floor"] for r in fig["results"])
    print(f"goals: >= 3x the OpenCV pipeline at every size and target count (worst {worst_cv:.1f}x: "
          f"{'met' if worst_cv >= 3 else 'NOT met'}); within 2x of the read floor (worst {worst_fl:.2f}x: "
          f"{'met' if worst_fl <= 2 else 'NOT met'})")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(fig, fh, indent=2)
        print(f"figures written to {args.json}")


if __name__ == "__main__":
    main()
