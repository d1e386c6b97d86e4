"""The trigger clock model: host time = gain x device time + offset.

Each clock query gives a device time (frame count and timer ticks -> seconds since frame 0 began)
bracketed by two host times (request sent, reply received). The device time belongs somewhere in
that round trip. Where: on a serial link the bytes take their wire time (10 bits a byte at the
baud rate: ~0.8 ms for a 9-byte request at 115200 baud, ~1.5 ms for a 17-byte reply) and the
device samples its clock once the request's last byte is in (plus its own processing). What the
wire does not explain (the host's write and read latency, a USB adapter's) is split evenly between
the way out and the way back (LinkTiming.sample_time); the round trip's plain midpoint would be
(reply - request) / 2 late, ~0.35 ms here. Without a known link (bytes that arrive at once, as on
the SoftwareTrigger's pty) the midpoint is the estimate, good to half the round trip.

The fit is NTP's clock filter and a least-squares line, made robust to a loaded host:
- a round trip shorter than the wire allows is impossible on that link: the device side was behind
  (a simulator that lags the wall clock) and its time is dropped (only while most round trips do
  respect the wire time: a link faster than its stated baud keeps everything);
- of every group of 1/keep_fraction consecutive samples only the one with the smallest round trip
  is kept (the lower envelope of the delay: its placement error is at most half its own excess
  latency), so the kept samples spread over the whole window, and a long window gives the gain
  its lever;
- gain and offset by least squares over those, outliers (beyond a few robust standard deviations)
  dropped and refitted; `gain_se` is the gain's standard error from the fit's residuals.
A device time that goes backwards, or a run of samples far off the model, means the device restarted
(or was reset): the window starts afresh. The far samples are held back until `jump_count` of them
agree with each other; they then seed the new window, so the model is fitted again at once (not
`min_samples` queries later).
"""

from __future__ import annotations

import functools
import math
from collections import deque
from dataclasses import dataclass

import numpy as np


@functools.lru_cache(maxsize=64)
def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs i < j of n samples (cached: the Theil-Sen start runs on every fit)."""
    return np.triu_indices(n, 1)


@dataclass(frozen=True)
class LinkTiming:
    """Where within a clock query's round trip the device samples its clock, from the wire."""

    request_s: float  # wire time of the request: the device has it all this long after host_t0
    reply_s: float  # wire time of the reply: the host has it all this long after it was begun
    device_s: float = 0.0  # device time from the request's last byte to its clock sample

    @classmethod
    def serial(cls, baudrate: float, request_bytes: int, reply_bytes: int, device_s: float = 0.0,
               bits_per_byte: int = 10) -> LinkTiming:
        """A UART link: `bits_per_byte` (8N1: 10) per byte at `baudrate`."""
        if not baudrate > 0 or request_bytes < 0 or reply_bytes < 0:
            raise ValueError("baudrate > 0 and byte counts >= 0 are required")
        byte_s = bits_per_byte / float(baudrate)
        return cls(request_bytes * byte_s, reply_bytes * byte_s, device_s)

    @property
    def min_rtt_s(self) -> float:
        return self.request_s + self.device_s + self.reply_s

    def sample_time(self, host_t0: float, host_t1: float) -> float:
        """Host time of the device's clock sample: the request's last byte in, then processing,
        plus half of the latency the wire does not explain (host write/read scheduling, split
        evenly between the two ways: the error is then at most half that excess). The sample also
        came at least the reply's wire time before host_t1: a round trip shorter than the wire
        allows (a link faster than its stated baud) is bounded by that, and by t0."""
        excess = max(0.0, (host_t1 - host_t0) - self.min_rtt_s)
        at = host_t0 + self.request_s + self.device_s + 0.5 * excess
        return max(host_t0, min(at, host_t1 - self.reply_s))


