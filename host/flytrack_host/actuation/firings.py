"""The firings table: one row per action of each firing, in the recording and in memory, and the
figures drawn from it (per rule: fired, latency from the frame's trigger time to the acknowledgement;
per output: done, failed)."""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from flytrack_host.actuation.devices.base import Outcome
from flytrack_host.recording.schema import (
    FIRING_DRY_RUN,
    FIRING_FAILED,
    FIRING_FRAME_EXACT,
    FIRING_PREDICTED,
    FIRINGS,
)


def outcome_row(o: Outcome, dry_run: bool = False) -> np.ndarray:
    j = o.job
    r = np.zeros(1, dtype=FIRINGS)
    r["rule"] = j.rule.encode()[:32]
    r["output"] = o.output.encode()[:32]
    r["kind"] = o.kind.encode()[:16]
    r["obj_id"] = j.obj_id
    r["condition_frame"] = j.condition_frame
    # A late pulse records the frame it landed on (-1: unknown); a failed action the frame it was for.
    late = o.error.startswith("late")
    r["scheduled_frame"] = o.scheduled_frame if late or o.scheduled_frame >= 0 else j.scheduled_frame
    r["frame_time"] = j.frame_time
    r["estimate_time"] = j.estimate_time
    r["time_sent"] = o.time_sent
    r["time_ack"] = o.time_ack
    r["x"], r["y"], r["z"] = j.pos
    flags = (FIRING_DRY_RUN if dry_run else 0) | (FIRING_PREDICTED if j.predicted else 0)
    flags |= FIRING_FRAME_EXACT if o.frame_exact else 0
    flags |= FIRING_FAILED if o.error and not math.isfinite(o.time_ack) else 0
    r["flags"] = flags
    r["error"] = o.error.encode("utf-8", "replace")[:96]
    return r


def percentiles_ms(v: list[float] | np.ndarray) -> dict[str, float]:
    a = np.asarray(v, dtype=float)
    a = a[np.isfinite(a)]
    if not a.size:
        return {"n": 0}
    return {"n": int(a.size), "p50": float(np.percentile(a, 50) * 1e3), "p99": float(np.percentile(a, 99) * 1e3),
            "max": float(a.max() * 1e3)}


class FiringLog:
    """Thread-safe: the output workers add outcomes; `record` appends each row to the recording."""

    def __init__(self, record: Callable[[np.ndarray], None] | None = None, keep: int = 100_000):
        self.record = record
        self.rows: deque[np.ndarray] = deque(maxlen=keep)  # the latest rows (the recording keeps them all)
        self.count = 0
        self.failed = 0
        self.last: str = ""
        self._lock = threading.Lock()

    def add(self, o: Outcome, dry_run: bool = False) -> None:
        row = outcome_row(o, dry_run)
        with self._lock:
            self.count += 1
            if row["flags"][0] & FIRING_FAILED:
                self.failed += 1
            self.rows.append(row)
            self.last = f"{o.job.rule} obj {o.job.obj_id} -> {o.output} frame {int(row['scheduled_frame'][0])}"
        if self.record is not None:
            self.record(row)

    def table(self) -> np.ndarray:
        with self._lock:
            return np.concatenate(self.rows) if self.rows else np.zeros(0, dtype=FIRINGS)


def summarize(rows: np.ndarray) -> dict[str, Any]:
    """Per rule: firings (distinct rule/object/frame), latency from the condition frame's trigger time to
    the last acknowledgement of the firing's actions; per rule and output: done, failed, latency."""
    out: dict[str, Any] = {}
    for rule in sorted({r.decode() for r in rows["rule"]}):
        rr = rows[rows["rule"] == rule.encode()]
        keys = sorted({(int(o), int(f)) for o, f in zip(rr["obj_id"], rr["condition_frame"], strict=True)})
        lat = []
        for o, f in keys:
            g = rr[(rr["obj_id"] == o) & (rr["condition_frame"] == f)]
            ack = g["time_ack"]
            lat.append(float(np.max(ack) - g["frame_time"][0]) if np.all(np.isfinite(ack)) else math.nan)
        per_out = {}
        for name in sorted({n.decode() for n in rr["output"]}):
            g = rr[rr["output"] == name.encode()]
            failed = (g["flags"] & FIRING_FAILED) != 0
            per_out[name] = {"done": int((~failed).sum()), "failed": int(failed.sum()),
                             "late": int(np.sum(np.char.startswith(g["error"], b"late"))),
                             "latency_ms": percentiles_ms(g["time_ack"] - g["frame_time"])}
        out[rule] = {"fired": len(keys), "latency_ms": percentiles_ms(lat), "outputs": per_out}
    return out


STAGES = ("trigger_to_estimate", "estimate_to_queued", "queued_to_worker", "worker_to_sent", "sent_to_ack",
          "trigger_to_ack")


def stage_latencies(stages: Any, rule: str) -> dict[str, dict[str, dict[str, float]]]:
    """Per output of `rule`: P50/P99 (ms) of each stage from the frame's trigger to the device's
    acknowledgement (the engine's `stages` rows: rule, output, frame, trigger, estimate, queued, taken by
    the worker, sent, acknowledged host times)."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    rows = [s for s in stages if s[0] == rule]
    for name in sorted({s[1] for s in rows}):
        a = np.array([s[3:] for s in rows if s[1] == name], dtype=float).reshape(-1, 6)
        d = {k: percentiles_ms(a[:, i + 1] - a[:, i]) for i, k in enumerate(STAGES[:-1])}
        d[STAGES[-1]] = percentiles_ms(a[:, 5] - a[:, 0])
        out[name] = d
    return out


def send_split(sends: Any, rule: str) -> dict[str, dict[str, dict[str, float]]]:
    """Per output of `rule` whose device stamps `Output.written`: P50/P99 (ms) of sent -> written and
    written -> acknowledged. For Modbus TCP, CAN and UDP, written is when the send call returned: the
    first part is the client library's own work (pymodbus building the request) and the send, the
    second the link and the device (for Modbus TCP: loopback and the server's answer). HID, USB, RTU and
    Python hooks stamp it before their transfer (so the tracking thread does not wait for it): for them
    the second part is the whole transfer. Rows: the engine's `sends` (rule, output, sent, written,
    acknowledged host times)."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    rows = [s for s in sends if s[0] == rule]
    for name in sorted({s[1] for s in rows}):
        a = np.array([s[2:] for s in rows if s[1] == name], dtype=float).reshape(-1, 3)
        out[name] = {"sent_to_written": percentiles_ms(a[:, 1] - a[:, 0]),
                     "written_to_ack": percentiles_ms(a[:, 2] - a[:, 1])}
    return out
