"""The goals the simulated rig is held to (GitHub issue 7), checked against a run's figures."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class GoalCheck:
    name: str
    goal: str
    measured: float
    ok: bool


def check_goals(report: Any) -> list[GoalCheck]:
    """Each goal of the demo at its defaults, with the run's figure and whether it is met.
    A figure that could not be measured (NaN) does not meet its goal."""
    s, lat = report.scores, report.latency

    def below(x: float, bound: float) -> bool:
        return math.isfinite(x) and x < bound

    def above(x: float, bound: float) -> bool:
        return math.isfinite(x) and x > bound

    kept_up = report.frames_in_time / report.frames_triggered if report.frames_triggered else math.nan
    scored = [] if s is None else [  # a run that was not scored (the soak) has no tracking goals
        GoalCheck("3D RMSE (mm)", "< 2", s.rmse_mm, below(s.rmse_mm, 2.0)),
        GoalCheck("MOTA", "> 0.99", s.mota, above(s.mota, 0.99)),
        GoalCheck("IDF1", "> 0.95", s.idf1, above(s.idf1, 0.95)),
        GoalCheck("merges", "0", float(s.merges), s.merges == 0),
    ]
    return scored + [
        GoalCheck("latency P50 (ms)", "< 3", lat["p50_ms"], below(lat["p50_ms"], 3.0)),
        GoalCheck("frames tracked in time", "all", kept_up, kept_up == 1.0),
    ] + _closed_loop(report)


def _closed_loop(report: Any) -> list[GoalCheck]:
    act = getattr(report, "actuation", None)
    if not act:
        return []
    from flytrack_host.sim.closed_loop import goal_checks

    return [GoalCheck(*g) for g in goal_checks(act)]
