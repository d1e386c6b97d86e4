"""A blinking LED in a DVS camera's events, turned into one 2D point per trigger frame for
self-calibration beside the frame cameras.

A LED switched on and off at a known frequency makes every pixel it covers fire a run of ON events at
switch-on and a run of OFF events at switch-off, once per period. Per pixel, the events are cut into
runs of one polarity; a run belongs to the LED when the next (or the previous) run of the same
polarity at that pixel starts one LED period later (within `tolerance`), and the run of the other
polarity between them starts after the LED's on (or off) time. A moving object, a flicker at another
frequency and background noise fail that test. The points are the LED's events around each sync
event (the trigger pulse recorded by the camera): the events within `window_us` of the pulse, kept
within `radius_px` of their median, fitted by position = a + b (t - t_pulse) per axis, so `a` is
where the LED was at the pulse even while it moves. The sync events give the trigger frame, so the
points pair with the frame cameras' points frame by frame.

All of it is vectorised NumPy; `LedExtractor` takes a file's events chunk by chunk (memory bounded by
a few frames of events), `led_points` a whole array.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

__all__ = ["LedParams", "LedPoints", "LedExtractor", "led_points", "periodic_mask", "dominant_frequencies",
           "sync_frames", "SyncError"]


class SyncError(ValueError):
    """The sync events cannot tie event times to trigger frames."""


@dataclass(frozen=True)
class LedParams:
    led_hz: float  # the LED's blink frequency
    tolerance: float = 0.15  # relative: a period (and an on/off time) may differ from the nominal by this
    duty: float | None = 0.5  # fraction of the period the LED is on (None: not checked)
    window_us: float | None = None  # events within +-window/2 of a pulse; default 4 periods, at most 0.8 frame
    radius_px: float = 6.0  # events farther than this from the window's median are not the LED
    min_events: int = 12  # fewer LED events in a window: no point
    check_frequency: bool = True  # False: every event is taken as the LED's (diagnosis; the test breaks it)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.led_hz) and 0.5 <= self.led_hz <= 50_000):
            raise ValueError(f"LED frequency must be 0.5..50000 Hz, got {self.led_hz}")
        if not (0.01 <= self.tolerance <= 0.45):
            raise ValueError(f"tolerance must be 0.01..0.45 (a fraction of the period), got {self.tolerance}")
        if self.duty is not None and not (0.05 <= self.duty <= 0.95):
            raise ValueError(f"duty must be 0.05..0.95, got {self.duty}")
        if self.window_us is not None and not (self.window_us > 0):
            raise ValueError(f"window must be positive, got {self.window_us} us")

    @property
    def period_us(self) -> float:
        return 1e6 / self.led_hz


@dataclass
class LedPoints:
    """One point per trigger frame where the LED was found."""

    frame: NDArray[np.int64]  # trigger frame number
    uv: NDArray[np.float64]  # (N, 2) pixel position of the LED at the pulse (x, y of the events)
    n_events: NDArray[np.int64]  # LED events the point was fitted from
    t_us: NDArray[np.int64]  # the pulse's time on the camera's clock
    spread_px: NDArray[np.float64]  # rms distance of those events from the fitted track
    stats: dict[str, int] = field(default_factory=dict)


def _runs(key: NDArray[np.int64], t: NDArray[np.int64], p: NDArray[np.uint8],
          max_gap: float = np.inf) -> tuple[NDArray, ...]:
    """Events ordered by pixel (time order kept within a pixel) and cut into same-polarity runs (a
    gap longer than max_gap starts a new run too): (order, run id of each ordered event, run start
    times, run pixels, run polarities)."""
    order = np.argsort(key, kind="stable")
    k, tt, pp = key[order], t[order], p[order]
    start = np.ones(len(k), bool)
    if len(k) > 1:
        start[1:] = (k[1:] != k[:-1]) | (pp[1:] != pp[:-1]) | ((tt[1:] - tt[:-1]) > max_gap)
    run = np.cumsum(start) - 1
    return order, run, tt[start], k[start], pp[start]


def periodic_mask(ev: np.ndarray, width: int, params: LedParams) -> NDArray[np.bool_]:
    """Which events (time-ordered EVENT_DTYPE) belong to an on/off cycle at the LED's frequency."""
    if not params.check_frequency:
        return np.ones(len(ev), bool)
    n = len(ev)
    if n < 3:
        return np.zeros(n, bool)
    T = params.period_us
    tol = params.tolerance * T
    # A switch's run of events lasts at most its on (or off) time: a longer gap at a pixel starts a
    # new run, and a run's events past that time are not the LED's (an OFF run may go on long after
    # the LED has passed, when something else darkens the pixel).
    on_off = max(params.duty, 1.0 - params.duty) if params.duty is not None else 1.0
    limit = on_off * T + tol
    key = ev["y"].astype(np.int64) * int(width) + ev["x"].astype(np.int64)
    order, run, r_t, r_k, r_p = _runs(key, ev["t"].astype(np.int64), ev["p"], max_gap=limit)
    m = len(r_t)
    ok = np.zeros(m, bool)
    if m >= 3:
        # run r and r+2: same pixel means same polarity (runs alternate within a pixel)
        same = r_k[2:] == r_k[:-2]
        per = r_t[2:] - r_t[:-2]
        fwd = same & (np.abs(per - T) <= tol)
        if params.duty is not None:
            on_time = np.where(r_p[:-2] == 1, params.duty, 1.0 - params.duty) * T
            fwd &= np.abs((r_t[1:-1] - r_t[:-2]) - on_time) <= tol
        ok[:-2] |= fwd  # the cycle starting at run r ...
        ok[2:] |= fwd  # ... and the run one period later
        ok[1:-1] |= fwd  # the opposite switch between them
    t_sorted = ev["t"].astype(np.int64)[order]
    ok_ev = ok[run] & (t_sorted - r_t[run] <= limit)
    mask = np.empty(n, bool)
    mask[order] = ok_ev
    return mask


