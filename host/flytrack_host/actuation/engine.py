"""The live rule engine: a `ResultSink` of the host pipeline that judges every tracked frame against
the rules and hands the resulting actions to per-device worker threads.

    engine = ActuationEngine.from_files(rig, rules_path, fps, context={"trigger": lambda: session.device})
    engine.attach(pipe)      # sink + status line + recording of firings; before or after pipe.start()
    engine.start()           # output workers connect (a device absent now is retried on its own)
    ...                      # pipe.stop() closes the engine (queued actions are finished first)

`on_frame` runs on the tracking thread: per rule one vectorised condition over the frame's objects
and a few dict updates per object, then `put_nowait` of each action (`make bench-actuation` prints
its cost per frame against the number of objects). Nothing here waits for a device's answer: on a
frame that fired, it only waits (at most `HANDOFF_MAX_S`) for the idle devices' threads to put their
commands on the wire (`devices.base.Handoff`), so they do not wait for this thread's next stretch of
work to get Python's GIL.

The frame each firing aims for is the first frame its slowest output can still reach (the measured
trigger-to-estimate latency, the device's latency and its arming lead; `prediction.reachable_frame`),
and with `predict = true` (default) the rule is judged on the state predicted to that frame. A shadow
evaluator judges every rule without prediction too (never sending anything) so the summary can say
how far off the firings would have been without it.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.actuation.devices import Output, make_output
from flytrack_host.actuation.devices.base import HANDOFF_MAX_S, WORKER_NICE, Handoff, Job, Outcome, OutputWorker
from flytrack_host.actuation.firings import FiringLog, summarize
from flytrack_host.actuation.history import Fire, RuleEvaluator
from flytrack_host.actuation.prediction import StepVelocities, reachable_frame
from flytrack_host.actuation.rules import RuleSet, bind_rules, load_rules
from flytrack_host.rig import ActuatorConfig, RigConfig
from flytrack_host.util import hostclock
from flytrack_host.util.ratelog import RateLimitedLog

log = logging.getLogger("flytrack.actuation")
SWITCH_INTERVAL_S = 0.0002
# Firings kept in memory (the recording keeps every one): the latest RECENT_FIRES for a live run's
# summary, so hours of firings cost no memory; ALL_FIRES when a caller scores every firing (the demo).
RECENT_FIRES = 1024
ALL_FIRES = 100_000


def estimates_arrays(result: Any) -> tuple[np.ndarray, np.ndarray]:
    est = result.estimates
    ids = np.fromiter((e.obj_id for e in est), dtype=np.int64, count=len(est))
    states = np.array([np.asarray(e.state, dtype=np.float64)[:6] for e in est], dtype=np.float64).reshape(-1, 6)
    return ids, states


class ActuationEngine:
    def __init__(self, rules: RuleSet, actuators: list[ActuatorConfig], fps: float,
                 context: dict[str, Any] | None = None, rules_path: Path | str = "<rules>",
                 keep: int = RECENT_FIRES):
        bind_rules(rules, actuators, rules_path)
        self.rules = rules
        self.rules_path = Path(rules_path)
        self.period_s = 1.0 / fps
        used = {a.output for r in rules.rules for a in r.actions}
        self.outputs: dict[str, Output] = {a.name: make_output(a, context) for a in actuators if a.name in used}
        self.evals = [RuleEvaluator(r, self.period_s) for r in rules.rules]
        # The same rules without prediction, for the "how far off without it" figure; a rule that does not
        # predict is its own shadow, so it is not evaluated twice.
        self.shadow = [RuleEvaluator(r.model_copy(update={"predict": False}), self.period_s) if r.predict else None
                       for r in rules.rules]
        self.rule_outputs = [[self.outputs[a.output] for a in r.actions] for r in rules.rules]
        self.step_vel = StepVelocities(self.period_s)  # the velocities to predict with, per frame
        self._predicting = any(r.predict for r in rules.rules)
        self.firings = FiringLog(record=self._record, keep=keep)
        # The latest `keep` firings (the recording keeps them all), and counts per rule.
        self.shadow_fires: deque[Fire] = deque(maxlen=keep)
        self.fires: deque[Fire] = deque(maxlen=keep)
        self.fired: dict[str, int] = {r.name: 0 for r in rules.rules}
        # Per action, the host times of each stage (trigger, estimate, queued, taken by the worker, sent,
        # acknowledged): where the time from a frame's trigger to the device's acknowledgement goes.
        self.stages: deque[tuple[str, str, int, float, float, float, float, float, float]] = deque(maxlen=keep)
        # Per action of a device that says when its command left the host (`Output.written`): rule,
        # output, sent (the device thread began the command), written (the write returned), acknowledged:
        # the client library's own work apart from the device's answer.
        self.sends: deque[tuple[str, str, float, float, float]] = deque(maxlen=keep)
        self.frames = 0
        self.eval_s_total = 0.0
        self.eval_s_max = 0.0
        self.handoff_max_s = HANDOFF_MAX_S  # 0: no hand-off wait (the benchmark's side-by-side)
        self.handoffs = 0  # frames that fired with an idle device: the tracking thread waited for the send
        self.handoff_timeouts = 0
        self.handoff_s_total = 0.0
        self.handoff_s_max = 0.0
        self._pipe: Any = None
        self.warn = RateLimitedLog(lambda m: self._log(m))
        self.workers = {n: OutputWorker(o, self._done, self.warn) for n, o in self.outputs.items()}
        self.rule_problems: list[str] = []  # rules left out at start (flytrack run --skip-bad-rules)
        self._started = False
        self._closed = False
        self._last_frame = -1
        self._switch_interval: float | None = None  # Python's, restored at close
        self.tracking_priority_raised: bool | None = None  # the calling (tracking) thread's, at its first frame

    @classmethod
    def from_files(cls, rig: RigConfig, rules_path: Path | str, fps: float,
                   context: dict[str, Any] | None = None, keep: int = RECENT_FIRES) -> ActuationEngine:
        ctx = {"base_dir": rig.base_dir, **(context or {})}
        return cls(load_rules(rules_path), rig.actuators, fps, ctx, rules_path, keep=keep)

    # --- wiring -----------------------------------------------------------------------------
    def attach(self, pipe: Any) -> None:
        self._pipe = pipe
        if self not in pipe.sinks:
            pipe.sinks.append(self)
        pipe.status_sources.append(self.status)
        names = ", ".join(f"{r.name}{' (dry run)' if r.dry_run else ''}" for r in self.rules.rules)
        self._log(f"rules from {self.rules_path}: {names}")
        for p in self.rule_problems:
            self._log(f"rule left out: {p}")

    def start(self) -> None:
        if not self._started:
            self._started = True
            if self.workers and sys.getswitchinterval() > SWITCH_INTERVAL_S:
                # The commands leave during the tracking thread's hand-off wait; after that, a device
                # thread that needs the GIL again (the firmware's ACK read by the trigger's reader thread,
                # a reply's bookkeeping) would wait for the tracking thread to block or for Python's 5 ms
                # switch interval. Measured side by side in chrt'd demos, 0.2 ms and 5 ms gave the same
                # trigger -> estimate (P50 0.95-1.15 ms host part) within the runs' spread.
                self._switch_interval = sys.getswitchinterval()
                sys.setswitchinterval(SWITCH_INTERVAL_S)
            for w in self.workers.values():
                w.start()

    def _log(self, message: str) -> None:
        if self._pipe is not None:
            self._pipe.log(message, "actuation")
        else:
            log.warning("%s", message)

    def _record(self, row: np.ndarray) -> None:
        rec = getattr(self._pipe, "recorder", None)
        if rec is not None:
            rec.append("actuation_firings", row)

    # --- the tracking thread's part -----------------------------------------------------------
    def on_frame(self, result: Any, frame_time: float, estimate_time: float) -> None:
        t0 = time.perf_counter()
        if self.tracking_priority_raised is None and self.workers:
            self._raise_caller()
        now = hostclock.now()
        frame = int(result.trigger_frame)
        if frame < self._last_frame:  # the trigger was re-armed (frame 0 again, a new tracker)
            self._log(f"trigger frames restarted ({self._last_frame} -> {frame}): rule histories cleared")
            for ev in (*self.evals, *self.shadow):
                if ev is not None:
                    ev.reset()
            self.step_vel.reset()
        self._last_frame = frame
        ids, states = estimates_arrays(result)
        step_vel = self.step_vel(frame, ids, states) if self._predicting else None  # once for all rules
        self.frames += 1
        handoff = False
        jobs: list[tuple[OutputWorker, Job]] = []
        targets = []
        for ev, outs in zip(self.evals, self.rule_outputs, strict=True):
            target = max((reachable_frame(frame, frame_time, now, o.lead_s + o.arm_frames * self.period_s,
                                          self.period_s) for o in outs),
                         default=reachable_frame(frame, frame_time, now, 0.0, self.period_s))
            targets.append(target)
            fires = ev.step(frame, target, ids, states, step_vel)
            if not ev.rule.predict:
                self.shadow_fires.extend(fires)  # its own shadow
            for f in fires:
                handoff = self._dispatch(f, ev, frame_time, estimate_time, handoff, jobs)
        # The devices that act at once (a coil, a CAN frame), the slowest to acknowledge first (its round
        # trip then overlaps the others' sends), before those a command reaches a frame ahead (the PULSE:
        # its lead counts the wait for the others).
        jobs.sort(key=lambda wj: (wj[0].output.arm_frames, -wj[0].output.lead_s))
        if not handoff:
            for worker, job in jobs:
                worker.submit(job)
        else:
            # Let the device threads put their commands on the wire now (this thread's GIL released),
            # rather than after this thread's next stretch of work: bounded, and only on a frame that fired.
            # All are woken at once (their wake-ups overlap) but send in this order, each after the one
            # before it sent (`Job.after`): each thread then has the interpreter to itself from taking its
            # job to its send (woken together without an order they took it from each other at switch
            # intervals, the first device's command leaving 0.08-0.51 ms after it was queued; woken one
            # after another, a loaded machine's wake-ups added up).
            latches = []
            for _, job in jobs:
                if job.handoff is not None:
                    job.after = latches[-1] if latches else None
                    job.after_wait_s = self.handoff_max_s
                    latches.append(job.handoff)  # kept: the device thread clears job.handoff once it sent
            t1 = time.perf_counter()
            for worker, job in jobs:
                worker.submit(job)
            deadline = t1 + self.handoff_max_s
            if not all(h.wait(max(0.0, deadline - time.perf_counter())) for h in latches):
                self.handoff_timeouts += 1
            w = time.perf_counter() - t1
            self.handoffs += 1
            self.handoff_s_total += w
            self.handoff_s_max = max(self.handoff_s_max, w)
        # The shadow (no prediction) only feeds the summary: judged after the commands have left.
        for sh, target in zip(self.shadow, targets, strict=True):
            if sh is not None:
                self.shadow_fires.extend(sh.step(frame, target, ids, states))
        dt = time.perf_counter() - t0
        self.eval_s_total += dt
        self.eval_s_max = max(self.eval_s_max, dt)

    def _raise_caller(self) -> None:
        """The thread that feeds the rules (the pipeline's tracking thread) runs at the device threads'
        priority (nice WORKER_NICE, Linux, when allowed): in a closed loop the time from a frame's
        datagrams to its commands is the host's part of the latency, and at nice 0 that thread waited for
        a CPU behind the simulated cameras' processes (nice -5) and other jobs. Not the program's main
        thread (a benchmark's or a test's loop calling on_frame): that would raise the whole program."""
        if threading.current_thread() is threading.main_thread():
            self.tracking_priority_raised = False
            return
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), WORKER_NICE)
            self.tracking_priority_raised = True
        except (PermissionError, OSError, AttributeError):
            self.tracking_priority_raised = False

    def _dispatch(self, f: Fire, ev: RuleEvaluator, frame_time: float, estimate_time: float,
                  handoff: bool, jobs: list[tuple[OutputWorker, Job]]) -> bool:
        """Adds the firing's actions to `jobs` (queued by the caller); a command for an idle, connected
        device gets a `Handoff`, which the tracking thread then waits for, bounded. True when any did."""
        self.fires.append(f)
        self.fired[f.rule] += 1
        pos = (float(f.pos[0]), float(f.pos[1]), float(f.pos[2]))
        rule = ev.rule
        if rule.dry_run or not rule.actions:
            for a in rule.actions or [None]:
                job = Job(f.rule, f.obj_id, f.condition_frame, f.scheduled_frame, frame_time, estimate_time, pos,
                          a, f.predicted)  # type: ignore[arg-type]
                out = Outcome(job, a.output if a else "", self.outputs[a.output].kind if a else "",
                              scheduled_frame=f.scheduled_frame, error="dry run")
                self.firings.add(out, dry_run=True)
            return handoff
        for a in rule.actions:
            job = Job(f.rule, f.obj_id, f.condition_frame, f.scheduled_frame, frame_time, estimate_time, pos,
                      a, f.predicted)
            worker = self.workers[a.output]
            # An idle, connected device's first command of this frame joins the hand-off.
            if self.handoff_max_s > 0 and worker.ready and all(w is not worker for w, _ in jobs):
                job.handoff = Handoff()
                job.handoff.add()
                handoff = True
            jobs.append((worker, job))
        return handoff

    def _done(self, o: Outcome) -> None:
        self.firings.add(o)
        j = o.job
        self.stages.append((j.rule, o.output, j.condition_frame, j.frame_time, j.estimate_time, j.queued_at,
                            o.time_started, o.time_sent, o.time_ack))
        if math.isfinite(o.time_written):
            self.sends.append((j.rule, o.output, o.time_sent, o.time_written, o.time_ack))
        late = o.error.startswith("late")
        if late:
            self.warn(f"{o.output}:late", f"output {o.output}: {o.error}")
        if o.kind == "trigger_pulse" and o.job.action.level is None and (not o.error or late):
            # The text log travels with every export (.braidz too): a high-speed camera's video is
            # aligned with the tracks from this line even without the firings table.
            how = "exact" if o.frame_exact else "estimated from the trigger clock: the PULSE was late"
            self._log(f"{o.output}: pulse (high-speed camera trigger point) at trigger frame {o.scheduled_frame} "
                      f"({how}); rule {o.job.rule}, object {o.job.obj_id}")
        # other failures: the worker has logged them (rate-limited)

    # --- reporting ----------------------------------------------------------------------------
    def status(self) -> str:
        parts = []
        for ev in self.evals:
            parts.append(f"{ev.rule.name} {self.fired[ev.rule.name]}{' dry' if ev.rule.dry_run else ''}")
        for name, w in self.workers.items():
            s = w.stats
            bad = s.errors + s.dropped
            state = "" if w.output.connected else " DOWN"
            parts.append(f"{name} ok {s.ok}" + (f" ERR {bad}" if bad else "") + state)
        if self.rule_problems:
            parts.append(f"{len(self.rule_problems)} rule problems")
        return "rules: " + ", ".join(parts)

    def summary(self) -> dict[str, Any]:
        rows = self.firings.table()
        per_rule = summarize(rows)
        out_rules = {}
        for ev in self.evals:
            d = per_rule.get(ev.rule.name, {"fired": 0, "latency_ms": {"n": 0}, "outputs": {}})
            d["fired"] = self.fired[ev.rule.name]
            d["suppressed"] = dict(ev.suppressed)
            d["dry_run"] = ev.rule.dry_run
            out_rules[ev.rule.name] = d
        return {
            "rules_file": str(self.rules_path),
            "frames": self.frames,
            "eval_us_mean": self.eval_s_total / self.frames * 1e6 if self.frames else math.nan,
            "eval_us_max": self.eval_s_max * 1e6,
            "tracking_priority_raised": bool(self.tracking_priority_raised),
            "handoff": {"frames": self.handoffs, "timeouts": self.handoff_timeouts,
                        "us_mean": self.handoff_s_total / self.handoffs * 1e6 if self.handoffs else math.nan,
                        "us_max": self.handoff_s_max * 1e6},
            "rules": out_rules,
            "outputs": {n: {**w.stats.__dict__, "connected": w.output.connected, "kind": w.output.kind,
                            "acknowledged_means": w.output.ack_means,
                            "lead_ms": w.output.lead_s * 1e3} for n, w in self.workers.items()},
            "firing_rows": int(len(rows)),  # the latest (`keep`); the recording has all of them
            "firings_total": int(self.firings.count),
            "rule_problems": list(self.rule_problems),
        }

    def close(self) -> None:
        """Finish what is queued (bounded), close the devices. Called by the pipeline's stop()."""
        if self._closed:
            return
        self._closed = True
        for w in self.workers.values():
            w.stop()
        self.warn.flush()  # the counts of messages held back
        if self._switch_interval is not None:
            sys.setswitchinterval(self._switch_interval)