@dataclass(frozen=True)
class ClockSample:
    host_t0: float  # host time the query was sent (s)
    host_t1: float  # host time the reply arrived (s)
    device_time_s: float
    host_sample: float = math.nan  # host time of the device's sample (the midpoint if not given)

    def __post_init__(self) -> None:
        if math.isnan(self.host_sample):
            object.__setattr__(self, "host_sample", self.host_mid)

    @property
    def rtt_s(self) -> float:
        return self.host_t1 - self.host_t0

    @property
    def host_mid(self) -> float:
        return 0.5 * (self.host_t0 + self.host_t1)


class ClockModel:
    """Least-squares map from device time to host time over a window of recent clock samples."""

    def __init__(
        self,
        frame_period_s: float | None = None,
        window: int = 200,
        max_rtt_s: float = 0.010,
        keep_fraction: float = 0.2,
        outlier_sigmas: float = 4.0,
        jump_threshold_s: float = 0.020,
        jump_count: int = 3,
        min_samples: int = 3,
        min_jump_span_s: float = 0.5,
        link: LinkTiming | None = None,
    ) -> None:
        if window < 2 or not 0 < keep_fraction <= 1 or max_rtt_s <= 0:
            raise ValueError("window >= 2, 0 < keep_fraction <= 1 and max_rtt_s > 0 are required")
        self.frame_period_s = frame_period_s
        self.window = window
        self.max_rtt_s = max_rtt_s
        self.keep_fraction = keep_fraction
        self.outlier_sigmas = outlier_sigmas
        self.jump_threshold_s = jump_threshold_s
        self.jump_count = jump_count
        # A fit over less device time than this is no reference for a jump: three samples a few ms
        # apart, each off by the host's jitter, can give a gain of 2.3 (seen at load 11), and every
        # later sample then looked far off, was held back, and (their offsets under that gain never
        # agreeing) never let the fit move again: frame times 1.75 s off for the rest of the run.
        self.min_jump_span_s = min_jump_span_s
        self.min_samples = min_samples
        # How a round trip maps to the device's sample instant; None: its midpoint. The driver that
        # knows the link (baud rate, frame sizes) sets it.
        self.link = link
        self._samples: deque[ClockSample] = deque(maxlen=window)
        self._held: list[ClockSample] = []  # samples far off the fit, held back until a jump is confirmed
        self.gain = 1.0
        self.offset = 0.0
        self.residual_s = math.nan
        self.n_samples = 0  # samples used by the last fit
        self.gain_se = math.nan  # standard error of the fitted gain (host s per device s)
        self.span_s = math.nan  # device-time span of the samples used by the last fit
        self.short_rtt = 0  # samples of the window dropped for a round trip shorter than the wire allows
        self.fitted = False
        self.rejected_rtt = 0
        self.restarts = 0

    # ------------------------------------------------------------------ samples

    def sample_host_time(self, host_t0: float, host_t1: float) -> float:
        """Host time at which the device sampled its clock during a query sent at host_t0 and
        answered at host_t1: from the link's wire timing, else the round trip's midpoint."""
        if self.link is None:
            return 0.5 * (host_t0 + host_t1)
        return self.link.sample_time(host_t0, host_t1)

    def reset(self) -> None:
        self._samples.clear()
        self._held.clear()
        self.fitted = False
        self.n_samples = 0
        self.residual_s = math.nan
        self.gain_se = math.nan
        self.span_s = math.nan

    def add_sample(self, host_t0: float, host_t1: float, device_time_s: float) -> bool:
        """Adds one clock query; returns False when it was rejected (round trip too long, not finite)."""
        if not all(math.isfinite(v) for v in (host_t0, host_t1, device_time_s)) or host_t1 < host_t0:
            self.rejected_rtt += 1
            return False
        s = ClockSample(host_t0, host_t1, device_time_s, self.sample_host_time(host_t0, host_t1))
        if s.rtt_s > self.max_rtt_s:
            self.rejected_rtt += 1
            return False
        if self._samples and device_time_s < self._samples[-1].device_time_s:
            self._restart()
        elif (self.fitted and self.span_s >= self.min_jump_span_s
              and abs(self.device_to_host(device_time_s) - s.host_sample) > self.jump_threshold_s):
            # Held back: an outlier unless the next ones agree with it (the same new offset).
            if self._held and abs(self._offset_of(s) - self._offset_of(self._held[-1])) > self.jump_threshold_s:
                self._held.clear()
            self._held.append(s)
            if len(self._held) < self.jump_count:
                return True
            confirming = self._held[:-1]
            self._restart()
            self._samples.extend(confirming)  # the jump's own samples start the new window
        else:
            self._held.clear()
        self._samples.append(s)
        self.fit()
        return True

    def fit_batch(self, host_t0: np.ndarray, host_t1: np.ndarray, device_time_s: np.ndarray) -> bool:
        """Fits the model once over many samples in time order (a recording's), as add_sample one by
        one would end up, without refitting after each: samples that are not finite or whose round trip
        exceeds max_rtt_s are rejected; where the device time goes back (a restart) the window starts
        afresh; the last `window` samples are fitted. Returns whether a fit was made."""
        t0 = np.asarray(host_t0, dtype=np.float64)
        t1 = np.asarray(host_t1, dtype=np.float64)
        dev = np.asarray(device_time_s, dtype=np.float64)
        ok = np.isfinite(t0) & np.isfinite(t1) & np.isfinite(dev) & (t1 >= t0) & (t1 - t0 <= self.max_rtt_s)
        self.rejected_rtt += int((~ok).sum())
        idx = np.flatnonzero(ok)
        back = np.flatnonzero(np.diff(dev[idx]) < 0)
        if len(back):
            self.restarts += len(back)
            idx = idx[back[-1] + 1:]
        self.reset()
        for i in idx[-self.window:]:
            a, b = float(t0[i]), float(t1[i])
            self._samples.append(ClockSample(a, b, float(dev[i]), self.sample_host_time(a, b)))
        return self.fit()

    def _offset_of(self, s: ClockSample) -> float:
        return s.host_sample - self.gain * s.device_time_s

    def _restart(self) -> None:
        self.restarts += 1
        self.reset()

    # ------------------------------------------------------------------ fit

    def select(self, samples: list[ClockSample]) -> np.ndarray:
        """Indices of the samples a fit uses: in each group of about 1/keep_fraction consecutive
        samples the one with the smallest round trip, never one shorter than the wire allows."""
        n = len(samples)
        rtts = np.fromiter((s.host_t1 - s.host_t0 for s in samples), dtype=np.float64, count=n)
        ok = np.ones(n, dtype=bool)
        if self.link is not None and np.median(rtts) >= self.link.min_rtt_s:
            ok = rtts >= self.link.min_rtt_s
        self.short_rtt = int(n - ok.sum())
        groups = min(n, max(self.min_samples, int(math.ceil(self.keep_fraction * n))))
        group = (np.arange(n) * groups) // n
        key = np.where(ok, rtts, np.inf)
        order = np.lexsort((key, group))
        first = np.ones(n, dtype=bool)
        first[1:] = group[order][1:] != group[order][:-1]
        idx = order[first]
        return np.sort(idx[np.isfinite(key[idx])])

    def fit(self) -> bool:
        """Refits gain and offset; False while there are too few samples."""
        samples = list(self._samples)
        if len(samples) < self.min_samples:
            return False
        idx = self.select(samples)
        if len(idx) < self.min_samples:
            return False
        dev = np.fromiter((samples[i].device_time_s for i in idx), dtype=np.float64, count=len(idx))
        host = np.fromiter((samples[i].host_sample for i in idx), dtype=np.float64, count=len(idx))
        if np.ptp(dev) <= 0:
            return False
        mask = np.ones(len(dev), dtype=bool)
        # A robust start (median of pairwise slopes): a few kept samples can still be far off (a
        # device side that lagged just enough to look tight), and a least-squares start tilted by
        # them could make the outlier test drop good samples instead.
        gain, offset = self._theil_sen(dev, host)
        for _ in range(4):
            full = host - (gain * dev + offset)
            mad = float(np.median(np.abs(full[mask] - np.median(full[mask]))))
            sigma = max(1.4826 * mad, 1e-6)
            new_mask = np.abs(full - np.median(full[mask])) <= self.outlier_sigmas * sigma
            if new_mask.sum() < self.min_samples or np.array_equal(new_mask, mask):
                break
            mask = new_mask
            gain, offset, _ = self._lstsq(dev[mask], host[mask])
        gain, offset, resid = self._lstsq(dev[mask], host[mask])
        self.gain, self.offset = gain, offset
        self.residual_s = float(np.sqrt(np.mean(resid**2)))
        self.n_samples = int(mask.sum())
        used = dev[mask]
        self.span_s = float(np.ptp(used))
        sxx = float(np.sum((used - used.mean()) ** 2))
        dof = self.n_samples - 2
        se = float(np.sqrt(np.sum(resid**2) / dof / sxx)) if dof > 0 and sxx > 0 else math.nan
        self.gain_se = max(se, self._block_jackknife_se(used, host[mask]))
        self.fitted = True
        return True

    @staticmethod
    def _block_jackknife_se(dev: np.ndarray, host: np.ndarray, blocks: int = 8) -> float:
        """Standard error of the gain by the delete-a-block jackknife over `blocks` consecutive runs of
        samples (0 when there are too few). The textbook formula assumes independent residuals, but a
        loaded host's scheduling delays drift over seconds: residuals of neighbouring queries were
        correlated (lag-1 0.2-0.6 at load 3) and that formula understated the gain's real error 2-4x
        (a -1.43 ppm error with a 0.46 ppm "standard error"). Deleting whole blocks keeps that drift."""
        n = len(dev)
        if n < 2 * blocks:
            return 0.0
        d0, h0 = float(dev.mean()), float(host.mean())
        dc, hc = dev - d0, host - h0
        gains = np.empty(blocks)
        for k, out in enumerate(np.array_split(np.arange(n), blocks)):
            keep = np.ones(n, dtype=bool)
            keep[out] = False
            x, y = dc[keep], hc[keep]
            x = x - x.mean()
            gains[k] = float(np.dot(x, y - y.mean()) / np.dot(x, x))
        return float(np.sqrt((blocks - 1) / blocks * np.sum((gains - gains.mean()) ** 2)))

    @staticmethod
    def _theil_sen(dev: np.ndarray, host: np.ndarray, max_points: int = 64) -> tuple[float, float]:
        """Median of the pairwise slopes (of at most max_points spread over the samples), and the
        median offset through it."""
        if len(dev) > max_points:
            pick = np.linspace(0, len(dev) - 1, max_points).round().astype(np.intp)
            dev, host = dev[pick], host[pick]
        d0, h0 = float(dev.mean()), float(host.mean())
        dc, hc = dev - d0, host - h0  # centred: epoch host times keep their precision
        i, j = _pairs(len(dev))
        dd = dc[j] - dc[i]
        ok = dd > 0
        if not ok.any():
            return 1.0, h0 - d0
        gain = float(np.median((hc[j] - hc[i])[ok] / dd[ok]))
        return gain, h0 + float(np.median(hc - gain * dc)) - gain * d0

    @staticmethod
    def _lstsq(dev: np.ndarray, host: np.ndarray) -> tuple[float, float, np.ndarray]:
        # Centred so that large epoch host times keep their precision.
        d0, h0 = float(dev.mean()), float(host.mean())
        dc, hc = dev - d0, host - h0
        denom = float(np.dot(dc, dc))
        gain = float(np.dot(dc, hc) / denom) if denom > 0 else 1.0
        offset = h0 - gain * d0
        return gain, offset, hc - gain * dc

    # ------------------------------------------------------------------ conversions

    def _need_fit(self) -> None:
        if not self.fitted:
            raise RuntimeError("the clock model has no fit yet (too few clock samples)")

    def device_to_host(self, t: float) -> float:
        self._need_fit()
        return self.gain * t + self.offset

    def host_to_device(self, t: float) -> float:
        self._need_fit()
        return (t - self.offset) / self.gain

    def _period(self) -> float:
        if not self.frame_period_s:
            raise RuntimeError("the frame period is not known (set_rate not called)")
        return self.frame_period_s

    def frame_to_host_time(self, frame: float) -> float:
        """Host time at which frame `frame` (0-based; fractional = within the frame) began."""
        return self.device_to_host(frame * self._period())

    def host_time_to_frame(self, t: float) -> float:
        """Fractional frame number at host time t (floor gives the frame under way)."""
        return self.host_to_device(t) / self._period()

    def summary(self) -> dict[str, float]:
        return {
            "gain": self.gain,
            "offset": self.offset,
            "residual_us": self.residual_s * 1e6,
            "n_samples": float(self.n_samples),
            "gain_se_ppm": self.gain_se * 1e6,
            "span_s": self.span_s,
            "rejected_rtt": float(self.rejected_rtt),
            "restarts": float(self.restarts),
        }


