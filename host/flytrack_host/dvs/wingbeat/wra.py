"""The weighted running average (WRA) wing-edge tracker of seed 002 (part II, section 3.1).

Every event of an edge moves the tracker towards it, x_k = (1 - m) x_{k-1} + m z_k (eq. 7). A beat is
counted when the track crosses its centre line upwards through a hysteresis band (the band adapts to
the last beat's amplitude, so noise cannot count extra beats); after each beat the frequency (one over
the time between crossings), the amplitude (half the track's range over the beat) and the centre (the
mean angle of the beat's events) are updated.

One addition to the seed: an event farther than `gate_rad` from the track is not used (a noise event
inside the region of interest would otherwise make a spike that the amplitude reads as a peak), unless
`regain_after` events in a row are that far, which means the track, not the events, is wrong.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class WraParams:
    mixing: float = 0.1  # m of eq. 7 (the seed's value)
    hysteresis: float = 0.3  # half-width of the band, as a share of the last amplitude
    gate_rad: float = 0.6
    regain_after: int = 20


@dataclass
class BeatSeries:
    """Per beat of one edge (or wing): when it ended, its frequency and amplitude."""

    t_us: NDArray[np.float64]
    freq_hz: NDArray[np.float64]
    amplitude: NDArray[np.float64]


@dataclass
class EdgeTrack:
    t_us: NDArray[np.float64]  # per update
    position: NDArray[np.float64]  # the track (rad from the heading)
    beats: BeatSeries
    used: int  # events used
    gated: int  # events left out as noise
    quality: float = 0.0  # analysis.beat_fit_quality of its events against its beats


def wra_track(t_us: NDArray, z: NDArray, centre: float, amplitude: float,
              params: WraParams = WraParams()) -> EdgeTrack:
    """Track one edge from its events' times (us) and angles (rad), starting at `centre` with a guess
    of the amplitude (from the initialisation)."""
    m = params.mixing
    x = float(centre)
    c = float(centre)
    band = params.hysteresis * amplitude
    low = True
    last_cross: float | None = None
    bmax, bmin, zsum, zn = -np.inf, np.inf, 0.0, 0
    far = 0
    gated = 0
    tt = np.asarray(t_us, dtype=np.float64)
    zz = np.asarray(z, dtype=np.float64)
    pos = np.empty(len(zz))
    keep = np.zeros(len(zz), dtype=bool)
    beats_t, beats_f, beats_a = [], [], []
    for i in range(len(zz)):
        zi = zz[i]
        if abs(zi - x) > params.gate_rad:
            far += 1
            if far < params.regain_after:
                gated += 1
                continue
        far = 0
        x = (1.0 - m) * x + m * zi
        pos[i] = x
        keep[i] = True
        if x > bmax:
            bmax = x
        if x < bmin:
            bmin = x
        zsum += zi
        zn += 1
        if low and x > c + band:
            low = False
            ti = tt[i]
            if last_cross is not None and zn > 4:
                amp = 0.5 * (bmax - bmin)
                beats_t.append(ti)
                beats_f.append(1e6 / (ti - last_cross))
                beats_a.append(amp)
                c = zsum / zn
                band = params.hysteresis * amp
            last_cross = ti
            bmax, bmin, zsum, zn = -np.inf, np.inf, 0.0, 0
        elif not low and x < c - band:
            low = True
    return EdgeTrack(t_us=tt[keep], position=pos[keep],
                     beats=BeatSeries(np.array(beats_t), np.array(beats_f), np.array(beats_a)),
                     used=int(keep.sum()), gated=gated)
