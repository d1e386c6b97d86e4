"""Wing beats of a tethered fly from its events: initialise, split the events into four edges (two
wings x leading/trailing), track each edge with the WRA or the EKF, and combine each wing's edges into
its frequency and amplitude per beat (seed 002, part II).

A wing's leading edge darkens the pixels it reaches (OFF events) and its trailing edge brightens them
again (ON events). The leading edge is ahead of the wing's centre line by half the wing's width in
either stroke direction, the trailing edge behind it, so the two edges' amplitudes straddle the wing's
own: their mean is the wing's amplitude, and their mean frequency its frequency.

Both trackers report some beat on any events (they are built to lock on), so every result carries a
fit quality (beat_fit_quality): how much of the events' angle spread a wing stroke phase-locked to
the reported beats explains. A tethered fly gives about 0.98; noise, a moving bar, anything that does
not beat, about 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from flytrack_host.dvs.wingbeat.ekf import EkfParams, ekf_track
from flytrack_host.dvs.wingbeat.geometry import FlyGeometry, WingbeatError, estimate_frequency, initialise
from flytrack_host.dvs.wingbeat.wra import BeatSeries, EdgeTrack, WraParams, wra_track

Method = Literal["ekf", "wra"]
EDGES = ("leading", "trailing")


#: Below this fit quality the events are not taken for a wing beat (`flytrack wingbeat --min-quality`).
MIN_QUALITY = 0.5


@dataclass
class WingTrack:
    wing: int
    edges: dict[str, EdgeTrack]
    beats: BeatSeries  # the wing's: per leading-edge beat, edges combined
    quality: float = 0.0  # beat_fit_quality, the mean of its two edges'
    z_t_us: NDArray[np.float64] = field(repr=False, default_factory=lambda: np.zeros(0))  # measurements
    z: NDArray[np.float64] = field(repr=False, default_factory=lambda: np.zeros(0))


@dataclass
class WingbeatResult:
    method: Method
    geometry: FlyGeometry
    start_freq_hz: tuple[float, float]
    wings: list[WingTrack]
    events_total: int
    events_in_roi: int
    seconds: float  # tracking time (CPU of this call)

    @property
    def quality(self) -> float:
        """The fit quality of the worse wing: both must beat for a fly's wing beats."""
        return min(w.quality for w in self.wings) if self.wings else 0.0