# ---------------------------------------------------------------------------------------------
# Samples taken early in a frame (strawlab triggerbox, flydra's trigger devices): the frame under way
# has begun but the pulse count has not stepped yet (it steps at a fixed timer mark, e.g. the
# strawlab firmware's OCR1A match 1000 ticks into the frame), so (count + fraction) is exactly one
# frame short for every sample taken before that mark.
# ---------------------------------------------------------------------------------------------
CLASSIFY_TOL = 0.3  # frames: a sample within this of 0 (or 1) frame off the line is clean (or early)
MIN_CLOCK_SAMPLES = 8


@dataclass
class CountCorrection:
    frames: np.ndarray  # corrected (count + fraction) per sample, in frames
    early_fixed: int  # samples found one frame short (count not yet incremented) and corrected
    count_offset: int  # constant offset added to every count (firmware convention)
    mark: float = math.nan  # fraction of the frame at which the count steps, found from the samples
    conflicts: int = 0  # samples whose own offset from the line disagreed with the mark (they were followed)
    note: str = ""  # why nothing was corrected although some samples looked one frame short


def _running_median(x: np.ndarray, window: int) -> np.ndarray:
    """Median of each value's `window` neighbours (odd); near the ends, of the first or last `window`."""
    half = window // 2
    if len(x) <= 2 * half + 1:
        return np.full(len(x), float(np.median(x)))
    med = np.median(np.lib.stride_tricks.sliding_window_view(x, 2 * half + 1), axis=1)
    return np.concatenate([np.full(half, med[0]), med, np.full(half, med[-1])])


