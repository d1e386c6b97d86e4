"""When would these rules have fired on a past recording? For designing rules on old data.

The recording's tracks (`kalman_estimates`) and per-frame timing (`latency`: trigger time and estimate
time) go frame by frame through the same `RuleEvaluator` the live engine uses, with the same
reachable-frame computation (each frame's own measured estimate latency plus the actions' lead), so a
replay of the rules a run used gives the firings it made (`actuation_firings`), and other rules give
what they would have done.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.actuation.history import Fire, RuleEvaluator
from flytrack_host.actuation.prediction import StepVelocities, reachable_frame
from flytrack_host.actuation.rules import RuleSet
from flytrack_host.recording.reader import Recording

# Lead of an action whose output kind is unknown (no rig in the recording), and per kind: a trigger
# pulse is armed a frame ahead and needs its serial round trip; the others their round trip.
DEFAULT_LEAD_S = {"trigger_pulse": 0.006, "modbus": 0.002}
ARM_FRAMES = {"trigger_pulse": 1}


@dataclass
class Replay:
    fires: list[Fire]
    frames: int
    fps: float
    recorded: np.ndarray  # the recording's own firings table (may be empty)
    suppressed: dict[str, dict[str, int]]


def _actuator_kinds(rec: Recording) -> dict[str, str]:
    data = rec.files.get("rig.toml")
    if not data:
        return {}
    try:
        rig = tomllib.loads(data.decode("utf-8", "replace"))
    except tomllib.TOMLDecodeError:
        return {}
    return {a.get("name", ""): a.get("kind", "") for a in rig.get("actuators", []) if isinstance(a, dict)}


def replay(rec: Recording, rules: RuleSet, prediction: bool | None = None, lead_s: float | None = None) -> Replay:
    """`prediction`: None keeps each rule's `predict`, True/False forces it. `lead_s`: the actions'
    lead for every rule (default: by output kind from the recording's rig file)."""
    fps = rec.fps
    if not fps:
        raise ValueError("the recording does not say its frame rate (meta.json fps)")
    period = 1.0 / fps
    k = rec.table("kalman_estimates")
    lat = rec.table("latency")
    t_trig = dict(zip(lat["trigger_frame"].tolist(), lat["trigger_time"].tolist(), strict=True))
    t_est = dict(zip(lat["trigger_frame"].tolist(), lat["estimate_time"].tolist(), strict=True))
    kinds = _actuator_kinds(rec)
    evals, leads = [], []
    for r in rules.rules:
        if prediction is not None:
            r = r.model_copy(update={"predict": prediction})
        evals.append(RuleEvaluator(r, period))
        if lead_s is not None:
            leads.append(lead_s)
        else:
            ks = [kinds.get(a.output, "") for a in r.actions]
            leads.append(max((DEFAULT_LEAD_S.get(x, 0.0) + ARM_FRAMES.get(x, 0) * period for x in ks), default=0.0))
    fires: list[Fire] = []
    step_vel = StepVelocities(period)
    order = np.argsort(k["trigger_frame"], kind="stable")
    k = k[order]
    frames = np.unique(k["trigger_frame"])
    bounds = np.searchsorted(k["trigger_frame"], frames, side="left")
    ends = np.r_[bounds[1:], len(k)]
    cols = ("x", "y", "z", "xvel", "yvel", "zvel")
    for f, a, b in zip(frames.tolist(), bounds.tolist(), ends.tolist(), strict=True):
        rows = k[a:b]
        states = np.stack([rows[c] for c in cols], axis=1)
        ids = rows["obj_id"].astype(np.int64)
        ft, et = t_trig.get(f, math.nan), t_est.get(f, math.nan)
        vel = step_vel(f, ids, states)  # once for all rules, as the live engine
        for ev, lead in zip(evals, leads, strict=True):
            target = reachable_frame(f, ft, et, lead, period)
            fires += ev.step(f, target, ids, states, vel)
    return Replay(fires, len(frames), fps, rec.table("actuation_firings"),
                  {ev.rule.name: dict(ev.suppressed) for ev in evals})


def plot_replay(rec: Recording, rules: RuleSet, result: Replay, path: Path) -> Path:
    """Top view and x over time of every track, the firing points marked, box regions drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    k = rec.table("kalman_estimates")
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(10, 7), constrained_layout=True)
    for oid in np.unique(k["obj_id"]):
        t = k[k["obj_id"] == oid]
        ax1.plot(t["x"], t["y"], lw=0.7, alpha=0.7)
        ax2.plot(t["trigger_frame"] / result.fps, t["x"], lw=0.7, alpha=0.7, label=f"obj {oid}")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, r in enumerate(rules.rules):
        c = colors[i % len(colors)]
        fs = [f for f in result.fires if f.rule == r.name]
        if fs:
            p = np.array([f.pos for f in fs])
            ax1.scatter(p[:, 0], p[:, 1], marker="*", s=120, color=c, edgecolor="k", zorder=5, label=r.name)
            ax2.scatter([f.scheduled_frame / result.fps for f in fs], p[:, 0], marker="*", s=120, color=c,
                        edgecolor="k", zorder=5)
        box = r.when.inside.box if r.when.inside is not None else None
        if box is not None:
            ax1.add_patch(Rectangle((box.min[0], box.min[1]), box.max[0] - box.min[0], box.max[1] - box.min[1],
                                    fill=False, ls="--", color=c))
            ax2.axhspan(box.min[0], box.max[0], color=c, alpha=0.1)
    ax1.set_xlabel("x (m)")
    ax1.set_ylabel("y (m)")
    ax1.set_aspect("equal", adjustable="datalim")
    ax1.set_title(f"rules replayed: {len(result.fires)} firings (stars) over {result.frames} frames")
    ax1.legend(loc="upper right", fontsize=8)
    ax2.set_xlabel("time from trigger frame 0 (s)")
    ax2.set_ylabel("x (m)")
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def fires_as_dicts(result: Replay) -> list[dict[str, Any]]:
    return [{"rule": f.rule, "obj_id": f.obj_id, "condition_frame": f.condition_frame,
             "frame": f.scheduled_frame, "time_s": f.scheduled_frame / result.fps,
             "x": float(f.pos[0]), "y": float(f.pos[1]), "z": float(f.pos[2])} for f in result.fires]
