"""The C feature extractor against a NumPy reference written here from the algorithm's description.

Same frames in; the same points must come out (same regions, peaks, areas; centres within 1e-3 px).
The reference uses float32 for the background model in the same operation order as the C library
(which is built without fused multiply-add), so per-pixel thresholds agree exactly.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from flytrack_host.edges.features import ExtractorParams, FeatureError, FeatureExtractor
from flytrack_host.geometry.camera import Camera

F32 = np.float32


class NumpyReference:
    """Straightforward, slow implementation of the extractor (seed 000 §2 with Braid's defaults)."""

    def __init__(self, width: int, height: int, p: ExtractorParams, maxval: int = 255,
                 mask: np.ndarray | None = None) -> None:
        self.w, self.h, self.p, self.maxval = width, height, p, maxval
        self.mean: np.ndarray | None = None
        self.sumsq: np.ndarray | None = None
        self.mask = np.ones((height, width), bool) if mask is None else mask.astype(bool)
        self.since = 0

    def _thresholds(self) -> None:
        p = self.p
        m = self.mean
        var = self.sumsq - m * m
        var = np.maximum(var, F32(0))
        t = F32(p.n_sigma) * np.sqrt(var)
        t = np.maximum(t, F32(p.diff_threshold))
        up = np.minimum(m + t, F32(self.maxval))
        dn = np.maximum(m - t, F32(0))
        hi = np.floor(up).astype(np.int64)
        lo = np.ceil(dn).astype(np.int64)
        bright = p.polarity != "dark"
        dark = p.polarity != "bright"
        self.hi = np.where(self.mask & bright, hi, self.maxval)
        self.lo = np.where(self.mask & dark, lo, 0)

    def process(self, frame: np.ndarray) -> list[dict]:
        p = self.p
        x = frame.astype(F32)
        if self.mean is None:
            self.mean, self.sumsq = x.copy(), x * x
            self._thresholds()
            return []
        fi = frame.astype(np.int64)
        cand = (fi > self.hi) | (fi < self.lo)
        d = x - self.mean
        if p.polarity == "both":
            d = np.abs(d)
        elif p.polarity == "dark":
            d = -d
        labels, n = ndimage.label(cand, structure=np.ones((3, 3)))
        points = []
        flat_d = d.ravel()
        flat_l = labels.ravel()
        order = np.argsort(flat_l, kind="stable")  # raster order within each label
        starts = np.searchsorted(flat_l[order], np.arange(1, n + 2))
        for k in range(n):
            idx = order[starts[k]:starts[k + 1]]
            dv = flat_d[idx].astype(np.float64)
            j = int(np.argmax(dv))  # first maximum in raster order
            beta = dv[j]
            peak = int(idx[j])
            py, px = divmod(peak, self.w)
            cut = max(p.clear_fraction * beta, p.despeckle_threshold, p.diff_threshold)
            keep = dv >= cut
            if keep.sum() < p.min_area:
                continue
            ys, xs = np.divmod(idx[keep], self.w)
            wt = dv[keep] - cut if p.subtract_cut else dv[keep]
            m0 = wt.sum()
            if m0 > 0:
                dx, dy = xs - px, ys - py
                mx, my = (wt * dx).sum() / m0, (wt * dy).sum() / m0
                u20 = (wt * dx * dx).sum() / m0 - mx * mx
                u02 = (wt * dy * dy).sum() / m0 - my * my
                u11 = (wt * dx * dy).sum() / m0 - mx * my
                ht, hd = 0.5 * (u20 + u02), 0.5 * (u20 - u02)
                disc = math.sqrt(hd * hd + u11 * u11)
                l1, l2 = ht + disc, ht - disc
                if l1 <= 1e-12 or disc <= 1e-9 * ht:
                    ori, ecc = math.nan, 1.0
                else:
                    ori = 0.5 * math.atan2(2 * u11, u20 - u02)
                    if ori <= -math.pi / 2:
                        ori += math.pi
                    ecc = math.sqrt(l1 / l2) if l2 > 1e-12 * l1 else math.nan
            else:
                mx = my = 0.0
                ori, ecc = math.nan, 1.0
            points.append(dict(x=px + mx, y=py + my, area=int(keep.sum()), beta=beta, peak=peak,
                               ori=ori, ecc=ecc, cur=int(frame.ravel()[peak]),
                               mean=float(self.mean.ravel()[peak]), sumsq=float(self.sumsq.ravel()[peak])))
        points.sort(key=lambda q: (-q["beta"], q["peak"]))
        points = points[: p.max_points]
        if p.bg_update_interval:
            self.since += 1
            if self.since >= p.bg_update_interval:
                self.since = 0
                a, a1 = F32(p.alpha), F32(1.0 - p.alpha)
                self.mean = a1 * self.mean + a * x
                self.sumsq = a1 * self.sumsq + a * (x * x)
                self._thresholds()
        return points


def render(rng: np.random.Generator, bg: np.ndarray, blobs: list[tuple[float, float, float, float]],
           noise: np.ndarray | float, maxval: int = 255) -> np.ndarray:
    """Background + Gaussian blobs (x, y, sigma, amplitude; negative = dark) + Gaussian noise."""
    h, w = bg.shape
    yy, xx = np.mgrid[0:h, 0:w]
    img = bg.astype(np.float64).copy()
    for cx, cy, s, a in blobs:
        img += a * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s))
    img += rng.normal(0.0, 1.0, img.shape) * noise
    dtype = np.uint16 if maxval > 255 else np.uint8
    return np.clip(np.rint(img), 0, maxval).astype(dtype)