def _best_mark(fr: np.ndarray, early: np.ndarray) -> tuple[float, float, int]:
    """Where in the frame samples known early (count not stepped) are best split from those known clean
    above them -> (the last fraction before the split, the first after it, samples on the wrong side)."""
    order = np.argsort(fr, kind="stable")
    f, e = fr[order], early[order]
    # cost of splitting before index k: clean ones below + early ones above
    clean_below = np.concatenate([[0], np.cumsum(~e)])
    early_above = np.concatenate([np.cumsum(e[::-1])[::-1], [0]])
    cost = clean_below + early_above
    k = int(np.argmin(cost))
    lo = f[k - 1] if k > 0 else 0.0
    hi = f[k] if k < len(f) else 1.0
    return float(lo), float(hi), int(cost[k])


def _segment_corrections(fr: np.ndarray, frames: np.ndarray, host: np.ndarray, tight: np.ndarray
                         ) -> tuple[np.ndarray, float, int, str]:
    """One run of samples (time order, count not going back) -> (fix mask, mark, conflicts, note)."""
    n = len(frames)
    none = np.zeros(n, dtype=bool)
    half = n // 2
    df, dh = frames[half:2 * half] - frames[:half], host[half:2 * half] - host[:half]
    ok = df > 0
    if not ok.any():
        return none, math.nan, 0, ""
    a = float(np.median(dh[ok] / df[ok]))  # host seconds per frame: pairs half the run apart
    if not (math.isfinite(a) and a > 0):
        return none, math.nan, 0, ""
    f0, h0 = float(np.median(frames)), float(np.median(host))
    lag = (host - h0) / a - (frames - f0)  # frames the host time says the sample is ahead of its count
    lag -= _running_median(lag, 61)  # against its neighbours: slow drift of the two clocks cancels
    near1, near0 = np.abs(lag - 1.0) < CLASSIFY_TOL, np.abs(lag) < CLASSIFY_TOL
    sure = tight & (near0 | near1)
    if not (sure & near1).any():
        return none, math.nan, 0, ""
    lo, hi, conflicts = _best_mark(fr[sure], near1[sure])
    mark = 0.5 * (lo + hi)
    if conflicts > 0.02 * int(sure.sum()) or mark > 0.5:
        note = (f"{int((sure & near1).sum())} samples look one frame short, but not all below one place in the "
                f"frame (best split {mark:.3f} of the frame, {conflicts} on the wrong side): none corrected")
        return none, mark, conflicts, note
    # Below the step: the count had not stepped, unless the sample itself clearly says otherwise; after
    # it: only a sample clearly one frame short (an interrupt that ran late). Between the last sample
    # known before the step and the first known after it, each sample's own offset decides.
    gap = (fr > lo) & (fr < hi)
    fix = ((fr <= lo) & ~(tight & near0)) | (gap & (lag > 0.5)) | (tight & near1)
    return fix, mark, conflicts, ""


