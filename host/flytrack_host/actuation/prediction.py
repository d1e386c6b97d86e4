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
    """Constant-velocity prediction of (N, 6) [x y z vx vy vz] states `dt` seconds ahead. `vel`
    (N, 3): the velocity to move the positions with (the rule evaluator passes `StepVelocities`,
    which follow a change of speed sooner than the filter's velocity state); the predicted states
    keep the tracker's velocity either way, for the conditions on speed."""
    out = np.array(states, dtype=np.float64, copy=True).reshape(-1, 6)
    out[:, :3] += (out[:, 3:6] if vel is None else np.asarray(vel, dtype=np.float64).reshape(-1, 3)) * dt
    return out


STEP_VELOCITY_TOLERANCE_M_S = 1.0  # the last position step predicts only this close to the filter's velocity


class StepVelocities:
    """Per object, the velocity to predict with: its estimate's last step (position now minus at the
    previous frame, over one period) when it was tracked on the previous frame, else the tracker's
    velocity. The filter's velocity lags a change of speed by several frames (seed 0's decelerating
    entry: -0.101 m/s against a true -0.073, its pulse 2 frames early) while its position follows the
    cameras within a frame; over 23 entries of 6 recorded demo runs (seeds 0-4) the frame error went
    from -2..+1 to 0. A step further than `STEP_VELOCITY_TOLERANCE_M_S` from the filter's velocity is a
    jump of the estimate (a new association), not flight: the filter's velocity then."""

    def __init__(self, period_s: float):
        self.period_s = period_s
        self.reset()

    def reset(self) -> None:
        self._frame = -2
        self._ids: list[int] = []  # the previous frame's ids, in its order, and their positions
        self._pos = np.zeros((0, 3))
        self._vel = np.zeros((0, 3))

    def __call__(self, frame: int, ids: np.ndarray, states: np.ndarray) -> np.ndarray:
        """(N, 3) velocities for this frame's ids (N,) and states (N, 6); remembers this frame."""
        # Few NumPy calls: this runs on the tracking thread for every frame, before a firing's commands
        # are queued (each call costs about a microsecond whatever the number of objects).
        id_list = (ids.tolist() if isinstance(ids, np.ndarray) and ids.dtype == np.int64
                   else np.asarray(ids, dtype=np.int64).tolist())
        if not (isinstance(states, np.ndarray) and states.dtype == np.float64 and states.ndim == 2):
            states = np.asarray(states, dtype=np.float64).reshape(-1, 6)
        if frame == self._frame and id_list == self._ids:
            return self._vel.copy()  # the same frame again (a second caller)
        vel = states[:, 3:6]
        pos = states[:, :3]
        if self._frame == frame - 1 and id_list and self._ids:
            if id_list == self._ids:  # the same objects in the same order: the common case
                prev = self._pos
            else:
                where = {oid: i for i, oid in enumerate(self._ids)}
                prev = np.full((len(id_list), 3), np.nan)
                for i, oid in enumerate(id_list):
                    j = where.get(oid)
                    if j is not None:
                        prev[i] = self._pos[j]
            step = (pos - prev) / self.period_s
            d = step - vel
            # NaN (no previous position) fails the comparison: the filter's velocity then.
            ok = (d * d).sum(axis=1) <= STEP_VELOCITY_TOLERANCE_M_S**2
            vel = np.where(ok[:, None], step, vel)
        else:
            vel = vel.copy()
        self._ids, self._pos = id_list, pos.copy()
        self._frame, self._vel = frame, vel
        return vel.copy()