def dominant_frequencies(ev: np.ndarray, width: int, top: int = 3) -> list[tuple[float, float]]:
    """The strongest repetition frequencies in the events: per pixel, the time from the start of one
    same-polarity run to the next of that polarity, histogrammed (20 Hz - 50 kHz, 3 % bins); the
    `top` peaks as (Hz, share of all such intervals)."""
    if len(ev) < 3:
        return []
    key = ev["y"].astype(np.int64) * int(width) + ev["x"].astype(np.int64)
    _, _, r_t, r_k, _ = _runs(key, ev["t"].astype(np.int64), ev["p"])
    same = r_k[2:] == r_k[:-2]
    dt = (r_t[2:] - r_t[:-2])[same]
    dt = dt[(dt >= 20) & (dt <= 50_000)]
    if not len(dt):
        return []
    f = 1e6 / dt
    edges = np.exp(np.arange(np.log(20.0), np.log(50_000.0) + 0.03, 0.03))
    hist, _ = np.histogram(f, bins=edges)
    # a peak with its neighbours (a frequency on a bin edge splits)
    smooth = hist + np.r_[0, hist[:-1]] + np.r_[hist[1:], 0]
    out: list[tuple[float, float]] = []
    s = smooth.astype(float)
    for _ in range(top):
        i = int(np.argmax(s))
        if s[i] <= 0:
            break
        lo, hi = max(0, i - 1), min(len(hist), i + 2)
        sel = (f >= edges[lo]) & (f < edges[hi])
        out.append((float(np.median(f[sel])), float(sel.sum() / len(f))))
        s[max(0, i - 3): i + 4] = 0
    return out


def sync_frames(t_us: NDArray[np.int64], first_frame: int = 0) -> tuple[NDArray[np.int64], int]:
    """Trigger frame numbers of consecutive sync events: first_frame, then one more per nominal
    interval (the median), so a missed pulse skips a frame number instead of shifting every later one.
    Returns (frames, pulses taken as missed)."""
    t = np.asarray(t_us, np.int64)
    if len(t) == 0:
        return np.zeros(0, np.int64), 0
    if len(t) == 1:
        return np.array([first_frame], np.int64), 0
    d = np.diff(t)
    if np.any(d <= 0):
        raise SyncError(f"sync events go back in time or repeat (at sync {int(np.argmax(d <= 0)) + 1}); "
                        "check that the file holds one camera's sync input")
    nominal = float(np.median(d))
    steps = np.maximum(1, np.rint(d / nominal)).astype(np.int64)
    frames = first_frame + np.r_[0, np.cumsum(steps)]
    return frames.astype(np.int64), int((steps - 1).sum())


