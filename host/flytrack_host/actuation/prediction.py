"""Latency compensation: which trigger frame an action can still reach, and the state at that frame.

A rule is judged on the state predicted to the frame its action lands on, not on the frame just
estimated: the estimate of frame F exists only some time after F's trigger pulse (the measured
trigger-to-estimate latency), and the action needs its device's own time on top (a PULSE must reach
the firmware before its frame starts). Without prediction a pulse lands at least one frame after the
frame the condition became true on; with it, on that frame (to within the tracker's error).
"""

from __future__ import annotations

import math

import numpy as np


def reachable_frame(frame: int, frame_time: float, now: float, lead_s: float, period_s: float) -> int:
    """The first trigger frame after `frame` that starts after `now + lead_s` (the action, sent now,
    takes `lead_s` to take effect). Without a frame time (no clock yet): the next frame."""
    if not (math.isfinite(frame_time) and math.isfinite(now)) or period_s <= 0:
        return frame + 1
    k = math.floor((now + lead_s - frame_time) / period_s) + 1
    return frame + max(1, k)


def predict_states(states: np.ndarray, dt: float, vel: np.ndarray | None = None) -> np.ndarray:
    """Constant-velocity prediction of (N, 6) [x y z vx vy vz] states `dt` seconds ahead (the
    tracker's own motion model). `vel` (N, 3): the velocity to move the positions with (the rule
    evaluator passes each object's last position step, which follows a change of speed sooner than
    the filter's velocity state); the predicted states keep the tracker's velocity either way, for
    the conditions on speed."""
    out = np.array(states, dtype=np.float64, copy=True).reshape(-1, 6)
    out[:, :3] += (out[:, 3:6] if vel is None else np.asarray(vel, dtype=np.float64).reshape(-1, 3)) * dt
    return out
