"""Helpers of the actuation tests: frames of tracked objects as the pipeline hands them to sinks."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import pytest

from flytrack_host.actuation.engine import ActuationEngine
from flytrack_host.actuation.rules import parse_rules
from flytrack_host.rig import ActuatorConfig
from flytrack_host.tracking.types import Estimate, FrameResult
from flytrack_host.util import hostclock

BOX_RULE = {"name": "enter", "when": {"inside": {"box": {"min": [1, -1, -1], "max": [2, 1, 1]}}}}


def result(frame: int, objs: dict[int, tuple[float, float]]) -> FrameResult:
    """Objects obj_id -> (x, vx) on the x axis."""
    est = [Estimate(i, np.array([x, 0, 0, vx, 0, 0], float), np.eye(6), 3) for i, (x, vx) in objs.items()]
    return FrameResult(frame, 0.0, est)


def engine(actions: list[dict], actuators: list[ActuatorConfig], fps: float = 100.0, context: dict | None = None,
           rule: dict | None = None) -> ActuationEngine:
    rs = parse_rules({"rules": [{**(rule or BOX_RULE), "actions": actions}]})
    return ActuationEngine(rs, actuators, fps, context)


def drive_entries(eng: ActuationEngine, n_entries: int, fps: float = 100.0, frames_out: int = 30,
                  frames_in: int = 5, between: Callable[[int], None] | None = None,
                  realtime: bool = False) -> list[float]:
    """One object going out (x = 0) and in (x = 1.5) `n_entries` times; returns on_frame durations."""
    durations = []
    f = 0
    t0 = hostclock.now()
    for k in range(n_entries):
        if between is not None:
            between(k)
        for x in [0.0] * frames_out + [1.5] * frames_in:
            ft = t0 + f / fps
            if realtime:
                time.sleep(max(0.0, ft + 0.002 - hostclock.now()))
            s = time.perf_counter()
            eng.on_frame(result(f, {1: (x, 0.0)}), ft, hostclock.now())
            durations.append(time.perf_counter() - s)
            f += 1
    return durations


def wait_for(cond: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.01)
    return cond()


class _Helpers:
    BOX_RULE = BOX_RULE
    result = staticmethod(result)
    engine = staticmethod(engine)
    drive_entries = staticmethod(drive_entries)
    wait_for = staticmethod(wait_for)


@pytest.fixture
def act() -> type[_Helpers]:
    return _Helpers
