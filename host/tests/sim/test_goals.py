"""The demo's goal check: each of issue 7's goals, met or not, and NaN never counts as met."""

from __future__ import annotations

import math
from types import SimpleNamespace

from flytrack_host.sim.goals import check_goals


def report(rmse=0.5, mota=0.995, idf1=0.99, merges=0, p50=1.5, in_time=1000, triggered=1000):
    return SimpleNamespace(
        scores=SimpleNamespace(rmse_mm=rmse, mota=mota, idf1=idf1, merges=merges),
        latency={"p50_ms": p50},
        frames_in_time=in_time,
        frames_triggered=triggered,
    )


def test_all_goals_met() -> None:
    assert all(g.ok for g in check_goals(report()))


def test_each_goal_can_fail() -> None:
    cases = {
        "3D RMSE (mm)": report(rmse=2.5),
        "MOTA": report(mota=0.98),
        "IDF1": report(idf1=0.9),
        "merges": report(merges=1),
        "latency P50 (ms)": report(p50=3.5),
        "frames tracked in time": report(in_time=999),
    }
    for name, r in cases.items():
        failed = [g.name for g in check_goals(r) if not g.ok]
        assert failed == [name], (name, failed)


def test_unmeasured_figures_do_not_meet_goals() -> None:
    failed = {g.name for g in check_goals(report(rmse=math.nan, p50=math.nan, triggered=0)) if not g.ok}
    assert failed == {"3D RMSE (mm)", "latency P50 (ms)", "frames tracked in time"}
