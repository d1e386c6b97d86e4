"""Latency instrumentation: for every tracked frame, trigger time -> estimate time and its parts.

Parts: arrival (trigger -> the last camera's packet of the frame reached the host) and tracking
(that moment -> the estimate was ready). Times are host clock seconds; the trigger time comes from
the trigger clock model. Each frame gives one LATENCY row (kept in the recording); a fixed-bin
histogram (0.1 ms bins up to 1 s) gives P50, P99 and max without keeping every value in memory.
Values of 1 s or more are not folded into the last bin: they are kept exactly (up to
`OVERFLOW_KEEP` of them), counted (`<part>_overflow`), and a percentile that falls among them is
computed from them, so an overloaded or stalled run reports its real latency.
"""

from __future__ import annotations

import math

import numpy as np

from flytrack_host.recording.schema import LATENCY

BIN_MS = 0.1
MAX_MS = 1000.0
PARTS = ("total", "arrival", "tracking")
OVERFLOW_KEEP = 200_000  # exact values kept past the histogram's end (per part)


def latency_summary(lat: np.ndarray) -> dict[str, float]:
    """P50/P99/max (ms) of each part, from LATENCY rows (exact percentiles)."""
    out: dict[str, float] = {"n": float(len(lat))}
    if len(lat) == 0:
        return out
    parts = {
        "total": lat["estimate_time"] - lat["trigger_time"],
        "arrival": lat["last_arrival"] - lat["trigger_time"],
        "tracking": lat["estimate_time"] - lat["last_arrival"],
    }
    for key, v in parts.items():
        v = v[np.isfinite(v)] * 1e3
        if len(v) == 0:
            continue
        out[f"{key}_p50_ms"] = float(np.percentile(v, 50))
        out[f"{key}_p99_ms"] = float(np.percentile(v, 99))
        out[f"{key}_max_ms"] = float(v.max())
    return out