def compare(c_points: np.ndarray, ref: list[dict], w: int) -> None:
    assert len(c_points) == len(ref), (len(c_points), len(ref))
    for cp, rp in zip(c_points, ref, strict=True):
        assert int(cp["peak_y"]) * w + int(cp["peak_x"]) == rp["peak"]
        assert abs(cp["x_dist"] - rp["x"]) < 1e-3 and abs(cp["y_dist"] - rp["y"]) < 1e-3
        assert cp["area"] == rp["area"]
        assert cp["peak_diff"] == pytest.approx(rp["beta"], abs=1e-4)
        assert cp["cur_val"] == rp["cur"]
        assert cp["mean_val"] == rp["mean"] and cp["sumsq_val"] == rp["sumsq"]
        for key, rk in (("orientation", "ori"), ("eccentricity", "ecc")):
            if math.isnan(rp[rk]):
                assert math.isnan(cp[key])
            else:
                assert cp[key] == pytest.approx(rp[rk], abs=1e-6, rel=1e-6)


def random_blobs(rng: np.random.Generator, w: int, h: int, n: int, signed: bool) -> list:
    out = []
    for _ in range(n):
        a = rng.uniform(50, 200) * (rng.choice([-1, 1]) if signed else 1)
        out.append((rng.uniform(5, w - 6), rng.uniform(5, h - 6), rng.uniform(0.7, 3.0), a))
    return out


@pytest.mark.parametrize("polarity", ["both", "bright", "dark"])
def test_c_matches_numpy_reference_over_a_sequence(polarity: str) -> None:
    rng = np.random.default_rng(42)
    w, h = 160, 120
    # Textured background, a noisy band (so n_sigma x std, not diff_threshold, decides there),
    # background updates every 3 frames so the variance model moves.
    bg = rng.uniform(40, 120, (h, w))
    noise = np.full((h, w), 1.5)
    noise[:, 100:130] = 9.0
    params = ExtractorParams(bg_update_interval=3, alpha=0.08, polarity=polarity, max_points=12)
    fx = FeatureExtractor(w, h, params=params)
    ref = NumpyReference(w, h, params)
    n_points_seen = 0
    for i in range(40):
        blobs = [] if i < 8 else random_blobs(rng, w, h, int(rng.integers(0, 16)), signed=True)
        frame = render(rng, bg, blobs, noise)
        got = fx.process(frame)
        want = ref.process(frame)
        compare(got.points, want, w)
        n_points_seen += len(want)
    assert n_points_seen > 100  # the comparison was not vacuous


def test_c_matches_reference_mono16_mask_and_plain_weights() -> None:
    rng = np.random.default_rng(7)
    w, h = 128, 96
    bg = rng.uniform(1000, 3000, (h, w))
    mask = np.ones((h, w), np.uint8)
    mask[:, :30] = 0
    params = ExtractorParams(diff_threshold=400, bg_update_interval=2, alpha=0.1, subtract_cut=False,
                             despeckle_threshold=50, min_area=2)
    fx = FeatureExtractor(w, h, "mono16", params=params, mask=mask)
    ref = NumpyReference(w, h, params, maxval=65535, mask=mask)
    seen = 0
    for i in range(20):
        blobs = [] if i < 4 else [(x, y, s, a * 20) for x, y, s, a in random_blobs(rng, w, h, 8, True)]
        frame = render(rng, bg, blobs, 30.0, maxval=65535)
        got = fx.process(frame)
        want = ref.process(frame)
        compare(got.points, want, w)
        assert all(p["peak_x"] >= 30 for p in got.points)
        seen += len(want)
    assert seen > 40


