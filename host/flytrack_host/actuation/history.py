"""A rule over time: per-object stretches of true/false, firing on entries, and the rule's gates.

`RuleEvaluator.step` is deterministic in trigger frames (times are frame x period), so the live
engine, `flytrack rules replay` and the demo's ground truth all get the same answer from the same
states. A rule fires for an object on the frame its condition has held `hold_ms` after having been
false for at least `after_false_ms` (an object first seen with the condition already true has no
"before" and does not fire); each true stretch fires at most once. Then the rule's gates: arming
window (seconds from trigger frame 0), cooldown and maximum rate (whatever the object); a firing a
gate stops is counted in `suppressed` and uses up that stretch.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from flytrack_host.actuation.conditions import compile_condition, turn_rate_deg_s
from flytrack_host.actuation.prediction import StepVelocities, predict_states
from flytrack_host.actuation.rules import Rule

_EPS = 1e-9


@dataclass
class Fire:
    rule: str
    obj_id: int
    condition_frame: int  # the frame whose estimate made the rule fire
    scheduled_frame: int  # the frame the action is meant for (the condition was judged there)
    pos: np.ndarray  # position the condition was judged on (predicted when `predicted`)
    predicted: bool


@dataclass
class _Obj:
    state: bool
    since: int  # first frame of the current stretch
    prev_false: int = -1  # length (frames) of the false stretch before this true one; -1 unknown
    fired: bool = False
    last_vel: np.ndarray | None = None
    last_frame: int = -1


@dataclass
class RuleEvaluator:
    rule: Rule
    period_s: float
    objs: dict[int, _Obj] = field(default_factory=dict)
    last_fire_frame: int | None = None
    recent: deque = field(default_factory=deque)  # frames of firings within the last minute
    suppressed: dict[str, int] = field(default_factory=dict)
    frames: int = 0

    def __post_init__(self) -> None:
        self._needs_turn = self.rule.when.turn_rate_deg_s is not None
        self._mask = compile_condition(self.rule.when)
        self._hold = self.rule.when.hold_ms / 1e3
        self._after = self.rule.when.after_false_ms / 1e3
        self._step_vel = StepVelocities(self.period_s)  # when the caller gives none (see `step`)

    def reset(self) -> None:
        """Forget every object and the last firing (trigger frames start again from 0)."""
        self._step_vel.reset()
        self.objs.clear()
        self.last_fire_frame = None
        self.recent.clear()

    def _select(self, ids: np.ndarray) -> np.ndarray:
        o = self.rule.objects
        if o == "any" or len(ids) == 0:
            return np.ones(len(ids), dtype=bool)
        if o == "first":
            return ids == ids.min()
        return ids == int(o)

    def step(self, frame: int, target_frame: int, ids: np.ndarray, states: np.ndarray,
             step_vel: np.ndarray | None = None) -> list[Fire]:
        """One frame's estimates (ids (N,), states (N, 6)); the action would reach `target_frame`.
        `step_vel`: the objects' velocities to predict with (`StepVelocities` of this frame: the engine
        computes them once for all its rules); None: this evaluator's own. Returns the firings (already
        through the gates)."""
        self.frames += 1
        r = self.rule
        id_list = ids.tolist()
        if r.predict:
            ahead = min((target_frame - frame) * self.period_s, r.max_predict_ms / 1e3)
            vel = self._step_vel(frame, ids, states) if step_vel is None else step_vel
            if ahead > 0 and isinstance(vel, np.ndarray) and vel.shape == (len(states), 3) and vel.dtype == np.float64:
                judged = states.astype(np.float64)  # predict_states, in fewer NumPy calls (tracking thread)
                judged[:, :3] += vel * ahead
            else:
                judged = predict_states(states, ahead, vel) if ahead > 0 else states
            at = target_frame
        else:
            judged = states
            at = target_frame  # the action still lands on the reachable frame, judged on frame `frame`
        turn = None
        if self._needs_turn:  # from each object's previous velocity (vectorised over the objects)
            prev = np.full((len(ids), 3), np.nan)
            dt = np.zeros(len(ids))
            for i, oid in enumerate(id_list):
                ob = self.objs.get(oid)
                if ob is not None and ob.last_vel is not None and frame > ob.last_frame:
                    prev[i] = ob.last_vel
                    dt[i] = (frame - ob.last_frame) * self.period_s
            turn = turn_rate_deg_s(prev, states[:, 3:6], dt)
        mask = self._mask(judged[:, :3], judged[:, 3:6], turn)
        if r.objects != "any":
            mask &= self._select(ids)
        fires: list[Fire] = []
        hold, after = self._hold, self._after
        seen = set()
        for i, (oid, m) in enumerate(zip(id_list, mask.tolist(), strict=True)):
            seen.add(oid)
            ob = self.objs.get(oid)
            if ob is None:
                ob = self.objs[oid] = _Obj(state=m, since=at)
            elif m != ob.state:
                if m:
                    ob.prev_false = at - ob.since
                    ob.fired = False
                ob.state, ob.since = m, at
            if self._needs_turn:
                ob.last_vel, ob.last_frame = states[i, 3:6].copy(), frame
            if not m or ob.fired or ob.prev_false < 1:
                continue
            if (at - ob.since) * self.period_s + _EPS < hold or ob.prev_false * self.period_s + _EPS < after:
                continue
            ob.fired = True
            why = self._gate(frame, at)
            if why:
                self.suppressed[why] = self.suppressed.get(why, 0) + 1
                continue
            self.last_fire_frame = at
            self.recent.append(at)
            fires.append(Fire(r.name, oid, frame, at, judged[i, :3].copy(), r.predict))
        for gone in set(self.objs) - seen:  # the track died: a new one starts without history
            del self.objs[gone]
        return fires

    def _gate(self, frame: int, at: int) -> str | None:
        r = self.rule
        t = frame * self.period_s
        if t + _EPS < r.armed_after_s or (r.armed_until_s is not None and t > r.armed_until_s):
            return "not armed"
        if self.last_fire_frame is not None and (at - self.last_fire_frame) * self.period_s + _EPS < r.cooldown_s:
            return "cooldown"
        if r.max_per_minute is not None:
            window = round(60.0 / self.period_s)
            while self.recent and self.recent[0] <= at - window:
                self.recent.popleft()
            if len(self.recent) >= r.max_per_minute:
                return "max rate"
        return None
