"""A tethered fly seen by an event camera, with known wing beats: the ground truth for the wing trackers.

The fly is backlit (seed 002, part II, Fig. 1): a wing darkens the pixels it covers. Each wing is a thin
sector of angular width `wing_width` between radii `r_in` and `r_out` about its hinge at the body centre,
whose stroke angle (from the heading, positive towards the fly's left) follows

    phi(t) = mean_stroke + amplitude(t) * sin(theta(t)),   theta' = 2 pi f(t)

A pixel emits an OFF event when the wing's leading edge covers it and an ON event when the trailing edge
uncovers it (one log-intensity step past the contrast threshold each time), at the moment the edge
crosses the pixel's angle, plus timing jitter. The frequency follows a manoeuvre (a smooth rise), the
amplitude can change, the body drifts slowly, and uniform noise events are added at a set share of all
events. Angles of both wings are measured from the heading (0) towards their own side, so a wing's
stroke angle is positive for both.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from flytrack_host.dvs.events.files import EVENT_DTYPE  # the event readers' layout: t (us), x, y, p (1 = ON)


@dataclass
class FlySimParams:
    width: int = 128  # DVS128 sensor
    height: int = 128
    duration_s: float = 2.0
    body_xy: tuple[float, float] = (64.0, 64.0)
    heading_rad: float = 0.6  # in the image: angle of the head direction from +x, counter-clockwise
    r_in: float = 7.0  # px: wing root (the body hides the inner part)
    r_out: float = 26.0  # px: wing tip
    wing_width_rad: float = 0.22
    mean_stroke_rad: float = 1.75  # a little behind the perpendicular, as a beating fly's wings sweep
    freq_hz: float = 200.0
    manoeuvre_start_s: float = 0.8  # the frequency rises smoothly by `manoeuvre_rise` over `manoeuvre_s`
    manoeuvre_s: float = 0.3
    manoeuvre_rise: float = 0.10
    amplitude_rad: tuple[float, float] = (1.0, 0.9)  # left, right at the start
    amplitude_change: float = 0.10  # both amplitudes grow by this share during the manoeuvre
    body_drift_px_s: tuple[float, float] = (0.6, -0.4)
    fire_probability: float = 0.2  # a pixel fires at an edge crossing with this chance (threshold
    # mismatch, refractory period): ~300 k events/s, the DVS128's USB figure
    noise_share: float = 0.20  # share of all events that are noise
    jitter_us: float = 15.0  # event timing jitter (std)
    dt_us: float = 8.0  # sampling step of the edge crossing search
    seed: int = 0


@dataclass
class FlyTruth:
    """What the trackers should recover, sampled every `dt_us`."""

    t_us: NDArray[np.int64]
    freq_hz: NDArray[np.float64]
    stroke: NDArray[np.float64]  # (2, n) stroke angle of the left, right wing (rad from the heading)
    amplitude: NDArray[np.float64]  # (2, n)
    body_xy: NDArray[np.float64]  # (n, 2)
    params: FlySimParams = field(default_factory=FlySimParams)

    def freq_at(self, t_us: NDArray | float) -> NDArray[np.float64]:
        return np.interp(t_us, self.t_us, self.freq_hz)

    def amplitude_at(self, wing: int, t_us: NDArray | float) -> NDArray[np.float64]:
        return np.interp(t_us, self.t_us, self.amplitude[wing])


def _ramp(t: NDArray[np.float64], start: float, length: float) -> NDArray[np.float64]:
    """0 before `start`, 1 after `start + length`, a smooth cosine step between."""
    u = np.clip((t - start) / length, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * u)


def fly_truth(p: FlySimParams | None = None) -> FlyTruth:
    """The ground truth alone (what `simulate_tethered_fly` returns beside its events, without them)."""
    p = p or FlySimParams()
    n = int(p.duration_s * 1e6 / p.dt_us) + 1
    t = np.arange(n) * p.dt_us * 1e-6
    ramp = _ramp(t, p.manoeuvre_start_s, p.manoeuvre_s)
    f = p.freq_hz * (1.0 + p.manoeuvre_rise * ramp)
    theta = 2.0 * np.pi * np.cumsum(f) * p.dt_us * 1e-6
    amp = np.array(p.amplitude_rad)[:, None] * (1.0 + p.amplitude_change * ramp)[None, :]
    stroke = p.mean_stroke_rad + amp * np.sin(theta)[None, :]
    body = np.array(p.body_xy)[None, :] + t[:, None] * np.array(p.body_drift_px_s)[None, :]
    return FlyTruth(t_us=np.round(t * 1e6).astype(np.int64), freq_hz=f, stroke=stroke, amplitude=amp,
                    body_xy=body, params=p)


def simulate_tethered_fly(p: FlySimParams | None = None) -> tuple[NDArray, FlyTruth]:
    """Events (EVENT_DTYPE, time-sorted) and the ground truth of one simulated recording."""
    p = p or FlySimParams()
    rng = np.random.default_rng(p.seed)
    truth = fly_truth(p)
    n = len(truth.t_us)
    t = np.arange(n) * p.dt_us * 1e-6  # as fly_truth computes it (not from the rounded t_us)
    stroke, body = truth.stroke, truth.body_xy

    # Pixels that a wing can cover: each gets its angle from the heading on its wing's side.
    ys, xs = np.mgrid[0:p.height, 0:p.width]
    px = xs.ravel().astype(np.float64)
    py = ys.ravel().astype(np.float64)
    chunks = []
    hx, hy = np.cos(p.heading_rad), np.sin(p.heading_rad)
    for wing, side in ((0, 1.0), (1, -1.0)):  # left wing: counter-clockwise of the heading in the image
        lo = stroke[wing] - p.wing_width_rad / 2
        hi = stroke[wing] + p.wing_width_rad / 2
        # The body drifts by under 2 px in a recording: pixel angles are taken about the mean body
        # position per block of time, which keeps the crossing search vectorised.
        block = max(1, int(0.05e6 / p.dt_us))
        for b0 in range(0, n - 1, block):
            b1 = min(n, b0 + block + 1)
            bx, by = body[(b0 + b1) // 2]
            dx, dy = px - bx, py - by
            r = np.hypot(dx, dy)
            fwd = dx * hx + dy * hy
            lat = side * (-dx * hy + dy * hx)  # towards this wing's side
            ang = np.arctan2(lat, fwd)  # 0 at the heading, +pi/2 straight out to this side
            sel = (r >= p.r_in) & (r <= p.r_out) & (ang > 0.0)
            ang_s = ang[sel]
            idx = np.flatnonzero(sel)
            covered = (ang_s[None, :] >= lo[b0:b1, None]) & (ang_s[None, :] <= hi[b0:b1, None])
            change = np.diff(covered.astype(np.int8), axis=0)
            ti, pj = np.nonzero(change)
            fire = rng.random(len(ti)) < p.fire_probability
            ti, pj = ti[fire], pj[fire]
            if len(ti) == 0:
                continue
            pol = (change[ti, pj] < 0).astype(np.uint8)  # uncovered -> brighter -> ON
            # Sub-step time: where the edge angle passed the pixel angle, interpolated.
            k = b0 + ti
            edge_now = np.where(ang_s[pj] >= stroke[wing, k], hi[k], lo[k])
            edge_next = np.where(ang_s[pj] >= stroke[wing, k], hi[k + 1], lo[k + 1])
            with np.errstate(divide="ignore", invalid="ignore"):
                frac = np.clip((ang_s[pj] - edge_now) / (edge_next - edge_now), 0.0, 1.0)
            frac = np.nan_to_num(frac, nan=0.5)
            te = (t[k] + frac * p.dt_us * 1e-6) * 1e6 + rng.normal(0.0, p.jitter_us, len(k))
            ev = np.zeros(len(k), dtype=EVENT_DTYPE)
            ev["t"] = np.round(te).astype(np.int64)
            ev["x"] = px[idx[pj]].astype(np.uint16)
            ev["y"] = py[idx[pj]].astype(np.uint16)
            ev["p"] = pol
            chunks.append(ev)
    wing_events = np.concatenate(chunks)
    n_noise = int(round(len(wing_events) * p.noise_share / (1.0 - p.noise_share)))
    noise = np.zeros(n_noise, dtype=EVENT_DTYPE)
    noise["t"] = rng.integers(0, int(p.duration_s * 1e6), n_noise)
    noise["x"] = rng.integers(0, p.width, n_noise)
    noise["y"] = rng.integers(0, p.height, n_noise)
    noise["p"] = rng.integers(0, 2, n_noise)
    events = np.concatenate([wing_events, noise]).astype(EVENT_DTYPE)  # concatenate drops the padding
    events = events[(events["t"] >= 0) & (events["t"] < int(p.duration_s * 1e6))]
    events = events[np.argsort(events["t"], kind="stable")]
    return events, truth
