"""The edge's event algorithms through their bindings, on synthetic streams with known truth: two
blobs crossing a DVS sensor at known velocities, with uniform noise events and a hot pixel."""

from __future__ import annotations

import numpy as np
import pytest

from flytrack_host.dvs.events import EVENT_DTYPE
from flytrack_host.dvs.events.algos import ClusterTracker, NoiseFilter

W, H = 346, 260


def blobs(seconds: float = 0.3, rate: float = 400e3, noise_rate: float = 100e3, seed: int = 0):
    """Two 4 px blobs: A from (60, 60) at (+500, +300) px/s, B from (280, 70) at (-500, +300) px/s
    (they cross at x = 170), each `rate`/2 events/s; uniform noise at `noise_rate`; a hot pixel
    firing 20 k events/s. Returns events (time-ordered), a mask of blob events, and truth(t, k)."""
    rng = np.random.default_rng(seed)
    starts = np.array([[60.0, 60.0], [280.0, 70.0]])
    vel = np.array([[500.0, 300.0], [-500.0, 300.0]])
    n = int(seconds * rate)
    t = np.sort(rng.uniform(0, seconds * 1e6, n))
    k = rng.integers(0, 2, n)
    pos = starts[k] + vel[k] * (t[:, None] * 1e-6) + rng.normal(0, 2.0, (n, 2))
    nn = int(seconds * noise_rate)
    tn = rng.uniform(0, seconds * 1e6, nn)
    nh = int(seconds * 20e3)
    th = np.linspace(0, seconds * 1e6, nh)
    ev = np.zeros(n + nn + nh, EVENT_DTYPE)
    ev["t"] = np.r_[t, tn, th].astype(np.int64)
    px, py = np.round(pos[:, 0]), np.round(pos[:, 1])
    ev["x"] = np.r_[np.clip(px, 0, W - 1), rng.integers(0, W, nn), np.full(nh, 300)]
    ev["y"] = np.r_[np.clip(py, 0, H - 1), rng.integers(0, H, nn), np.full(nh, 200)]
    ev["p"] = rng.integers(0, 2, len(ev))
    blob = np.r_[np.ones(n, bool), np.zeros(nn + nh, bool)]
    on_sensor = np.r_[(px >= 0) & (px < W) & (py >= 0) & (py < H), np.ones(nn + nh, bool)]
    ev, blob = ev[on_sensor], blob[on_sensor]  # a blob that has left the sensor sends nothing
    order = np.argsort(ev["t"], kind="stable")

    def truth(tt: float) -> np.ndarray:
        return starts + vel * tt * 1e-6

    return ev[order], blob[order], truth


def _key(a: np.ndarray) -> np.ndarray:
    return a["t"] * 1_000_000 + a["y"].astype(np.int64) * 1000 + a["x"]


def test_background_activity_filter_keeps_the_animals_and_drops_the_noise():
    ev, blob, _ = blobs()
    nf = NoiseFilter(W, H, refractory_us=0, hot_pixel_count=0)
    kept = nf.apply(ev)
    survived = np.isin(_key(ev), _key(kept))  # the output is a compacted copy
    assert survived[blob].mean() > 0.97, survived[blob].mean()
    assert survived[~blob & (ev["x"] != 300)].mean() < 0.1  # uniform noise
    st = nf.stats
    assert st["in"] == len(ev) and st["out"] == len(kept) and st["ba_removed"] == len(ev) - len(kept)


def test_refractory_filter_equals_a_per_pixel_oracle():
    ev, _, _ = blobs(seconds=0.1)
    kept = NoiseFilter(W, H, ba_window_us=0, hot_pixel_count=0, refractory_us=100).apply(ev)
    last: dict[tuple[int, int], int] = {}
    want = []
    for e in ev:  # an event survives if its pixel's last survivor is at least 100 us older
        k = (int(e["x"]), int(e["y"]))
        if k not in last or int(e["t"]) - last[k] >= 100:
            last[k] = int(e["t"])
            want.append(e)
    want = np.array(want, dtype=ev.dtype)
    assert len(kept) < 0.95 * len(ev)  # the dense blobs do lose events to it
    assert np.array_equal(kept[["t", "x", "y"]], want[["t", "x", "y"]])


def test_hot_pixel_is_learned_and_removed():
    ev, _, _ = blobs(seconds=1.3)
    nf = NoiseFilter(W, H, hot_pixel_count=10_000, refractory_us=0)
    kept = nf.apply(ev)
    late = kept[kept["t"] > 1_000_000]
    assert nf.stats["hot_pixels"] == 1
    assert not np.any((late["x"] == 300) & (late["y"] == 200))
    assert np.any((kept["x"] == 300) & (kept["y"] == 200) & (kept["t"] < 1_000_000))


def test_clusters_with_kalman_follow_two_crossing_animals():
    ev, _, truth = blobs()
    nf = NoiseFilter(W, H)
    ct = ClusterTracker(W, H, radius_px=12.0)
    errs, verr = [], []
    ids_seen = set()
    for t_end in np.arange(20_000, 300_001, 10_000):
        chunk = ev[(ev["t"] >= t_end - 10_000) & (ev["t"] < t_end)]
        ct.feed(nf.apply(chunk))
        cl = ct.clusters(t_end)
        tr = truth(t_end)
        assert len(cl) == 2, (t_end, cl)
        for c in cl:
            d = np.hypot(tr[:, 0] - c["x"], tr[:, 1] - c["y"])
            j = int(np.argmin(d))
            errs.append(d[j])
            if c["tracking"]:
                verr.append(np.hypot(c["vx"] - [500, -500][j], c["vy"] - 300))
            ids_seen.add(int(c["id"]))
    # Position within a pixel or two, velocity within ~10 %, and the crossing (t ~ 0.11 s) does not
    # merge the two clusters: they move 1000 px/s apart in x.
    assert np.median(errs) < 1.5 and np.max(errs) < 6.0, (np.median(errs), np.max(errs))
    assert len(verr) > 40 and np.median(verr) < 60.0, np.median(verr)
    assert ct.stats["merged"] == 0
    assert len(ids_seen) == 2


def test_bad_parameters_and_bad_arrays_are_clear_errors():
    with pytest.raises(ValueError, match="unknown parameter"):
        NoiseFilter(W, H, ba_window=1)
    with pytest.raises(ValueError, match="bad noise-filter parameters"):
        NoiseFilter(W, H, stc_min_neighbours=9)
    with pytest.raises(ValueError, match="bad cluster-tracker"):
        ClusterTracker(W, H, max_clusters=0)
    with pytest.raises(TypeError, match="EVENT_DTYPE"):
        NoiseFilter(W, H).apply(np.zeros(3, dtype=[("t", "<i8")]))
