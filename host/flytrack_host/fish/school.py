"""Synthetic schools with ground truth: fish of the shape model swimming in the 0.61 x 0.30 x 0.40 m tank,
coasting with a tail beat, turning, doing C-starts and S-starts, and crossing each other in groups of two
or three at different depths (occlusions in the top view, as in seed 004 §5).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from flytrack_host.fish.shape import heading_from_angles, make_state, p_for_length

F64 = NDArray[np.float64]
TANK = np.array([0.61, 0.30, 0.40])


@dataclass
class Event:
    fish: int
    kind: str  # "C-start", "S-start", "turn"
    frame: int  # onset frame (first frame of the bend)


@dataclass
class School:
    truth: F64  # (T, F, 11): r, h, p per frame and fish
    fps: float
    length: float
    events: list[Event] = field(default_factory=list)
    groups: list[list[int]] = field(default_factory=list)  # fish that cross together


def _bend_c(x: F64) -> F64:
    """C shape (one bend, same sign along the body) scaled by x in [0, 1]."""
    return np.stack([0.55 * x, 0.0 * x, -0.05 * x], axis=-1)  # f2'' > 0 along the whole body


def _bend_s(x: F64) -> F64:
    """S shape (inflection near mid-body) scaled by x."""
    return np.stack([0.70 * x, -0.52 * x, 0.0 * x], axis=-1)  # f2'' changes sign at s = 0.45


def make_school(n_fish: int, n_frames: int = 200, fps: float = 250.0, length: float = 0.05, seed: int = 0,
                speed: float = 0.15, cross_frame: int | None = None) -> School:
    """Fish in crossing groups of up to three (depths 3 cm apart); fish 0 does a C-start, fish 1 an S-start,
    fish 2 a coasting turn (a single fish does all three in turn)."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / fps
    sizes: list[int] = []
    left = n_fish
    while left > 0:
        k = 3 if left >= 5 or left == 3 else min(2, left)
        sizes.append(k)
        left -= k
    centres = [(0.305, 0.15), (0.17, 0.11), (0.44, 0.19), (0.17, 0.20), (0.44, 0.10)]
    # fish start apart (a clear view for the model) and cross later
    t_cross = cross_frame if cross_frame is not None else max(int(0.35 * n_frames), 60)
    groups: list[list[int]] = []
    yaw0 = np.zeros(n_fish)
    start = np.zeros((n_fish, 3))
    fi = 0
    for g, k in enumerate(sizes):
        cx, cy = centres[g % len(centres)]
        # headings kept >= 50 degrees away from the side camera's axis (y) so each fish shows its length
        # in the side view at the start, as the seed's model generation needs
        # and at least 80 degrees apart, so they start apart and meet only at the crossing
        dirs = [0.0, 220.0, 140.0] if k == 3 else [30.0, 150.0]
        flip = 180.0 * rng.integers(0, 2)
        members = []
        tc = t_cross + 12 * g  # groups cross at different times
        for j in range(k):
            yaw = np.deg2rad(dirs[j] + flip + rng.uniform(-8, 8))
            # a depth of its own per fish, so the side view starts clear (the seed's model needs it)
            z = 0.20 + (fi - (n_fish - 1) / 2) * min(0.03, 0.24 / max(n_fish, 1)) + rng.uniform(-0.003, 0.003)
            h = heading_from_angles(yaw, 0.0)
            start[fi] = np.array([cx, cy, z]) - h * speed * tc * dt
            yaw0[fi] = yaw
            members.append(fi)
            fi += 1
        groups.append(members)
    # per-frame yaw rate (rad/s), speed (m/s), pitch (rad), bend (p3..p5 as fractions of the length)
    T = n_frames
    t = np.arange(T) * dt
    yaw_rate = np.zeros((n_fish, T))
    spd = np.full((n_fish, T), speed)
    bend = np.zeros((n_fish, T, 3))
    events: list[Event] = []
    phase = rng.uniform(0, 2 * np.pi, n_fish)
    for f in range(n_fish):
        # coasting tail beat: a small travelling wave, stronger at the tail
        w = 2 * np.pi * 5.0
        bend[f, :, 0] += 0.03 * np.sin(w * t + phase[f])
        bend[f, :, 1] += 0.05 * np.sin(w * t + phase[f] - 1.2)
        bend[f, :, 2] += -0.03 * np.sin(w * t + phase[f] - 2.0)
    def c_start(f: int, k0: int, sign: float) -> None:
        n1, n2 = 9, 12  # bend in 36 ms, straighten in 48 ms (fast starts take < 100 ms)
        if k0 + n1 + n2 >= T:
            return
        x = np.concatenate([np.sin(np.linspace(0, np.pi / 2, n1)), np.cos(np.linspace(0, np.pi / 2, n2))])
        bend[f, k0:k0 + n1 + n2] += sign * _bend_c(x)
        yaw_rate[f, k0:k0 + n1 + n2] += sign * np.deg2rad(90) / ((n1 + n2) * dt)
        spd[f, k0 + n1:] = np.maximum(spd[f, k0 + n1:], 0.35)
        events.append(Event(f, "C-start", k0))
    def s_start(f: int, k0: int, sign: float) -> None:
        n1, n2 = 8, 12
        if k0 + n1 + n2 >= T:
            return
        x = np.concatenate([np.sin(np.linspace(0, np.pi / 2, n1)), np.cos(np.linspace(0, np.pi / 2, n2))])
        bend[f, k0:k0 + n1 + n2] += sign * _bend_s(x)
        yaw_rate[f, k0:k0 + n1 + n2] += sign * np.deg2rad(15) / ((n1 + n2) * dt)
        spd[f, k0 + n1:] = np.maximum(spd[f, k0 + n1:], 0.35)
        events.append(Event(f, "S-start", k0))
    def turn(f: int, k0: int, sign: float) -> None:
        n = min(40, T - k0 - 1)
        if n < 10:
            return
        x = np.sin(np.linspace(0, np.pi, n))
        bend[f, k0:k0 + n, 0] += sign * 0.12 * x
        yaw_rate[f, k0:k0 + n] += sign * np.deg2rad(45) / (n * dt) * x / x.mean()
        events.append(Event(f, "turn", k0))
    after = t_cross + 30
    if n_fish == 1:
        turn(0, int(0.15 * T), 1.0)
        c_start(0, int(0.45 * T), 1.0)
        s_start(0, int(0.75 * T), -1.0)
    else:
        c_start(0, after + 12, 1.0)
        s_start(1, after + 24, -1.0)
        if n_fish > 2:
            turn(2, int(0.1 * T), 1.0)
    truth = np.zeros((T, n_fish, 11))
    for f in range(n_fish):
        yaw = yaw0[f] + np.concatenate([[0.0], np.cumsum(yaw_rate[f, :-1] * dt)])
        pitch = 0.06 * np.sin(2 * np.pi * 0.8 * t + phase[f])
        h = heading_from_angles(yaw, pitch)
        r = start[f] + np.concatenate([np.zeros((1, 3)), np.cumsum(h[:-1] * (spd[f, :-1] * dt)[:, None], axis=0)])
        p = p_for_length(bend[f], length)
        truth[:, f] = make_state(r, h, p)
    events.sort(key=lambda e: (e.frame, e.fish))
    return School(truth=truth, fps=fps, length=length, events=events, groups=groups)