@pytest.mark.parametrize("dtype_max", [255, 65535])
def test_noiseless_centre_error_below_0_05_px(dtype_max: int) -> None:
    rng = np.random.default_rng(3)
    w, h = 200, 150
    bg = np.full((h, w), 30.0 if dtype_max == 255 else 3000.0)
    scale = 1.0 if dtype_max == 255 else 200.0
    params = ExtractorParams(diff_threshold=30 * scale)
    fx = FeatureExtractor(w, h, "mono8" if dtype_max == 255 else "mono16", params=params)
    fx.process(render(rng, bg, [], 0.0, dtype_max))
    worst = 0.0
    for _ in range(30):
        # Fly-sized blobs on a grid (no overlaps), sub-pixel positions, sigma 1.5..3 px.
        blobs = []
        for gx in range(4):
            for gy in range(3):
                blobs.append((25 + 45 * gx + rng.uniform(-0.5, 0.5), 25 + 45 * gy + rng.uniform(-0.5, 0.5),
                              rng.uniform(1.5, 3.0), rng.uniform(100, 220) * scale))
        got = fx.process(render(rng, bg, blobs, 0.0, dtype_max))
        assert len(got.points) == len(blobs)
        for x, y, _, _ in blobs:
            e = np.hypot(got.points["x_dist"] - x, got.points["y_dist"] - y).min()
            worst = max(worst, float(e))
    print(f"worst noiseless centre error ({dtype_max}): {worst:.4f} px")
    assert worst < 0.05


def test_undistortion_matches_camera_model() -> None:
    cam = Camera.look_at("c", (0, -2, 0.5), (0, 0, 0.3), 640, 480, 600.0,
                         dist=(-0.25, 0.08, 0.0012, -0.0009, -0.01))
    cam.K[0, 1] = 0.3  # a little skew too
    fx = FeatureExtractor(640, 480, camera=cam)
    rng = np.random.default_rng(0)
    uv = np.column_stack([rng.uniform(0, 639, 200), rng.uniform(0, 479, 200)])
    want = cam.undistort(uv)
    got = np.array([fx.undistort(u, v) for u, v in uv])
    assert np.abs(got - want).max() < 1e-6
    # and through the extractor: a blob's undistorted centre is the undistorted distorted centre
    bg = np.full((480, 640), 20, np.uint8)
    fx.process(bg)
    frame = render(rng, bg, [(100.3, 70.6, 1.8, 180)], 0.0)
    pt = fx.process(frame).points[0]
    u, v = cam.undistort([[pt["x_dist"], pt["y_dist"]]])[0]
    assert abs(pt["x_undist"] - u) < 1e-6 and abs(pt["y_undist"] - v) < 1e-6
    assert abs(pt["x_undist"] - pt["x_dist"]) > 1.0  # distortion is large there


def test_bad_input_is_a_clear_error() -> None:
    fx = FeatureExtractor(64, 48)
    with pytest.raises(FeatureError, match="3071 bytes"):
        fx.process(np.zeros(64 * 48 - 1, np.uint8))
    with pytest.raises(FeatureError, match="uint8"):
        fx.process(np.zeros((48, 64), np.float32))
    with pytest.raises(FeatureError, match="unknown pixel format"):
        FeatureExtractor(64, 48, "rgb24")
    with pytest.raises(FeatureError, match="alpha"):
        FeatureExtractor(64, 48, params=ExtractorParams(alpha=2.0))
    with pytest.raises(FeatureError, match="unknown parameter"):
        fx.set_param("no_such_param", 1.0)
    with pytest.raises(FeatureError, match="out of range"):
        fx.set_param("clear_fraction", 1.5)
    with pytest.raises(FeatureError, match="mask shape"):
        fx.set_mask(np.ones((10, 10), np.uint8))
    fx.set_param("diff_threshold", 12.5)
    assert fx.get_param("diff_threshold") == 12.5
    # max_points: at most 255 FEATURES parts x 32 points, at create and at run time alike.
    with pytest.raises(FeatureError, match="max_points must be in 1..8160"):
        FeatureExtractor(64, 48, params=ExtractorParams(max_points=8161))
    for bad in (8161, 100000, 2**32 - 1):
        with pytest.raises(FeatureError, match="out of range"):
            fx.set_param("max_points", bad)
    assert fx.get_param("max_points") == 100
    fx.set_param("max_points", 8160)
    assert fx.get_param("max_points") == 8160


def test_missing_library_tells_how_to_build(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    from flytrack_host.edges.features import FeatureLibraryError, _lib

    monkeypatch.setenv("FLYTRACK_BUILD_DIR", str(tmp_path))
    monkeypatch.setattr(_lib, "_lib", None)
    with pytest.raises(FeatureLibraryError, match="make build"):
        _lib.load()