def _fit_windows(ev: np.ndarray, sync_t: NDArray[np.int64], half_w: float,
                 params: LedParams) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64],
                                             NDArray[np.float64]]:
    """LED position at each pulse from the (LED) events near it: (sync index, uv, events, spread)."""
    empty = (np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0))
    if not len(ev) or not len(sync_t):
        return empty
    t = ev["t"].astype(np.int64)
    j = np.searchsorted(sync_t, t)  # nearest pulse: j-1 or j
    jl = np.clip(j - 1, 0, len(sync_t) - 1)
    jr = np.clip(j, 0, len(sync_t) - 1)
    pick_r = np.abs(sync_t[jr] - t) < np.abs(t - sync_t[jl])
    jn = np.where(pick_r, jr, jl)
    dt = (t - sync_t[jn]).astype(np.float64)
    keep = np.abs(dt) <= half_w
    if not np.any(keep):
        return empty
    jn, dt = jn[keep], dt[keep]
    x = ev["x"][keep].astype(np.float64)
    y = ev["y"][keep].astype(np.float64)
    # Robust centre: the per-window median of x and of y (sort by window, then coordinate).
    wins, inv, counts = np.unique(jn, return_inverse=True, return_counts=True)
    first = np.r_[0, np.cumsum(counts)[:-1]]
    med = np.empty((len(wins), 2))
    for a, c in enumerate((x, y)):
        o = np.lexsort((c, inv))
        med[:, a] = c[o][first + counts // 2]
    near = np.hypot(x - med[inv, 0], y - med[inv, 1]) <= params.radius_px
    inv, dt, x, y = inv[near], dt[near], x[near], y[near]
    nw = len(wins)
    s0 = np.bincount(inv, minlength=nw).astype(np.float64)
    s1 = np.bincount(inv, dt, nw)
    s2 = np.bincount(inv, dt * dt, nw)
    uv = np.empty((nw, 2))
    res2 = np.zeros(nw)
    det = s0 * s2 - s1 * s1
    flat = det <= 1e-9 * np.maximum(s0 * s2, 1e-300)  # all events at one time: the mean
    for a, c in enumerate((x, y)):
        sc = np.bincount(inv, c, nw)
        sct = np.bincount(inv, c * dt, nw)
        with np.errstate(invalid="ignore", divide="ignore"):
            a0 = np.where(flat, sc / s0, (s2 * sc - s1 * sct) / np.where(flat, 1.0, det))
            b0 = np.where(flat, 0.0, (s0 * sct - s1 * sc) / np.where(flat, 1.0, det))
        uv[:, a] = a0
        r = c - (a0[inv] + b0[inv] * dt)
        res2 += np.bincount(inv, r * r, nw)
    with np.errstate(invalid="ignore", divide="ignore"):
        spread = np.sqrt(res2 / s0)
    # Events on both sides of the pulse: the fit interpolates (the LED turned away, or out of view,
    # in half the window would leave an extrapolation).
    side = max(3, params.min_events // 4)
    before = np.bincount(inv, dt < 0, nw)
    after = np.bincount(inv, dt > 0, nw)
    good = (s0 >= params.min_events) & (before >= side) & (after >= side) & np.all(np.isfinite(uv), axis=1)
    return wins[good].astype(np.int64), uv[good], s0[good].astype(np.int64), spread[good]


class LedExtractor:
    """Streams a DVS camera's events and sync events through the LED finder:

        ex = LedExtractor(width, height, LedParams(led_hz=500))
        for events, syncs in ...:   # time-ordered EVENT_DTYPE chunks and the sync times (us) they held
            ex.feed(events, syncs)
        pts = ex.finish(first_frame=0)

    Events are kept only while a pulse near them is still to be done: a pulse is done once events
    are in more than its window plus three LED periods past it (what the periodicity test looks at).
    """

    def __init__(self, width: int, height: int, params: LedParams) -> None:
        if width <= 0 or height <= 0:
            raise ValueError(f"sensor size {width}x{height} is not positive")
        self.width, self.height, self.p = int(width), int(height), params
        self._buf: list[np.ndarray] = []
        self._sync: list[NDArray[np.int64]] = []
        self._sync_all = np.zeros(0, np.int64)
        self._done = 0  # pulses processed
        self._out: list[tuple[NDArray, ...]] = []
        self.stats = {"events": 0, "led_events": 0, "windows": 0}
        self._freq_sample: list[np.ndarray] = []  # a bounded sample of events for the error message
        self._freq_n = 0
        self._half: float | None = None

    def _half_window(self) -> float:
        """Half the window, whole microseconds (so a frame interval measured a microsecond apart gives the same)."""
        if self._half is not None:
            return self._half
        T = self.p.period_us
        w = self.p.window_us if self.p.window_us is not None else 4 * T
        if self.p.window_us is None and len(self._sync_all) >= 2:
            w = min(w, 0.8 * float(np.median(np.diff(self._sync_all[:1000]))))
        half = float(max(1, int(w // 2)))
        if self.p.window_us is not None or len(self._sync_all) >= 5:
            self._half = half  # settled
        return half

    def feed(self, events: np.ndarray, sync_t: NDArray[np.int64] | None = None) -> None:
        if len(events):
            if len(events) > 1 and np.any(np.diff(events["t"]) < 0):
                raise ValueError("events must come in non-decreasing time")
            self._buf.append(events)
            self.stats["events"] += len(events)
            if self._freq_n < 4_000_000:
                self._freq_sample.append(events)
                self._freq_n += len(events)
        if sync_t is not None and len(sync_t):
            self._sync_all = np.concatenate([self._sync_all, np.asarray(sync_t, np.int64)])
        if self._buf:
            self._process(final=False)

    def _process(self, final: bool) -> None:
        if not self._buf:
            return
        ev = self._buf[0] if len(self._buf) == 1 else np.concatenate(self._buf)
        self._buf = [ev]
        if not len(ev) or self._done >= len(self._sync_all):
            self._trim(ev)
            return
        half = self._half_window()
        margin = half + 3 * self.p.period_us * (1 + self.p.tolerance)
        t_last = int(ev["t"][-1])
        sync = self._sync_all
        stop = len(sync) if final else int(np.searchsorted(sync, t_last - margin, side="right"))
        if stop <= self._done:
            self._trim(ev)
            return
        lo = sync[self._done] - margin
        hi = sync[stop - 1] + margin
        i0, i1 = np.searchsorted(ev["t"], [lo, hi + 1])
        block = ev[i0:i1]
        mask = periodic_mask(block, self.width, self.p)
        led = block[mask]
        self.stats["led_events"] += int(np.count_nonzero(mask[(block["t"] >= sync[self._done] - half)
                                                               & (block["t"] <= sync[stop - 1] + half)]))
        idx, uv, n, spread = _fit_windows(led, sync[self._done:stop], half, self.p)
        self.stats["windows"] += stop - self._done
        self._out.append((idx + self._done, uv, n, spread))
        self._done = stop
        self._trim(ev)

    def _trim(self, ev: np.ndarray) -> None:
        """Drops the events no pulse still to be done can use (a pulse not yet seen comes after the
        events so far, less than a margin before the last)."""
        if not len(ev):
            self._buf = []
            return
        margin = self._half_window() + 3 * self.p.period_us * (1 + self.p.tolerance)
        keep_from = float(ev["t"][-1]) - 2 * margin
        if self._done < len(self._sync_all):
            keep_from = min(keep_from, float(self._sync_all[self._done]) - margin)
        i = int(np.searchsorted(ev["t"], keep_from))
        self._buf = [ev[i:]] if i < len(ev) else []

    def finish(self, first_frame: int = 0, frames: NDArray[np.int64] | None = None) -> LedPoints:
        """The points; the pulses' frame numbers are first_frame, first_frame + 1, ... (a missed pulse
        skipped, see sync_frames), or `frames` (one per sync time fed)."""
        self._process(final=True)
        if frames is not None:
            frames = np.asarray(frames, np.int64)
            if len(frames) != len(self._sync_all):
                raise SyncError(f"{len(frames)} frame numbers for {len(self._sync_all)} pulses")
            missed = 0
        else:
            frames, missed = sync_frames(self._sync_all, first_frame)
        if self._out:
            idx = np.concatenate([o[0] for o in self._out])
            uv = np.concatenate([o[1] for o in self._out])
            n = np.concatenate([o[2] for o in self._out])
            spread = np.concatenate([o[3] for o in self._out])
        else:
            idx, uv, n, spread = np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0)
        # Inside the sensor only (a fit at the border can land just outside).
        inside = ((uv[:, 0] >= -0.5) & (uv[:, 0] <= self.width - 0.5)
                  & (uv[:, 1] >= -0.5) & (uv[:, 1] <= self.height - 0.5))
        idx, uv, n, spread = idx[inside], uv[inside], n[inside], spread[inside]
        stats = dict(self.stats, syncs=len(self._sync_all), missed_syncs=missed, points=len(idx))
        return LedPoints(frames[idx] if len(idx) else np.zeros(0, np.int64), uv, n,
                         self._sync_all[idx] if len(idx) else np.zeros(0, np.int64), spread, stats)

    def frequencies(self, top: int = 3) -> list[tuple[float, float]]:
        """The dominant repetition frequencies in (the first few million of) the events seen."""
        if not self._freq_sample:
            return []
        return dominant_frequencies(np.concatenate(self._freq_sample), self.width, top)


def led_points(ev: np.ndarray, sync_t: NDArray[np.int64], width: int, height: int, params: LedParams,
               first_frame: int = 0) -> LedPoints:
    """The LED's points of a whole time-ordered event array (see LedExtractor)."""
    ex = LedExtractor(width, height, params)
    ex.feed(ev, np.asarray(sync_t, np.int64))
    return ex.finish(first_frame)
