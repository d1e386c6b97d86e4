"""The demo's closed loop: the rules file drives the simulated rig's trigger firmware (its high-speed
camera line), a real pymodbus TCP server on loopback in its own process (a coil) and a python-can
virtual bus (a frame),
and the firings are scored against the simulated flight's ground truth.

    lab = ClosedLoopLab(rules_path, out)     # starts the Modbus server and the CAN listener
    rig = lab.rig(rig)                      # the rig file gets the lab's actuators and the rules
    engine = lab.engine(rig, fps, session)  # after the TriggerSession opened; engine.attach(pipe)
    ...
    report = lab.report(engine, gt, pulse_frames)   # the JSON's `actuation`
    lab.close()

Expected firings come from the same rule evaluator run on the ground truth (every animal's true
position and velocity at every frame, no latency): the frame each animal truly entered.
"""

from __future__ import annotations

import math
import shutil
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.actuation.engine import ALL_FIRES, RECENT_FIRES, ActuationEngine
from flytrack_host.actuation.firings import percentiles_ms, send_split, stage_latencies
from flytrack_host.actuation.history import RuleEvaluator
from flytrack_host.actuation.peers import CanListener, ModbusPeerProcess
from flytrack_host.actuation.rules import load_rules
from flytrack_host.recording.schema import FIRING_FRAME_EXACT
from flytrack_host.rig import ActuatorConfig, RigConfig
from flytrack_host.util.placement import run_as_hardware

MATCH_WINDOW_S = 0.3  # a firing further than this from every true entry is a false fire
LATENCY_DEFINITION = (
    "latency_ms_p50/p99: per firing, from the trigger time of the frame whose estimate fired (the host's trigger "
    "clock model) to the last acknowledgement of the devices that act at once (Modbus response, CAN send); the "
    "PULSE is armed ahead for a later frame, its ACK time is pulse_ack_ms_p50/p99 and its landing frame_error_max. "
    "What each device's acknowledgement is: outputs.NAME.acknowledged_means. latency_stages_ms splits it per "
    "output: trigger -> estimate -> queued -> taken by the device thread -> sent -> acknowledged.")


def expected_firings(rule: Any, gt: Any) -> list[tuple[int, int]]:
    """(frame, animal) of each firing the rule would make on the true states (no latency)."""
    ev = RuleEvaluator(rule.model_copy(update={"predict": False}), 1.0 / gt.fps)
    ids = np.arange(gt.n_animals)
    out = []
    for f in range(gt.n_frames):
        st = np.concatenate([gt.pos[f], gt.vel[f]], axis=1)
        out += [(fi.scheduled_frame, fi.obj_id) for fi in ev.step(f, f, ids, st)]
    return out


def match(fired: list[int], expected: list[int], window: int) -> tuple[list[int], int, int]:
    """Pairs firings with true entries, closest first; returns (signed frame errors, missed, false fires)."""
    pairs = sorted((abs(f - e), i, j) for i, f in enumerate(fired) for j, e in enumerate(expected)
                   if abs(f - e) <= window)
    used_f: set[int] = set()
    used_e: set[int] = set()
    errs = []
    for _, i, j in pairs:
        if i in used_f or j in used_e:
            continue
        used_f.add(i)
        used_e.add(j)
        errs.append(fired[i] - expected[j])
    return errs, len(expected) - len(used_e), len(fired) - len(used_f)


def latency_by_output(rows: np.ndarray) -> dict[str, dict[str, Any]]:
    """Per output (device) of a rule's firing rows: trigger time of the frame -> that device's own
    acknowledgement (ms, P50/P99), so the figure says which device costs what. The PULSE's ack is its
    ACK of the armed request (the pulse itself lands on its scheduled frame: frame_error_max)."""
    out: dict[str, dict[str, Any]] = {}
    for name in sorted({bytes(n) for n in rows["output"]}):
        r = rows[rows["output"] == name]
        p = percentiles_ms(r["time_ack"] - r["frame_time"])
        out[name.decode()] = {"kind": bytes(r["kind"][0]).decode(), "n": p["n"],
                              "p50": p.get("p50", math.nan), "p99": p.get("p99", math.nan)}
    return out


def _max_abs(v: list[int]) -> float:
    return float(max((abs(x) for x in v), default=math.nan))


def _start_modbus(out: Path, attempts: int = 3) -> ModbusPeerProcess:
    """The PLC's server on a free port. The port is free when chosen, not reserved: another process
    may bind it before the server does (the server then exits), so a few ports are tried."""
    err: Exception | None = None
    for _ in range(attempts):
        try:
            return ModbusPeerProcess(log_dir=str(out)).start()
        except RuntimeError as exc:
            err = exc
    raise RuntimeError(f"the simulated PLC (Modbus server) did not start on {attempts} ports: {err}")


