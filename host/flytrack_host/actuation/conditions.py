"""A rule's condition on N objects at once: positions and velocities in, one bool per object out.

Everything is NumPy over the objects of one frame (a few to a few tens), so a rule costs a few
microseconds a frame whatever the number of objects.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from flytrack_host.actuation.rules import Condition, Region, Target, _Range


def _in_range(v: np.ndarray, r: _Range) -> np.ndarray:
    return (v >= r.min) & (v <= r.max)


def point_in_polygon(xy: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd rule, (N, 2) points against one (M, 2) polygon."""
    x, y = xy[:, 0:1], xy[:, 1:2]
    x0, y0 = poly[:, 0], poly[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    crosses = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xi = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return np.sum(crosses & (x < xi), axis=1) % 2 == 1


def region_mask(region: Region, pos: np.ndarray) -> np.ndarray:
    if region.box is not None:
        lo, hi = np.asarray(region.box.min), np.asarray(region.box.max)
        return np.all((pos >= lo) & (pos <= hi), axis=1)
    if region.sphere is not None:
        d = pos - np.asarray(region.sphere.center)
        return np.einsum("ij,ij->i", d, d) <= region.sphere.radius**2
    if region.cylinder is not None:
        c = region.cylinder
        d = pos[:, :2] - np.asarray(c.center)
        return (np.einsum("ij,ij->i", d, d) <= c.radius**2) & _in_range(pos[:, 2], c.z)
    p = region.polygon
    assert p is not None
    return point_in_polygon(pos[:, :2], np.asarray(p.points, dtype=float)) & _in_range(pos[:, 2], p.z)


def _offset(t: Target, pos: np.ndarray) -> np.ndarray:
    """Vector from the target to each object (horizontal only for a post)."""
    if t.point is not None:
        return pos - np.asarray(t.point)
    d = pos.copy()
    d[:, :2] -= np.asarray(t.post)
    d[:, 2] = 0.0
    return d


def distance(t: Target, pos: np.ndarray) -> np.ndarray:
    return np.linalg.norm(_offset(t, pos), axis=1)


def closing_speed(t: Target, pos: np.ndarray, vel: np.ndarray) -> np.ndarray:
    """Speed towards the target (m/s): minus the rate of change of the distance."""
    d = _offset(t, pos)
    v = vel.copy()
    if t.post is not None:
        v[:, 2] = 0.0
    n = np.linalg.norm(d, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = -np.einsum("ij,ij->i", d, v) / n
    return np.where(n > 0, out, 0.0)


def turn_rate_deg_s(vel_prev: np.ndarray, vel: np.ndarray, dt: float | np.ndarray) -> np.ndarray:
    """Angle between successive velocity vectors per second (NaN where either is ~zero or dt is 0)."""
    a = np.linalg.norm(vel_prev, axis=1)
    b = np.linalg.norm(vel, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cos = np.einsum("ij,ij->i", vel_prev, vel) / (a * b)
        ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) / dt
    return np.where((a > 1e-6) & (b > 1e-6) & (np.asarray(dt) > 0), ang, np.nan)


def condition_mask(c: Condition, pos: np.ndarray, vel: np.ndarray, turn: np.ndarray | None = None) -> np.ndarray:
    """True where every given part of the condition holds. NaN states are never true. (One call of
    `compile_condition`, which the rule engine keeps per rule.)"""
    return compile_condition(c)(pos, vel, turn)


Mask = Callable[[np.ndarray, np.ndarray, "np.ndarray | None"], np.ndarray]


def _compile_region(region: Region) -> Callable[[np.ndarray], np.ndarray]:
    if region.box is not None:
        lo, hi = np.asarray(region.box.min, float), np.asarray(region.box.max, float)
        return lambda pos: ((pos >= lo) & (pos <= hi)).all(axis=1)
    return lambda pos: region_mask(region, pos)


def compile_condition(c: Condition) -> Mask:
    """`condition_mask` for one condition with its constants made once (the per-frame call is a few
    NumPy operations on the frame's objects)."""
    parts: list[Callable[[np.ndarray, np.ndarray, np.ndarray | None], np.ndarray]] = []
    if c.inside is not None:
        f_in = _compile_region(c.inside)
        parts.append(lambda pos, vel, turn: f_in(pos))
    if c.outside is not None:
        f_out = _compile_region(c.outside)
        parts.append(lambda pos, vel, turn: ~f_out(pos))
    rest = c.model_copy(update={"inside": None, "outside": None})
    others = any(getattr(rest, k) is not None for k in ("speed_m_s", "altitude_m", "distance_m",
                                                         "closing_speed_m_s", "turn_rate_deg_s"))
    if others:
        parts.append(lambda pos, vel, turn: _others(rest, pos, vel, turn))

    def mask(pos: np.ndarray, vel: np.ndarray, turn: np.ndarray | None = None) -> np.ndarray:
        ok = np.isfinite(pos).all(axis=1) & np.isfinite(vel).all(axis=1)
        for p in parts:
            ok &= p(pos, vel, turn)
        return ok

    return mask


def _others(c: Condition, pos: np.ndarray, vel: np.ndarray, turn: np.ndarray | None) -> np.ndarray:
    ok = np.ones(len(pos), dtype=bool)
    if c.speed_m_s is not None:
        ok &= _in_range(np.linalg.norm(vel, axis=1), c.speed_m_s)
    if c.altitude_m is not None:
        ok &= _in_range(pos[:, 2], c.altitude_m)
    if c.distance_m is not None:
        d = distance(c.distance_m, pos)
        ok &= (d >= c.distance_m.min) & (d <= c.distance_m.max)
    if c.closing_speed_m_s is not None:
        s = closing_speed(c.closing_speed_m_s, pos, vel)
        ok &= (s >= c.closing_speed_m_s.min) & (s <= c.closing_speed_m_s.max)
    if c.turn_rate_deg_s is not None:
        tr = turn if turn is not None else np.full(len(pos), np.nan)
        ok &= np.isfinite(tr) & _in_range(np.nan_to_num(tr, nan=0.0), c.turn_rate_deg_s)
    return ok
