"""Curvature of the midline and fast-start detection (seed 04 §5.3, eq. 5.2):
kappa(s) = |f1' f2'' - f2' f1''| / (f1'^2 + f2'^2)^(3/2), kappa_total = int_0^1 kappa(s) ds, derivatives in s.

Curvature is in 1/m. Fast starts (C-start, S-start: a bend and turn within 100 ms, seed 004 §1) show as a
fast, high peak of kappa_total; a C-start bends the whole body one way (the signed curvature keeps one
sign), an S-start has two opposite bends (the signed curvature changes sign along the body).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from flytrack_host.fish.shape import midline_body

F64 = NDArray[np.float64]
S_GRID = np.linspace(0.0, 1.0, 41)


def signed_curvature(p: F64, s: F64 = S_GRID) -> F64:
    """Signed curvature (1/m) of the body midline for p (..., 5) at s: (..., Ns). Positive bends to +y."""
    p = np.asarray(p, float)
    shape = p.shape[:-1]
    _, df, d2f = midline_body(p.reshape(-1, 5), s)
    num = df[..., 0] * d2f[..., 1] - df[..., 1] * d2f[..., 0]
    den = (df[..., 0] ** 2 + df[..., 1] ** 2) ** 1.5
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.where(den > 0, num / den, np.nan)
    return k.reshape(*shape, len(s))


def curvature(p: F64, s: F64 = S_GRID) -> F64:
    """Eq. 5.2's kappa(s), 1/m."""
    return np.abs(signed_curvature(p, s))


def total_curvature(p: F64, s: F64 = S_GRID) -> F64:
    """Eq. 5.2's kappa_total = int_0^1 kappa(s) ds (trapezoid on s), 1/m."""
    return np.trapezoid(curvature(p, s), s, axis=-1)


@dataclass
class FastStart:
    fish: int
    kind: str  # "C-start" or "S-start"
    onset: int  # frame where the bend starts
    peak: int  # frame of the largest total curvature
    peak_total: float  # kappa_total at the peak, 1/m
    rise_ms: float


def detect_fast_starts(P: F64, fps: float, length: float, fish: int = 0, threshold_bl: float = 0.45,
                       max_rise_ms: float = 100.0, onset_fraction: float = 0.15) -> list[FastStart]:
    """Fast starts in one fish's midline parameters P (T, 5): peaks of kappa_total above `threshold_bl`
    (in 1/body length) reached within `max_rise_ms` of the onset, the first frame of the climb above the
    baseline (the track's median) plus `onset_fraction` of the rise. NaN frames are skipped."""
    kt = total_curvature(P) * length  # in 1/body length
    base = float(np.nanmedian(kt)) if np.any(np.isfinite(kt)) else 0.0
    ks = signed_curvature(P)
    T = len(kt)
    out: list[FastStart] = []
    k = 0
    while k < T:
        if not (np.isfinite(kt[k]) and kt[k] > threshold_bl):
            k += 1
            continue
        # the peak of this excursion
        e = k
        while e + 1 < T and np.isfinite(kt[e + 1]) and kt[e + 1] > threshold_bl:
            e += 1
        seg = kt[k:e + 1]
        peak = k + int(np.nanargmax(seg))
        level = base + onset_fraction * (kt[peak] - base)
        onset = peak
        while onset > 0 and np.isfinite(kt[onset - 1]) and kt[onset - 1] > level:
            onset -= 1
        rise_ms = (peak - onset) * 1000.0 / fps
        if rise_ms <= max_rise_ms:
            prof = ks[peak, 2:-2]  # the very ends carry little bend
            pos = np.nansum(np.clip(prof, 0, None))
            neg = np.nansum(np.clip(-prof, 0, None))
            kind = "S-start" if min(pos, neg) > 0.2 * max(pos, neg) else "C-start"
            out.append(FastStart(fish, kind, onset, peak, float(kt[peak] / length), rise_ms))
        k = e + 1
    return out