class ClosedLoopLab:
    """The lab devices of the simulated rig, real protocol stacks on loopback."""

    def __init__(self, rules_path: Path, out: Path):
        self.rules_src = Path(rules_path)
        self.rules = load_rules(self.rules_src)  # a bad file stops the demo before anything starts
        self.rules_copy = Path(out) / "rules.toml"
        shutil.copyfile(self.rules_src, self.rules_copy)
        self.modbus = _start_modbus(out)  # a process of its own, as a PLC
        if self.modbus.proc is not None:
            # A PLC is a machine of its own: it runs at the simulated hardware's priority (as the cameras
            # and the trigger), so a loaded machine delays the host under test rather than the device.
            run_as_hardware(self.modbus.proc.pid)
        self.can_channel = f"flytrack-demo-{uuid.uuid4().hex[:8]}"
        self.can = CanListener("virtual", self.can_channel)

    @property
    def actuators(self) -> list[ActuatorConfig]:
        return [
            ActuatorConfig(name="hscam", kind="trigger_pulse", channel=0),
            ActuatorConfig(name="valve", kind="modbus", address=self.modbus.address),
            ActuatorConfig(name="stimulus_can", kind="can", interface="virtual", address=self.can_channel),
        ]

    def rig(self, rig: RigConfig) -> RigConfig:
        return rig.model_copy(update={"actuators": self.actuators, "rules": self.rules_copy.name})

    def engine(self, rig: RigConfig, fps: float, session: Any, score: bool = True) -> ActuationEngine:
        """The rig's engine; `score` keeps every firing in memory for `report` (a soak keeps the latest)."""
        assert rig.rules_path is not None
        ctx = {"trigger": lambda: session.device, "clock": session.clock}
        return ActuationEngine.from_files(rig, rig.rules_path, fps, context=ctx,
                                          keep=ALL_FIRES if score else RECENT_FIRES)

    def report(self, engine: ActuationEngine, gt: Any, pulse_frames: np.ndarray | None) -> dict[str, Any]:
        rows = engine.firings.table()
        summary = engine.summary()
        # A run that kept only the latest firings (a soak: the recording has them all) cannot be matched
        # against the truth: its firings are counted, not scored.
        complete = sum(engine.fired.values()) <= len(engine.fires)
        out_rules: dict[str, Any] = {}
        for ev in engine.evals:
            name = ev.rule.name
            exp = [f for f, _ in expected_firings(ev.rule, gt)]
            fired = [f.scheduled_frame for f in engine.fires if f.rule == name]
            shadow = [f.scheduled_frame for f in engine.shadow_fires if f.rule == name]
            w = round(MATCH_WINDOW_S * gt.fps)
            errs, missed, false = match(fired, exp, w)
            errs_np, _, _ = match(shadow, exp, w)
            if pulse_frames is not None and len(pulse_frames):
                # Frame errors of the high-speed camera pulse as the simulated pin saw it.
                errs, _, _ = match([int(x) for x in pulse_frames], exp, w)
            rr = rows[rows["rule"] == name.encode()]
            exact = (rr["flags"] & FIRING_FRAME_EXACT) != 0
            # Latency: the frame's trigger time (clock model) -> the device's acknowledgement, per firing
            # the latest of its loopback devices (Modbus, CAN...). The firmware pulse is scheduled for a
            # later frame; its serial round trip is reported apart (pulse_ack_ms).
            lat, est, ack = [], [], []
            keys = {(int(o), int(c)) for o, c in zip(rr["obj_id"], rr["condition_frame"], strict=True)}
            for o, c in keys:
                g = rr[(rr["obj_id"] == o) & (rr["condition_frame"] == c) & ~exact
                       & (rr["kind"] != b"trigger_pulse")]
                if len(g) and np.all(np.isfinite(g["time_ack"])):
                    lat.append(float(np.max(g["time_ack"]) - g["frame_time"][0]))
                    est.append(float(g["estimate_time"][0] - g["frame_time"][0]))
                    ack.append(float(np.max(g["time_ack"]) - g["estimate_time"][0]))
            lp = percentiles_ms(lat)
            pulse = rr[rr["kind"] == b"trigger_pulse"]
            pp = percentiles_ms(pulse["time_ack"] - pulse["frame_time"])
            d: dict[str, Any] = {
                "fired": len(fired) if complete else engine.fired[name],
                "expected": len(exp),
                "missed": missed if complete else None,
                "false_fires": false if complete else None,
                "scored": complete,
                "frame_error_max": _max_abs(errs),
                "frame_errors": errs,
                "frame_error_max_no_prediction": _max_abs(errs_np),
                "frame_errors_no_prediction": errs_np,
                "latency_ms_p50": lp.get("p50", math.nan),
                "latency_ms_p99": lp.get("p99", math.nan),
                "latency_n": lp["n"],
                # Where it went: the host's trigger -> estimate, then estimate -> the devices' acknowledgement.
                "latency_parts_ms_p50": {"trigger_to_estimate": percentiles_ms(est).get("p50", math.nan),
                                         "estimate_to_ack": percentiles_ms(ack).get("p50", math.nan)},
                # Each stage per output: trigger -> estimate -> queued -> taken by the device thread -> sent
                # -> acknowledged (ms, P50/P99).
                "latency_stages_ms": stage_latencies(engine.stages, name),
                # sent_to_ack split where the device stamps its write: the client's work, then the device's.
                "latency_send_split_ms": send_split(engine.sends, name),
                # Each device on its own: the firmware pulse's ACK, the Modbus response, the CAN send.
                "latency_ms_by_output": latency_by_output(rr),
                "pulse_ack_ms_p50": pp.get("p50", math.nan),
                "pulse_ack_ms_p99": pp.get("p99", math.nan),
                "expected_frames": exp,
                "fired_frames": fired,
                "suppressed": dict(ev.suppressed),
                "outputs": summary["rules"].get(name, {}).get("outputs", {}),
            }
            if pulse_frames is not None:
                # The high-speed camera line as the simulated pin saw it, against the recorded frames.
                recorded = sorted(int(f) for f in pulse["scheduled_frame"])
                d["pulses_on_pin"] = int(len(pulse_frames))
                d["pulse_frames_on_pin"] = [int(x) for x in pulse_frames]
                d["pulse_frames_recorded"] = recorded
                d["pulse_frames_exact"] = int(np.sum((pulse["flags"] & FIRING_FRAME_EXACT) != 0))
                exact = {int(f) for f in pulse["scheduled_frame"][(pulse["flags"] & FIRING_FRAME_EXACT) != 0]}
                d["pulse_frames_match_recording"] = exact <= {int(x) for x in pulse_frames}
            out_rules[name] = d
        return {
            "rules_file": str(self.rules_src),
            "latency_definition": LATENCY_DEFINITION,
            "rules": out_rules,
            "modbus_coil_writes": len(self.modbus.writes),
            "can_frames": len(self.can.frames),
            "eval_us_mean": summary["eval_us_mean"],
            "eval_us_max": summary["eval_us_max"],
            "handoff": summary["handoff"],
            "tracking_priority_raised": summary["tracking_priority_raised"],
            "outputs": summary["outputs"],
        }

    def close(self) -> None:
        self.can.close()
        self.modbus.stop()


