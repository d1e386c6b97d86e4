"""Figures of the simulated rig that are not tracking quality (that is flytrack_host.tracking.evaluation):
percentiles of a flat array of latencies."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray


def latency_percentiles_ms(latencies_s: Sequence[float] | NDArray[np.float64]) -> dict[str, float]:
    """P50, P99, max and mean of a flat array of latencies in seconds, in milliseconds (NaN when there
    are none). Not flytrack_host.recording.latency.latency_summary, which splits LATENCY recording rows by part."""
    a = np.asarray(latencies_s, dtype=np.float64)
    a = a[np.isfinite(a)]
    if a.size == 0:
        nan = float("nan")
        return {"p50_ms": nan, "p99_ms": nan, "max_ms": nan, "mean_ms": nan, "n": 0}
    return {
        "p50_ms": float(np.percentile(a, 50) * 1e3),
        "p99_ms": float(np.percentile(a, 99) * 1e3),
        "max_ms": float(a.max() * 1e3),
        "mean_ms": float(a.mean() * 1e3),
        "n": int(a.size),
    }
