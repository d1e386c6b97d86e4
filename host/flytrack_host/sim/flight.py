"""A 3D flight model of several insects in a box arena, with per-frame ground truth.

The behaviour follows what flydra's paper (seed 000) reports for Drosophila: horizontal speed about
0.15 m/s with a standard deviation of 0.07 m/s (§7), straight segments punctuated by saccades, brief
fast turns (figure 3c), flights that stay clear of the walls and sometimes end in a landing on the
floor or a wall, followed by a take-off. Now and then one animal turns towards another, so two
animals pass close: the hard case for data association.

The model is integrated with a fixed small step (at most 2 ms) and sampled at the frame times, so the
trajectories do not depend on the frame rate beyond the sampling. Everything is vectorised over the
animals; the whole run is computed up front (it is small: frames x animals x 3).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

FLYING, APPROACH, LANDED = 0, 1, 2


@dataclass(frozen=True)
class Arena:
    """An axis-aligned box; x along the long axis, z up, the floor at z = 0, centred in x and y."""

    length: float = 1.5  # x, m
    width: float = 0.3  # y, m
    height: float = 0.3  # z, m

    def __post_init__(self) -> None:
        for name in ("length", "width", "height"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0.05 <= v <= 100.0):
                raise ValueError(f"arena {name} must be between 0.05 and 100 m, got {v}")

    @property
    def lo(self) -> F64:
        return np.array([-self.length / 2, -self.width / 2, 0.0])

    @property
    def hi(self) -> F64:
        return np.array([self.length / 2, self.width / 2, self.height])

    @property
    def center(self) -> F64:
        return (self.lo + self.hi) / 2

    def corners(self) -> F64:
        lo, hi = self.lo, self.hi
        return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])

    def contains(self, p: F64, margin: float = 0.0) -> NDArray[np.bool_]:
        p = np.atleast_2d(p)
        return np.all((p >= self.lo + margin) & (p <= self.hi - margin), axis=-1)


@dataclass(frozen=True)
class FlightParams:
    speed_mean: float = 0.15  # m/s, seed 000 §7 (high contrast)
    speed_std: float = 0.07  # m/s, spread between animals and over time
    speed_min: float = 0.04
    speed_max: float = 0.45
    speed_tau_s: float = 0.6  # how fast an animal's speed wanders around its own preference
    wobble_rad_s: float = 0.6  # std of the slow turning of "straight" segments
    wobble_tau_s: float = 0.25
    saccade_rate_hz: float = 0.8  # spontaneous saccades per second
    saccade_rate_rad_s: tuple[float, float] = (14.0, 24.0)  # angular speed during a saccade (800-1400 deg/s)
    saccade_angle_rad: tuple[float, float] = (0.5, 2.0)  # spontaneous turn size
    wall_margin_m: float = 0.03
    lookahead_s: float = 0.3
    pitch_std_rad: float = 0.15
    pitch_tau_s: float = 0.4
    pitch_max_rad: float = 0.7
    land_rate_hz: float = 0.08  # landings per second of flight, per animal
    min_flight_s: float = 1.5  # no landing this soon after a take-off
    landed_s: tuple[float, float] = (0.4, 1.5)
    encounter_rate_hz: float = 0.15  # per animal: turning towards another animal
    encounter_s: tuple[float, float] = (0.4, 0.9)
    # So that every run of a few seconds shows each behaviour at least once: animal 0 lands at a
    # quarter of the run (and takes off again), and at half the run two animals fly at each other.
    scripted_events: bool = True
    body_length_m: float = 0.0025  # Drosophila: about 2.5 mm
    body_width_m: float = 0.0011
    rest_height_m: float = 0.0006  # centre of a landed body above its surface


@dataclass
class GroundTruth:
    """Per-frame truth for every animal. Frame k is at time t[k] = k / fps."""

    fps: float
    arena: Arena
    t: F64  # (F,)
    pos: F64  # (F, n, 3) m
    vel: F64  # (F, n, 3) m/s
    axis: F64  # (F, n, 3) unit body axis, head direction
    landed: NDArray[np.bool_]  # (F, n)
    body_length_m: float
    body_width_m: float
    meta: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return int(self.pos.shape[0])

    @property
    def n_animals(self) -> int:
        return int(self.pos.shape[1])

    def pair_distances(self) -> F64:
        """(F, n, n) distances between animals; the diagonal is +inf."""
        d = np.linalg.norm(self.pos[:, :, None, :] - self.pos[:, None, :, :], axis=-1)
        idx = np.arange(self.n_animals)
        d[:, idx, idx] = np.inf
        return d

    def close_frames(self, distance_m: float) -> NDArray[np.bool_]:
        """(F, n): the animal is within distance_m of another animal at that frame."""
        if self.n_animals < 2:
            return np.zeros(self.landed.shape, dtype=bool)
        return self.pair_distances().min(axis=2) < distance_m

    def horizontal_speed(self) -> F64:
        return np.linalg.norm(self.vel[:, :, :2], axis=-1)


def _wrap(a: F64) -> F64:
    return (a + np.pi) % (2 * np.pi) - np.pi


def _heading(yaw: F64, pitch: F64) -> F64:
    cp = np.cos(pitch)
    return np.stack([cp * np.cos(yaw), cp * np.sin(yaw), np.sin(pitch)], axis=-1)


def simulate_flight(
    n_animals: int,
    seconds: float,
    fps: float,
    seed: int = 0,
    arena: Arena | None = None,
    params: FlightParams | None = None,
    max_step_s: float = 0.002,
) -> GroundTruth:
    """Simulate `n_animals` insects for `seconds` and sample them at `fps`."""
    if n_animals < 1 or n_animals > 200:
        raise ValueError(f"number of animals must be 1..200, got {n_animals}")
    if not (math.isfinite(fps) and 1.0 <= fps <= 10000.0):
        raise ValueError(f"fps must be between 1 and 10000, got {fps}")
    if not (math.isfinite(seconds) and 0.0 < seconds <= 24 * 3600):
        raise ValueError(f"seconds must be positive (and at most a day), got {seconds}")
    arena = arena or Arena()
    p = params or FlightParams()
    rng = np.random.default_rng(seed)
    n = n_animals
    n_frames = int(round(seconds * fps))
    if n_frames < 1:
        raise ValueError(f"{seconds} s at {fps} fps is less than one frame")
    sub = max(1, math.ceil((1.0 / fps) / max_step_s))
    dt = 1.0 / fps / sub

    lo, hi = arena.lo, arena.hi
    m = p.wall_margin_m
    inner_lo, inner_hi = lo + 2 * m, hi - 2 * m
    inner_lo[2], inner_hi[2] = lo[2] + 0.04 * arena.height + m, hi[2] - m
    # Start apart from each other, flying, at places chosen at random inside the inner box.
    pos = np.empty((n, 3))
    for i in range(n):
        for _ in range(200):
            cand = rng.uniform(inner_lo, inner_hi)
            if i == 0 or np.min(np.linalg.norm(pos[:i] - cand, axis=1)) > 0.05:
                break
        pos[i] = cand
    pref_speed = np.clip(rng.normal(p.speed_mean, p.speed_std * 0.75, n), p.speed_min * 1.5, p.speed_max * 0.8)
    speed = pref_speed.copy()
    yaw = rng.uniform(-np.pi, np.pi, n)
    pitch = rng.normal(0.0, p.pitch_std_rad, n)
    pitch_target = np.zeros(n)
    wobble = np.zeros(n)
    mode = np.full(n, FLYING)
    sacc_left = np.zeros(n)
    sacc_rate = np.zeros(n)
    flight_time = rng.uniform(0.0, p.min_flight_s, n)
    landed_left = np.zeros(n)
    land_target = np.zeros((n, 3))
    land_normal = np.zeros((n, 3))
    rest_axis = np.zeros((n, 3))
    pursuit_of = np.full(n, -1)
    pursuit_left = np.zeros(n)

    out_pos = np.empty((n_frames, n, 3))
    out_vel = np.empty((n_frames, n, 3))
    out_axis = np.empty((n_frames, n, 3))
    out_landed = np.empty((n_frames, n), dtype=bool)
    counts = {"saccades": 0, "wall_saccades": 0, "landings": 0, "takeoffs": 0, "encounters": 0}

    def start_saccade(i: int, delta: float) -> None:
        rate = rng.uniform(*p.saccade_rate_rad_s)
        sacc_left[i] = abs(delta) / rate
        sacc_rate[i] = math.copysign(rate, delta)

    def record(k: int) -> None:
        vel = np.where((mode == LANDED)[:, None], 0.0, _heading(yaw, pitch) * speed[:, None])
        out_pos[k] = pos
        out_vel[k] = vel
        ax = _heading(yaw, pitch)
        out_axis[k] = np.where((mode == LANDED)[:, None], rest_axis, ax)
        out_landed[k] = mode == LANDED

    record(0)
    sq = math.sqrt(dt)
    t_now = 0.0
    land_at = 0.25 * seconds if p.scripted_events and seconds >= 3.0 else math.inf
    meet_at = 0.5 * seconds if p.scripted_events and seconds >= 3.0 and n >= 2 else math.inf
    for k in range(1, n_frames):
        for _ in range(sub):
            t_now += dt
            if t_now >= land_at:
                land_at = math.inf
                i = next((a for a in range(n) if mode[a] == FLYING), None)
                if i is not None:
                    _choose_landing(i, pos, arena, rng, land_target, land_normal, p)
                    mode[i] = APPROACH
                    pursuit_of[i] = -1
            if t_now >= meet_at:
                pair = _closest_flying_pair(pos, mode)
                # No two animals in the air: try again a little later (until 80 % of the run).
                meet_at = t_now + 0.2 if pair is None and t_now + 0.2 < 0.8 * seconds else math.inf
                if pair is not None:
                    a, b = pair
                    pursuit_of[a], pursuit_of[b] = b, a
                    pursuit_left[a] = pursuit_left[b] = 3.0
                    speed[a] = max(speed[a], p.speed_mean)
                    speed[b] = max(speed[b], p.speed_mean)
                    counts["encounters"] += 1
            flying = mode != LANDED
            # Speed: each animal wanders around its own preferred speed.
            speed += np.where(
                flying,
                (np.where(pursuit_of >= 0, np.maximum(pref_speed, 1.4 * p.speed_mean), pref_speed) - speed)
                * dt / p.speed_tau_s
                + p.speed_std * 0.65 * math.sqrt(2 / p.speed_tau_s) * sq * rng.standard_normal(n),
                0.0,
            )
            np.clip(speed, p.speed_min, p.speed_max, out=speed)
            # Yaw: saccade in progress, else a small wobble.
            in_sacc = sacc_left > 0
            wobble += -wobble * dt / p.wobble_tau_s + p.wobble_rad_s * math.sqrt(
                2 / p.wobble_tau_s
            ) * sq * rng.standard_normal(n)
            yaw += np.where(in_sacc, sacc_rate, wobble) * dt * flying
            sacc_left = np.maximum(sacc_left - dt, 0.0)
            pitch += (pitch_target - pitch) * dt / p.pitch_tau_s + p.pitch_std_rad * math.sqrt(
                2 / p.pitch_tau_s
            ) * sq * rng.standard_normal(n) * flying
            np.clip(pitch, -p.pitch_max_rad, p.pitch_max_rad, out=pitch)
            flight_time += dt * flying

            for i in range(n):
                if mode[i] == LANDED:
                    landed_left[i] -= dt
                    if landed_left[i] <= 0:  # take off, away from the surface
                        tang = rng.normal(size=3)
                        tang -= land_normal[i] * (tang @ land_normal[i])
                        tang /= np.linalg.norm(tang) + 1e-12
                        d = 0.7 * land_normal[i] + 0.7 * tang
                        d /= np.linalg.norm(d)
                        yaw[i] = math.atan2(d[1], d[0])
                        pitch[i] = float(np.clip(math.asin(d[2]), -p.pitch_max_rad, p.pitch_max_rad))
                        pitch_target[i] = 0.0
                        speed[i] = p.speed_min * 1.5
                        mode[i] = FLYING
                        flight_time[i] = 0.0
                        counts["takeoffs"] += 1
                    continue
                if mode[i] == APPROACH:
                    to = land_target[i] - pos[i]
                    dist = float(np.linalg.norm(to))
                    if dist < max(speed[i] * dt * 1.5, 0.002):
                        pos[i] = land_target[i]
                        mode[i] = LANDED
                        landed_left[i] = rng.uniform(*p.landed_s)
                        h = _heading(yaw[i : i + 1], np.zeros(1))[0]
                        h -= land_normal[i] * (h @ land_normal[i])
                        nh = np.linalg.norm(h)
                        rest_axis[i] = h / nh if nh > 1e-6 else np.array([1.0, 0.0, 0.0])
                        counts["landings"] += 1
                        continue
                    # Steer straight at the landing spot, slowing down.
                    yaw[i] = math.atan2(to[1], to[0])
                    pitch[i] = math.asin(np.clip(to[2] / dist, -1, 1))
                    speed[i] = max(p.speed_min, min(speed[i], 0.1, 2.0 * dist + p.speed_min))
                    sacc_left[i] = 0.0
                    continue
                # FLYING: decide saccades, landings, encounters.
                h = _heading(yaw[i : i + 1], pitch[i : i + 1])[0]
                ahead = pos[i] + h * speed[i] * p.lookahead_s
                near_wall_xy = np.any((ahead[:2] < lo[:2] + m) | (ahead[:2] > hi[:2] - m))
                if near_wall_xy and sacc_left[i] <= 0:
                    goal = rng.uniform(inner_lo, inner_hi)
                    want = math.atan2(goal[1] - pos[i, 1], goal[0] - pos[i, 0])
                    start_saccade(i, float(_wrap(np.array(want - yaw[i]))))
                    counts["wall_saccades"] += 1
                elif sacc_left[i] <= 0 and rng.random() < p.saccade_rate_hz * dt:
                    ang = rng.uniform(*p.saccade_angle_rad) * rng.choice((-1.0, 1.0))
                    start_saccade(i, ang)
                    counts["saccades"] += 1
                if ahead[2] < lo[2] + m + 0.02:
                    pitch_target[i] = 0.35
                elif ahead[2] > hi[2] - m:
                    pitch_target[i] = -0.35
                else:
                    pitch_target[i] = 0.0
                # Pursuit: turn towards another animal for a moment, which makes close passes.
                if pursuit_of[i] >= 0:
                    pursuit_left[i] -= dt
                    j = pursuit_of[i]
                    if pursuit_left[i] <= 0 or mode[j] == LANDED or np.linalg.norm(pos[j] - pos[i]) < 0.01:
                        pursuit_of[i] = -1
                    elif sacc_left[i] <= 0:
                        to = pos[j] - pos[i]
                        want = math.atan2(to[1], to[0])
                        err = float(_wrap(np.array(want - yaw[i])))
                        yaw[i] += float(np.clip(err, -8.0 * dt, 8.0 * dt))
                        pitch_target[i] = float(np.clip(math.atan2(to[2], np.hypot(to[0], to[1])), -0.5, 0.5))
                elif n > 1 and rng.random() < p.encounter_rate_hz * dt:
                    others = [j for j in range(n) if j != i and mode[j] != LANDED]
                    if others:
                        pursuit_of[i] = int(rng.choice(others))
                        pursuit_left[i] = rng.uniform(*p.encounter_s)
                        counts["encounters"] += 1
                if pursuit_of[i] < 0 and flight_time[i] > p.min_flight_s and rng.random() < p.land_rate_hz * dt:
                    _choose_landing(i, pos, arena, rng, land_target, land_normal, p)
                    mode[i] = APPROACH
                    pursuit_of[i] = -1

            h = _heading(yaw, pitch)
            moving = (mode != LANDED)[:, None]
            new = pos + h * speed[:, None] * dt * moving
            # The walls are solid: an animal that would pass one is stopped at it and turned back.
            low_hit = new < lo + 1e-4
            high_hit = new > hi - 1e-4
            hit = (low_hit | high_hit) & moving & (mode == FLYING)[:, None]
            if np.any(hit):
                for i in np.nonzero(hit.any(axis=1))[0]:
                    d = h[i].copy()
                    d[hit[i]] *= -1
                    yaw[i] = math.atan2(d[1], d[0])
                    pitch[i] = math.asin(np.clip(d[2], -1, 1))
                    sacc_left[i] = 0.0
            pos = np.clip(new, lo + 1e-4, hi - 1e-4)
        record(k)

    gt = GroundTruth(
        fps=float(fps),
        arena=arena,
        t=np.arange(n_frames) / fps,
        pos=out_pos,
        vel=out_vel,
        axis=out_axis,
        landed=out_landed,
        body_length_m=p.body_length_m,
        body_width_m=p.body_width_m,
        meta={"seed": seed, "step_s": dt, **counts},
    )
    return gt


def _closest_flying_pair(pos: F64, mode: NDArray[np.int_]) -> tuple[int, int] | None:
    idx = [i for i in range(len(mode)) if mode[i] == FLYING]
    best: tuple[float, int, int] | None = None
    for x in idx:
        for y in idx:
            if x < y:
                d = float(np.linalg.norm(pos[x] - pos[y]))
                if best is None or d < best[0]:
                    best = (d, x, y)
    return None if best is None else (best[1], best[2])


def _choose_landing(
    i: int,
    pos: F64,
    arena: Arena,
    rng: np.random.Generator,
    land_target: F64,
    land_normal: F64,
    p: FlightParams,
) -> None:
    """Pick a landing spot on the floor, the ceiling or a long wall near the animal, clear of the edges."""
    lo, hi = arena.lo, arena.hi
    dists = {"floor": pos[i, 2] - lo[2], "ceiling": hi[2] - pos[i, 2], "y_lo": pos[i, 1] - lo[1],
             "y_hi": hi[1] - pos[i, 1]}
    surface = min(dists, key=dists.get) if rng.random() < 0.7 else str(rng.choice(list(dists)))
    edge = 0.02
    spot = np.clip(pos[i] + rng.normal(0.0, 0.03, 3), lo + edge, hi - edge)
    normal = np.zeros(3)
    if surface == "floor":
        spot[2] = lo[2] + p.rest_height_m
        normal[2] = 1.0
    elif surface == "ceiling":
        spot[2] = hi[2] - p.rest_height_m
        normal[2] = -1.0
    elif surface == "y_lo":
        spot[1] = lo[1] + p.rest_height_m
        normal[1] = 1.0
    else:
        spot[1] = hi[1] - p.rest_height_m
        normal[1] = -1.0
    land_target[i] = spot
    land_normal[i] = normal