def beat_fit_quality(t_us: NDArray, z: NDArray, beat_t_us: NDArray, window_us: float = 100_000.0,
                     min_events: int = 50) -> float:
    """How well an edge's events follow the beats reported for it, from 0 (not at all) to 1.

    Each event gets the phase of the reported beats (2 pi per beat, linear in time between the
    beats' ends), and in each window of `window_us` the events' angles are fitted by a stroke of two
    harmonics of that phase, a + sum_k (b_k sin k phi + c_k cos k phi), least squares. The window's
    figure is 1 - median squared residual / median squared deviation from the window's median angle
    (medians: the noise events a fly also gives do not count); the edge's is the median over the
    windows. Events that beat at the reported rhythm are explained by it whatever the tracker; events
    that do not (noise, an object passing) are not, whatever beats the tracker found in them. 0 when
    fewer than 3 beats were reported or no window holds `min_events` events."""
    bt = np.asarray(beat_t_us, dtype=np.float64)
    if len(bt) < 3:
        return 0.0
    t = np.asarray(t_us, dtype=np.float64)
    zz = np.asarray(z, dtype=np.float64)
    sel = (t >= bt[0]) & (t <= bt[-1])
    t, zz = t[sel], zz[sel]
    if len(t) < min_events:
        return 0.0
    phase = 2.0 * np.pi * np.interp(t, bt, np.arange(len(bt), dtype=np.float64))
    design = np.stack([np.ones_like(phase), np.sin(phase), np.cos(phase), np.sin(2 * phase), np.cos(2 * phase)],
                      axis=1)
    figures = []
    win = ((t - t[0]) // window_us).astype(np.int64)
    for k in np.unique(win):
        s = win == k
        if s.sum() < min_events:
            continue
        coef, *_ = np.linalg.lstsq(design[s], zz[s], rcond=None)
        res = zz[s] - design[s] @ coef
        spread = float(np.median(np.square(zz[s] - np.median(zz[s]))))
        figures.append(1.0 - float(np.median(np.square(res))) / spread if spread > 0 else 0.0)
    return float(np.median(figures)) if figures else 0.0


def _combine(lead: BeatSeries, trail: BeatSeries) -> BeatSeries:
    if len(lead.t_us) == 0 or len(trail.t_us) == 0:
        return lead if len(trail.t_us) == 0 else trail
    f = 0.5 * (lead.freq_hz + np.interp(lead.t_us, trail.t_us, trail.freq_hz))
    a = 0.5 * (lead.amplitude + np.interp(lead.t_us, trail.t_us, trail.amplitude))
    return BeatSeries(lead.t_us, f, a)


def track_wings(events: NDArray, method: Method = "ekf", init_s: float = 0.1, width: int = 128,
                height: int = 128, ekf: EkfParams | None = None, wra: WraParams | None = None,
                start_freq_hz: float | None = None) -> WingbeatResult:
    """Track both wings of a tethered fly in `events` (fields t in us, x, y, p with 1 = ON)."""
    import time

    t0 = time.process_time()
    if len(events) < 200:
        raise WingbeatError(f"{len(events)} events: too few for wing-beat analysis")
    # The initialisation buffer: the first `init_s` of events (enough beats for the frequency search).
    head = events[events["t"] < events["t"][0] + init_s * 1e6]
    geo = initialise(head["x"], head["y"], width, height)
    ang, wing = geo.angles(events["x"], events["y"])
    h_ang, h_wing = geo.angles(head["x"], head["y"])
    freqs = []
    for w in (0, 1):
        sel = h_wing == w
        freqs.append(start_freq_hz or estimate_frequency(head["t"][sel], h_ang[sel]))
    wings = []
    for w in (0, 1):
        edges = {}
        for name, pol in (("leading", 0), ("trailing", 1)):
            sel = (wing == w) & (events["p"] == pol)
            tt, zz = events["t"][sel], ang[sel]
            if method == "ekf":
                edges[name] = ekf_track(tt, zz, geo.mean_stroke[w], geo.spread[w], freqs[w], ekf or EkfParams())
            elif method == "wra":
                edges[name] = wra_track(tt, zz, geo.mean_stroke[w], geo.spread[w], wra or WraParams())
            else:
                raise ValueError(f"method is 'ekf' or 'wra', not {method!r}")
        quality = []
        for name, pol in (("leading", 0), ("trailing", 1)):
            sel = (wing == w) & (events["p"] == pol)
            edges[name].quality = beat_fit_quality(events["t"][sel], ang[sel], edges[name].beats.t_us)
            quality.append(edges[name].quality)
        sel = wing == w
        wings.append(WingTrack(w, edges, _combine(edges["leading"].beats, edges["trailing"].beats),
                               quality=float(np.mean(quality)), z_t_us=events["t"][sel].astype(np.float64),
                               z=ang[sel]))
    return WingbeatResult(method, geo, (freqs[0], freqs[1]), wings, len(events), int((wing >= 0).sum()),
                          time.process_time() - t0)


@dataclass
class WingScore:
    wing: int
    beats: int
    freq_err_pct_mean: float  # mean |f_est / f_true - 1|, %
    freq_err_pct_max: float
    freq_jitter_pct: float  # std of f_est / f_true - 1, %
    amp_err_pct_mean: float
    amp_err_pct_max: float


def score_wings(result: WingbeatResult, freq_at, amp_at, skip_s: float = 0.15) -> list[WingScore]:
    """Each wing's per-beat estimates against the truth (callables of time in us), after `skip_s` of
    convergence. Frequencies are compared with the truth averaged over the beat they describe."""
    out = []
    for wt in result.wings:
        b = wt.beats
        ok = b.t_us >= b.t_us[0] + skip_s * 1e6 if len(b.t_us) else np.zeros(0, dtype=bool)
        t, f, a = b.t_us[ok], b.freq_hz[ok], b.amplitude[ok]
        if len(t) == 0:
            out.append(WingScore(wt.wing, 0, *(float("nan"),) * 5))
            continue
        period = 1e6 / f
        f_true = np.array([np.mean(freq_at(np.linspace(ti - pi, ti, 16))) for ti, pi in zip(t, period, strict=True)])
        a_true = np.array([np.mean(amp_at(wt.wing, np.linspace(ti - pi, ti, 16))) for ti, pi in zip(t, period,
                                                                                                     strict=True)])
        fe = f / f_true - 1.0
        ae = a / a_true - 1.0
        out.append(WingScore(wt.wing, len(t), float(100 * np.mean(np.abs(fe))), float(100 * np.max(np.abs(fe))),
                             float(100 * np.std(fe)), float(100 * np.mean(np.abs(ae))),
                             float(100 * np.max(np.abs(ae)))))
    return out
