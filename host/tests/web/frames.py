"""Synthetic tracked frames for the live-output tests and the benchmark (no tracker needed)."""

from __future__ import annotations

import numpy as np

from flytrack_host.tracking.types import Estimate, FrameResult


def make_result(frame: int, n: int = 3, born: list[int] | None = None, died: list[int] | None = None,
                first_id: int = 1, t: float | None = None) -> FrameResult:
    """n targets on circles; fresh arrays per frame, as the tracker gives."""
    tt = frame * 0.01 if t is None else t
    ests = []
    for k in range(n):
        a = tt + k
        state = np.array([0.1 * np.cos(a), 0.1 * np.sin(a), 0.2 + 0.01 * k, -0.1 * np.sin(a), 0.1 * np.cos(a), 0.0])
        cov = np.diag([1e-6, 2e-6, 3e-6, 1e-3, 2e-3, 3e-3]) + 1e-9
        ests.append(Estimate(obj_id=first_id + k, state=state, covariance=cov, n_cameras=3))
    return FrameResult(trigger_frame=frame, timestamp=tt, estimates=ests, born=list(born or []),
                       died=list(died or []))