def latency_histogram(lat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Histogram (counts, bin edges in ms) of trigger -> estimate; values of 1 s or more are left out
    (LatencyStats counts them as overflow)."""
    v = (lat["estimate_time"] - lat["trigger_time"]) * 1e3
    v = v[np.isfinite(v)]
    edges = np.arange(0.0, MAX_MS + BIN_MS / 2, BIN_MS)
    counts, _ = np.histogram(np.clip(v[v < MAX_MS], 0.0, MAX_MS - BIN_MS / 2), bins=edges)
    return counts.astype(np.int64), edges


class LatencyStats:
    """Running histograms of the three parts, fed one frame at a time from the tracking thread."""

    def __init__(self) -> None:
        n = int(round(MAX_MS / BIN_MS))
        self.counts = {p: np.zeros(n, dtype=np.int64) for p in PARTS}
        self.max_ms = dict.fromkeys(PARTS, 0.0)
        self.overflow: dict[str, list[float]] = {p: [] for p in PARTS}
        self.overflow_n = dict.fromkeys(PARTS, 0)
        self.n = 0

    def _over(self, part: str, ms: np.ndarray | list[float]) -> None:
        self.overflow_n[part] += len(ms)
        keep = self.overflow[part]
        room = OVERFLOW_KEEP - len(keep)
        if room > 0:
            keep.extend(float(x) for x in ms[:room])

    def row(self, trigger_frame: int, trigger_time: float, first_arrival: float, last_arrival: float,
            estimate_time: float, n_cameras: int, n_missing: int) -> np.ndarray:
        """Account one frame; returns its LATENCY row for the recording."""
        self.n += 1
        vals = {
            "total": estimate_time - trigger_time,
            "arrival": last_arrival - trigger_time,
            "tracking": estimate_time - last_arrival,
        }
        n_bins = len(self.counts["total"])
        for p, v in vals.items():
            if math.isfinite(v):
                ms = v * 1e3
                self.max_ms[p] = max(self.max_ms[p], ms)
                if ms >= MAX_MS:
                    self._over(p, [ms])
                else:
                    self.counts[p][min(max(int(ms / BIN_MS), 0), n_bins - 1)] += 1
        r = np.zeros(1, dtype=LATENCY)
        r[0] = (trigger_frame, trigger_time, first_arrival, last_arrival, estimate_time, n_cameras, n_missing)
        return r

    def add_rows(self, lat: np.ndarray) -> None:
        """Account many LATENCY rows at once (finalising a recording chunk by chunk)."""
        self.n += len(lat)
        vals = {
            "total": lat["estimate_time"] - lat["trigger_time"],
            "arrival": lat["last_arrival"] - lat["trigger_time"],
            "tracking": lat["estimate_time"] - lat["last_arrival"],
        }
        n_bins = len(self.counts["total"])
        for p, v in vals.items():
            ms = v[np.isfinite(v)] * 1e3
            if len(ms):
                self.max_ms[p] = max(self.max_ms[p], float(ms.max()))
                over = ms >= MAX_MS
                if over.any():
                    self._over(p, ms[over])
                    ms = ms[~over]
                idx = np.clip((ms / BIN_MS).astype(np.int64), 0, n_bins - 1)
                self.counts[p] += np.bincount(idx, minlength=n_bins)

    def histogram(self) -> tuple[np.ndarray, np.ndarray]:
        """(counts, bin edges in ms) of trigger -> estimate, as `latency_histogram` gives."""
        return self.counts["total"].copy(), np.arange(0.0, MAX_MS + BIN_MS / 2, BIN_MS)

    def percentile(self, part: str, q: float) -> float:
        return histogram_percentile(self.counts[part], self.overflow[part], q, self.overflow_n[part],
                                    self.max_ms[part])

    def summary(self) -> dict[str, float]:
        out: dict[str, float] = {"n": float(self.n)}
        for p in PARTS:
            if self.counts[p].sum() or self.overflow_n[p]:
                out[f"{p}_p50_ms"] = self.percentile(p, 50)
                out[f"{p}_p99_ms"] = self.percentile(p, 99)
                out[f"{p}_max_ms"] = self.max_ms[p]
                out[f"{p}_overflow"] = float(self.overflow_n[p])
        return out

    def format(self) -> str:
        s = self.summary()
        if self.n == 0 or "total_p50_ms" not in s:
            return "latency: no tracked frames"
        lines = [f"latency over {self.n} frames (trigger -> estimate and its parts), ms:"]
        for p in PARTS:
            if f"{p}_p50_ms" in s:
                over = int(s[f"{p}_overflow"])
                lines.append(f"  {p:9s} P50 {s[f'{p}_p50_ms']:8.2f}  P99 {s[f'{p}_p99_ms']:8.2f}  "
                             f"max {s[f'{p}_max_ms']:8.2f}"
                             + (f"  ({over} frames at {MAX_MS / 1e3:g} s or more)" if over else ""))
        return "\n".join(lines)


def histogram_percentile(counts: np.ndarray, over_ms: list[float], q: float, n_over: int | None = None,
                         max_ms: float = math.inf) -> float:
    """The q-th percentile (ms) of a latency histogram: `counts` per BIN_MS bin from 0, and the values of
    MAX_MS or more kept exactly in `over_ms` (`n_over` of them in all, when not all were kept). A rank
    among the bins gives its bin's middle (at most `max_ms`, the largest value seen)."""
    in_range = int(np.sum(counts))
    n_over = len(over_ms) if n_over is None else n_over
    total = in_range + n_over
    if total == 0:
        return math.nan
    rank = max(1, math.ceil(q / 100.0 * total))
    if rank > in_range:  # among the values of 1 s or more: exact, from the kept ones
        kept = sorted(over_ms)
        return kept[min(rank - in_range, len(kept)) - 1]
    k = int(np.searchsorted(np.cumsum(counts), rank))
    return min((k + 0.5) * BIN_MS, max_ms)
