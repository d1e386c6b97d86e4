"""How the demo scores the closed loop against ground truth: matching firings to true entries, the goals."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from flytrack_host.actuation.rules import load_rules
from flytrack_host.sim.closed_loop import closed_loop_line, expected_firings, goal_checks, match
from flytrack_host.sim.flight import simulate_flight

EXAMPLE = Path(__file__).resolve().parents[3] / "examples" / "closed_loop.toml"


def test_match_pairs_closest_first_and_counts_misses_and_false_fires() -> None:
    errs, missed, false = match([12, 50, 300], [10, 49, 200], window=5)
    assert sorted(errs) == [1, 2] and missed == 1 and false == 1
    assert match([], [5], 3) == ([], 1, 0)
    assert match([5], [], 3) == ([], 0, 1)


def test_expected_entries_from_ground_truth() -> None:
    gt = simulate_flight(3, 2.0, 100.0, seed=0)
    rule = load_rules(EXAMPLE).rules[0]
    exp = expected_firings(rule, gt)
    assert exp and all(0 < f < gt.n_frames for f, _ in exp)
    lo, hi = np.array(rule.when.inside.box.min), np.array(rule.when.inside.box.max)
    for f, a in exp:  # inside at the entry frame, outside the frame before
        assert np.all((gt.pos[f, a] >= lo) & (gt.pos[f, a] <= hi))
        assert not np.all((gt.pos[f - 1, a] >= lo) & (gt.pos[f - 1, a] <= hi))


def _act(**kw: float) -> dict:
    d = {"fired": 5, "expected": 5, "missed": 0, "false_fires": 0, "frame_error_max": 1.0,
         "frame_error_max_no_prediction": 3.0, "latency_ms_p50": 1.5, "latency_ms_p99": 4.0,
         "frame_errors": [0, -1, 1], "frame_errors_no_prediction": [3, 2]}
    d.update(kw)
    return {"rules": {"enters_box": d}}


def test_goals_and_summary_line() -> None:
    assert all(ok for *_, ok in goal_checks(_act()))
    failed = {name for name, _, _, ok in goal_checks(_act(missed=1, frame_error_max=2.0, latency_ms_p99=math.nan))
              if not ok}
    assert failed == {"closed loop missed + false fires", "closed loop pulse frame error", "closed loop ack P99 (ms)"}
    # No entry in the flight at all: the count goal is not met (nothing was shown).
    assert not goal_checks(_act(expected=0, fired=0))[0][3]
    assert goal_checks({}) == []
    assert closed_loop_line(_act()) == ("5/5, 0 miss, 0 false",
                                        "frame err -1..+1 (+2..+3 unpredicted); ack P50/P99 1.5/4.0 ms")


def test_latency_by_output_is_each_devices_own_ack() -> None:
    from flytrack_host.recording.schema import FIRINGS
    from flytrack_host.sim.closed_loop import latency_by_output

    rows = np.zeros(6, dtype=FIRINGS)
    rows["output"] = [b"valve", b"can", b"hscam"] * 2
    rows["kind"] = [b"modbus", b"can", b"trigger_pulse"] * 2
    rows["frame_time"] = [10.0] * 3 + [20.0] * 3
    # Modbus answers 1 and 3 ms after the trigger, CAN 0.5 and 0.5, the pulse's ACK 4 and 6 ms; a
    # failed write (no ack) is left out, not counted as zero.
    rows["time_ack"] = [10.001, 10.0005, 10.004, 20.003, 20.0005, 20.006]
    d = latency_by_output(rows)
    assert sorted(d) == ["can", "hscam", "valve"]
    assert d["valve"]["kind"] == "modbus" and d["valve"]["n"] == 2
    assert math.isclose(d["valve"]["p50"], 2.0, abs_tol=1e-6)
    assert math.isclose(d["can"]["p99"], 0.5, abs_tol=1e-6)
    assert math.isclose(d["hscam"]["p50"], 5.0, abs_tol=1e-6)
    rows["time_ack"][0] = np.nan
    assert latency_by_output(rows)["valve"]["n"] == 1