def correct_clock_counts(
    count: np.ndarray, fraction: np.ndarray, host_time: np.ndarray, count_offset: int = 0,
    rtt: np.ndarray | None = None,
) -> CountCorrection:
    """Frame positions (count + count_offset + fraction) of clock samples, with the early-frame error
    fixed from the samples themselves: a line host = a x frames + b (robust: slopes between samples
    half the run apart, offsets against the running median of their neighbours) puts each sample 0
    or 1 frame ahead of its count; those clearly one frame short (with a round trip no longer than the
    median, when `rtt` is given) and those clearly on the line give the mark, the fraction of the
    frame below which the count has not stepped (the split with fewest samples on the wrong side;
    it must have at most 2 % there and lie in the first half of the frame). Every sample below the
    mark then gets count + 1, unless it clearly sits on the line; above it only a sample clearly one
    frame short does. No sample clearly short: nothing changes (a count that steps at the wrap).
    A count going back (the device restarted) starts a new run, handled on its own. count_offset:
    Braid's and the strawlab firmware's counts number the pulse under way from 1 (pass -1 to make
    frame 0 the first pulse) where others count completed pulses (0)."""
    count = np.asarray(count, dtype=np.float64)
    fraction = np.asarray(fraction, dtype=np.float64)
    host = np.asarray(host_time, dtype=np.float64)
    frames = count + count_offset + fraction
    out = frames.copy()
    good = np.isfinite(frames) & np.isfinite(host)
    idx = np.flatnonzero(good)
    idx = idx[np.argsort(host[idx], kind="stable")]
    if rtt is not None:
        r = np.asarray(rtt, dtype=np.float64)[idx]
        tight = r <= np.median(r[np.isfinite(r)]) if np.isfinite(r).any() else np.ones(len(idx), dtype=bool)
    else:
        tight = np.ones(len(idx), dtype=bool)
    cuts = np.flatnonzero(np.diff(frames[idx]) < -1.5) + 1  # the count went back (not just one short): a new run
    fixed, marks, conflicts, notes = 0, [], 0, []
    for seg in np.split(np.arange(len(idx)), cuts):
        if len(seg) < MIN_CLOCK_SAMPLES:
            continue
        j = idx[seg]
        fix, mark, c, note = _segment_corrections(fraction[j], frames[j], host[j], tight[seg])
        out[j[fix]] += 1.0
        fixed += int(fix.sum())
        conflicts += c
        if note:
            notes.append(note)
        elif math.isfinite(mark):
            marks.append(mark)
    return CountCorrection(out, fixed, count_offset, float(np.median(marks)) if marks else math.nan, conflicts,
                           "; ".join(notes))