def closed_loop_line(act: dict[str, Any]) -> tuple[str, str]:
    """The summary's one closed-loop line: value and note (kept short: the table is 80 columns)."""
    parts_v, parts_n = [], []
    for d in act.get("rules", {}).values():
        parts_v.append(f"{d['fired']}/{d['expected']}, {d['missed']} miss, {d['false_fires']} false")
        err, err_np = _span(d.get("frame_errors")), _span(d.get("frame_errors_no_prediction"))
        p50, p99 = _fmt(d["latency_ms_p50"], ".1f"), _fmt(d["latency_ms_p99"], ".1f")
        parts_n.append(f"frame err {err} ({err_np} unpredicted); ack P50/P99 {p50}/{p99} ms")
    return "; ".join(parts_v), "; ".join(parts_n)


def _span(errs: list[int] | None) -> str:
    """Signed frame errors as a range (+0, -3..+1), n/a when there is none."""
    if not errs:
        return "n/a"
    lo, hi = min(errs), max(errs)
    return f"{lo:+d}" if lo == hi else f"{lo:+d}..{hi:+d}"


def _fmt(x: float, kind: str = ".2f") -> str:
    if x is None or not math.isfinite(x):
        return "n/a"
    return str(int(x)) if kind == "d" else format(x, kind)


def goal_checks(act: dict[str, Any]) -> list[tuple[str, str, float, bool]]:
    """(name, goal, measured, ok) of the closed loop, over all rules (issue 10's goals)."""
    rules = list(act.get("rules", {}).values())
    if not rules:
        return []
    missed = sum(d["missed"] for d in rules) + sum(d["false_fires"] for d in rules)
    ferr = max((d["frame_error_max"] for d in rules), default=math.nan)
    p50 = max((d["latency_ms_p50"] for d in rules), default=math.nan)
    p99 = max((d["latency_ms_p99"] for d in rules), default=math.nan)

    def fin(x: float) -> bool:
        return x is not None and math.isfinite(x)

    return [
        ("closed loop missed + false fires", "0", float(missed), missed == 0 and all(d["expected"] for d in rules)),
        ("closed loop pulse frame error", "<= 1", ferr, fin(ferr) and ferr <= 1),
        ("closed loop ack P50 (ms)", "< 2", p50, fin(p50) and p50 < 2.0),
        ("closed loop ack P99 (ms)", "< 5", p99, fin(p99) and p99 < 5.0),
    ]
