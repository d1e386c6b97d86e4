"""Where the tethered fly is: the initialisation phase of seed 002 (part II, section 2), and events
turned into wing angles (eq. 8).

From a buffer of the first events: 2-means on the event positions (prototypes started at two opposite
sensor corners) finds the two wings' centres of mass; the body is between them, the heading is
orthogonal to the line joining them, and of the two orthogonal directions the tail is the side where
more wing events fall (a beating fly's wings sweep further back than forward). The fly's size is twice
the body-to-centroid distance; events outside that radius (the tether, noise) are ignored afterwards.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


class WingbeatError(ValueError):
    """Events from which no fly can be found (too few, no two wings)."""


@dataclass(frozen=True)
class FlyGeometry:
    body: tuple[float, float]  # px
    heading_rad: float  # direction of the head in sensor coordinates, from +x towards +y
    size_px: float  # twice the body-to-wing-centroid distance
    mean_stroke: tuple[float, float]  # wing 0, wing 1: mean angle of their events from the heading (rad)
    spread: tuple[float, float]  # half the 5-95 % range of each wing's event angles (rad): amplitude guess
    inner_px: float  # events closer to the body than this are ignored (the body itself)

    def angles(self, x: NDArray, y: NDArray) -> tuple[NDArray[np.float64], NDArray[np.int8]]:
        """Eq. 8: each event's angle from the heading about the body, folded to its wing's side.

        Returns (angle in [0, pi], wing) where wing 0 lies on the +90 degree side of the heading in sensor
        coordinates (the fly's left or right depending on whether the camera looks from above or below),
        wing 1 on the other, and -1 for events outside the region of interest."""
        dx = np.asarray(x, dtype=np.float64) - self.body[0]
        dy = np.asarray(y, dtype=np.float64) - self.body[1]
        hx, hy = np.cos(self.heading_rad), np.sin(self.heading_rad)
        ang = np.arctan2(-dx * hy + dy * hx, dx * hx + dy * hy)
        r = np.hypot(dx, dy)
        wing = np.where(ang >= 0.0, 0, 1).astype(np.int8)
        wing[(r > self.size_px) | (r < self.inner_px)] = -1
        return np.abs(ang), wing


def two_means(xy: NDArray[np.float64], width: int, height: int, iterations: int = 50) -> tuple[NDArray, NDArray]:
    """2-means with prototypes started at the upper-right and lower-left sensor corners (seed 002)."""
    proto = np.array([[width - 1.0, 0.0], [0.0, height - 1.0]])
    label = np.zeros(len(xy), dtype=np.int64)
    for it in range(iterations):
        d = ((xy[:, None, :] - proto[None, :, :]) ** 2).sum(axis=2)
        new = np.argmin(d, axis=1)
        if it and np.array_equal(new, label):
            break
        label = new
        for k in (0, 1):
            if np.any(label == k):
                proto[k] = xy[label == k].mean(axis=0)
    return proto, label


def initialise(x: NDArray, y: NDArray, width: int = 128, height: int = 128) -> FlyGeometry:
    """The fly's body, heading, size and region of interest from a buffer of events."""
    x = np.asarray(x, dtype=np.int64)
    y = np.asarray(y, dtype=np.int64)
    if len(x) < 200:
        raise WingbeatError(f"{len(x)} events are too few to find the fly (need at least 200)")
    # Noise events fall on pixels that fire once or twice in the buffer; a beating wing's pixels fire at
    # every stroke (tens of times in 0.1 s).
    counts = np.bincount(y * width + x, minlength=width * height)
    keep = counts[y * width + x] >= 4
    if keep.sum() < 100 or keep.mean() < 0.2:
        raise WingbeatError("no pixel fires repeatedly in the first events: no beating wing in view")
    xy = np.stack([x[keep], y[keep]], axis=1).astype(np.float64)
    proto, label = two_means(xy, width, height)
    n0, n1 = np.bincount(label, minlength=2)
    if min(n0, n1) < 0.1 * len(label):
        raise WingbeatError(f"the events form one cluster ({n0} / {n1}): two beating wings are not in view")
    body = proto.mean(axis=0)
    half = np.linalg.norm(proto[0] - body)
    if half < 2.0:
        raise WingbeatError("the two wing clusters coincide: two beating wings are not in view")
    axis = (proto[0] - proto[1]) / (2.0 * half)
    perp = np.array([-axis[1], axis[0]])
    # The tail is where more wing events fall: the heading points the other way.
    side = (xy - body) @ perp
    near = np.linalg.norm(xy - body, axis=1) <= 2.0 * half
    heading_vec = -perp if np.sum(side[near] > 0) > np.sum(side[near] < 0) else perp
    heading = float(np.arctan2(heading_vec[1], heading_vec[0]))
    geo = FlyGeometry(body=(float(body[0]), float(body[1])), heading_rad=heading, size_px=float(2.0 * half),
                      mean_stroke=(0.0, 0.0), spread=(0.0, 0.0), inner_px=float(0.15 * half))
    ang, wing = geo.angles(xy[:, 0], xy[:, 1])
    means, spreads = [], []
    for w in (0, 1):
        a = ang[wing == w]
        if len(a) < 20:
            raise WingbeatError(f"too few events on wing {w} after initialisation ({len(a)})")
        lo, hi = np.percentile(a, [5, 95])
        means.append(float(np.mean(a)))
        spreads.append(float((hi - lo) / 2.0))
    return FlyGeometry(geo.body, heading, geo.size_px, (means[0], means[1]), (spreads[0], spreads[1]),
                       geo.inner_px)


def estimate_frequency(t_us: NDArray, angle: NDArray, lo_hz: float = 50.0, hi_hz: float = 1000.0) -> float:
    """The wing-beat frequency in a buffer of one wing's events, from the autocorrelation of the mean
    event angle in 0.1 ms bins; starts the EKF near the truth (seed 002 needs it within 5 %)."""
    t = np.asarray(t_us, dtype=np.float64)
    if len(t) < 50 or t[-1] - t[0] < 3e6 / lo_hz:
        raise WingbeatError("too short a buffer to estimate the wing-beat frequency (need 3 slowest beats)")
    bin_us = 100.0
    idx = ((t - t[0]) / bin_us).astype(np.int64)
    n = idx[-1] + 1
    s = np.bincount(idx, weights=angle, minlength=n)
    c = np.bincount(idx, minlength=n)
    with np.errstate(invalid="ignore"):
        m = s / c
    m = np.where(c > 0, m - np.nanmean(m), 0.0)
    ac = np.correlate(m, m, mode="full")[n - 1:]
    lags = np.arange(len(ac)) * bin_us * 1e-6
    ok = (lags >= 1.0 / hi_hz) & (lags <= 1.0 / lo_hz)
    if not ok.any():
        raise WingbeatError("buffer too short for the frequency search")
    # The first lag whose correlation is near the best: the period, not a multiple of it.
    cand = np.flatnonzero(ok)
    vals = ac[cand]
    good = vals >= 0.85 * vals.max()
    k = cand[np.argmax(good)]
    while k + 1 < len(ac) and ac[k + 1] > ac[k]:
        k += 1
    # Parabolic refinement of the peak for sub-bin precision.
    if 0 < k < len(ac) - 1:
        y0, y1, y2 = ac[k - 1], ac[k], ac[k + 1]
        den = y0 - 2 * y1 + y2
        k = k + (0.5 * (y0 - y2) / den if den != 0 else 0.0)
    return float(1.0 / (k * bin_us * 1e-6))
