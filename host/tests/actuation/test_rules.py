"""Rules file validation, conditions on N objects, and the per-object history (entries, gates)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from flytrack_host.actuation.conditions import closing_speed, condition_mask, point_in_polygon, region_mask
from flytrack_host.actuation.history import RuleEvaluator
from flytrack_host.actuation.prediction import StepVelocities, predict_states, reachable_frame
from flytrack_host.actuation.rules import Condition, Region, RulesError, bind_rules, load_rules, parse_rules
from flytrack_host.rig import ActuatorConfig, load_rig

ROOT = Path(__file__).resolve().parents[3]
EXAMPLE = ROOT / "examples" / "closed_loop.toml"


def _acts() -> list[ActuatorConfig]:
    return [ActuatorConfig(name="hscam", kind="trigger_pulse", channel=0),
            ActuatorConfig(name="valve", kind="modbus", address="127.0.0.1:5020"),
            ActuatorConfig(name="stimulus_can", kind="can", interface="virtual", address="demo")]


def test_example_rules_load_and_bind() -> None:
    rs = load_rules(EXAMPLE)
    assert [r.name for r in rs.rules] == ["enters_box"]
    bind_rules(rs, _acts(), EXAMPLE)


def _rules_text(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "rules.toml"
    p.write_text(text)
    return p


def test_malformed_rules_name_file_rule_and_field(tmp_path: Path) -> None:
    p = _rules_text(tmp_path, """
[[rules]]
name = "enter"
cooldown_s = -1
[rules.when]
inside = { box = { min = [0, 0, 0], max = [1, -1, 1] } }
[[rules.actions]]
output = "hscam"
""")
    with pytest.raises(RulesError) as ei:
        load_rules(p)
    msg = str(ei.value)
    assert str(p) in msg
    assert "rules[0] 'enter'.cooldown_s" in msg and "greater than or equal to 0" in msg
    assert "rules[0] 'enter'.when.inside.box" in msg and "below max" in msg


@pytest.mark.parametrize("text, expect", [
    ("[[rules]\nname=", "not valid TOML"),
    ("[[rules]]\nname = \"a\"\n[rules.when]\nspeed_m_s = [1, 2]\n", "at least one [[rules.actions]]"),
    ("[[rules]]\nname = \"a\"\ndry_run = true\n[rules.when]\n", "a condition needs at least one"),
    ("[[rules]]\nname = \"a\"\ndry_run = true\nspeling = 1\n[rules.when]\nspeed_m_s = [1, 2]\n",
     "rules[0] 'a'.speling: Extra inputs are not permitted (remove it or check its spelling)"),
    ("[[rules]]\nname = \"a\"\ndry_run = true\n[rules.when]\nspeed_m_s = [3, 2]\n", "min 3.0 is above max 2.0"),
    ("[[rules]]\nname = \"a\"\ndry_run = true\n[rules.when]\ninside = { box = { min = [0, 0, 0], max = [1, 1, 1] }, "
     "sphere = { center = [0, 0, 0], radius = 1 } }\n", "exactly one of box, cylinder, sphere, polygon"),
    ("[[rules]]\nname = \"a\"\ndry_run = true\n[rules.when]\naltitude_m = [0, nan]\n", "not a finite number"),
    ("[[rules]]\nname = \"a\"\ndry_run = true\nobjects = \"frist\"\n[rules.when]\naltitude_m = [0, 1]\n",
     "rules[0] 'a'.objects: objects is \"any\", \"first\" or a track id (an integer >= 0), not 'frist'"),
])
def test_bad_rules_files(tmp_path: Path, text: str, expect: str) -> None:
    with pytest.raises(RulesError) as ei:
        load_rules(_rules_text(tmp_path, text))
    assert expect in str(ei.value)


def test_missing_rules_file(tmp_path: Path) -> None:
    with pytest.raises(RulesError, match="file not found"):
        load_rules(tmp_path / "nope.toml")


def test_unknown_output_and_wrong_fields_named() -> None:
    rs = parse_rules({"rules": [{"name": "r", "when": {"speed_m_s": [0, 1]},
                                 "actions": [{"output": "lazer"}, {"output": "valve", "coil": 1},
                                             {"output": "hscam", "can_id": 5}]}]})
    with pytest.raises(RulesError) as ei:
        bind_rules(rs, _acts(), "x.toml")
    lines = str(ei.value).splitlines()
    assert len(lines) == 3
    assert "rules[0] 'r'.actions[0].output: 'lazer' is not an actuator of the rig (known: hscam, stimulus_can, valve)" \
        in lines[0]
    assert "actions[1]: give the value to write" in lines[1]
    assert "actions[2]: can_id do(es) not apply to a trigger_pulse output" in lines[2]


def test_rig_rules_path_and_actuator_checks(tmp_path: Path) -> None:
    base = (ROOT / "examples" / "rig.toml").read_text()
    rig = tmp_path / "rig.toml"
    rig.write_text('rules = "missing.toml"\n' + base)
    with pytest.raises(Exception, match="rules: file .*missing.toml does not exist"):
        load_rig(rig)
    rig.write_text(base + '\n[[actuators]]\nname = "valve"\nkind = "modbus"\n')
    with pytest.raises(Exception, match="needs `address`"):
        load_rig(rig)


def test_regions_vectorised() -> None:
    pos = np.array([[0.0, 0.0, 0.5], [2.0, 0.0, 0.5], [0.9, 0.0, 0.5], [0.0, 0.0, 2.0]])
    box = Region.model_validate({"box": {"min": [-1, -1, 0], "max": [1, 1, 1]}})
    assert region_mask(box, pos).tolist() == [True, False, True, False]
    sph = Region.model_validate({"sphere": {"center": [0, 0, 0.5], "radius": 1.0}})
    assert region_mask(sph, pos).tolist() == [True, False, True, False]
    cyl = Region.model_validate({"cylinder": {"center": [0, 0], "radius": 0.95, "z": [0, 1]}})
    assert region_mask(cyl, pos).tolist() == [True, False, True, False]
    # An L-shaped floor plan: the notch is outside.
    L = [[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]]
    xy = np.array([[0.5, 0.5], [1.5, 0.5], [1.5, 1.5], [0.5, 1.5], [3, 3]])
    assert point_in_polygon(xy, np.array(L, float)).tolist() == [True, True, False, True, False]


def test_condition_parts_and_nan() -> None:
    c = Condition.model_validate({"speed_m_s": [0.5, 2.0], "altitude_m": {"min": 0.1},
                                  "distance_m": {"post": [0, 0], "max": 0.5},
                                  "closing_speed_m_s": {"post": [0, 0], "min": 0.2}})
    pos = np.array([[0.3, 0, 0.2], [0.3, 0, 0.2], [0.3, 0, 0.05], [0.3, 0, 0.2], [np.nan, 0, 0.2]])
    vel = np.array([[-1.0, 0, 0], [1.0, 0, 0], [-1.0, 0, 0], [-3.0, 0, 0], [-1.0, 0, 0]])
    # towards the post / away / too low / too fast / NaN
    assert condition_mask(c, pos, vel).tolist() == [True, False, False, False, False]
    t = Condition.model_validate({"distance_m": {"point": [0, 0, 0], "max": 1}}).distance_m
    assert closing_speed(t, np.array([[1.0, 0, 0]]), np.array([[-0.5, 0, 0]]))[0] == pytest.approx(0.5)


def _eval(rule: dict, period: float = 0.01) -> RuleEvaluator:
    rs = parse_rules({"rules": [{"name": "r", "dry_run": True, **rule}]})
    return RuleEvaluator(rs.rules[0], period)


def _run(ev: RuleEvaluator, xs: np.ndarray, vx: float = 0.0, lead: int = 0) -> list[int]:
    """One object at x = xs[frame] (y = z = 0), judged `lead` frames ahead; returns firing frames."""
    out = []
    for f, x in enumerate(xs):
        st = np.array([[x, 0, 0, vx, 0, 0]])
        out += [fi.scheduled_frame for fi in ev.step(f, f + lead, np.array([1]), st)]
    return out


BOX = {"inside": {"box": {"min": [1, -1, -1], "max": [2, 1, 1]}}}


def test_entry_fires_once_per_stretch_with_history() -> None:
    xs = np.r_[np.zeros(30), np.full(10, 1.5), np.zeros(5), np.full(10, 1.5)]
    # Fires on entering (frame 30); re-entry after 50 ms outside is not an entry with after_false 100 ms.
    assert _run(_eval({"when": {**BOX, "after_false_ms": 100}}), xs) == [30]
    assert _run(_eval({"when": {**BOX, "after_false_ms": 40}}), xs) == [30, 45]
    # hold: inside for 50 ms -> fires 5 frames after entering.
    assert _run(_eval({"when": {**BOX, "hold_ms": 50}}), xs) == [35, 50]
    # An object first seen inside has no "before": no firing until it leaves and comes back.
    assert _run(_eval({"when": BOX}), np.r_[np.full(5, 1.5), np.zeros(3), np.full(3, 1.5)]) == [8]


def test_gates_cooldown_rate_arming() -> None:
    xs = np.tile(np.r_[np.zeros(5), np.full(5, 1.5)], 10)  # an entry every 100 ms: frames 5, 15, ...
    assert _run(_eval({"when": BOX}), xs) == list(range(5, 100, 10))
    ev = _eval({"when": BOX, "cooldown_s": 0.25})
    assert _run(ev, xs) == [5, 35, 65, 95]
    assert ev.suppressed == {"cooldown": 6}
    assert _run(_eval({"when": BOX, "max_per_minute": 3}), xs) == [5, 15, 25]
    assert _run(_eval({"when": BOX, "armed_after_s": 0.3, "armed_until_s": 0.6}), xs) == [35, 45, 55]


def test_objects_selection() -> None:
    ev = _eval({"when": BOX, "objects": 7})
    ids = np.array([3, 7])
    fired = []
    for f, x in enumerate(np.r_[np.zeros(5), np.full(3, 1.5)]):
        st = np.array([[x, 0, 0, 0, 0, 0], [x, 0, 0, 0, 0, 0]])
        fired += [(fi.obj_id, fi.scheduled_frame) for fi in ev.step(f, f, ids, st)]
    assert fired == [(7, 5)]
    ev = _eval({"when": BOX, "objects": "first"})
    for f, x in enumerate(np.r_[np.zeros(5), np.full(3, 1.5)]):
        fired = [fi.obj_id for fi in ev.step(f, f, ids, np.array([[x, 0, 0, 0, 0, 0]] * 2))] or fired
    assert fired == [3]


def test_prediction_fires_on_the_entry_frame() -> None:
    # x = 0.9 + 0.02 * (f - 0): crosses x = 1 between frames 5 and 6 (true entry frame 6).
    f = np.arange(20)
    xs = 0.9 + 0.0195 * f
    vx = 0.0195 / 0.01
    true_entry = int(np.argmax(xs >= 1.0))
    # An action reaching 2 frames after the estimate: without prediction it lands 2 frames late.
    ev_pred = _eval({"when": BOX})
    ev_nopred = _eval({"when": BOX, "predict": False})
    assert _run(ev_pred, xs, vx, lead=2) == [true_entry]
    assert _run(ev_nopred, xs, vx, lead=2) == [true_entry + 2]


def test_prediction_follows_a_decelerating_object() -> None:
    # Slowing from 0.3 to 0.05 m/s towards the box: the tracker's velocity state lags the change (here it
    # keeps the speed of 4 frames before), its positions do not. The entry is predicted from the last
    # position step: on the true entry frame; from the lagging velocity it would be 2 frames early.
    n = 60
    v = np.maximum(0.05, 0.3 - 0.015 * np.arange(n))  # m/s at each frame
    xs = 0.97 + np.r_[0.0, np.cumsum(v[1:] * 0.01)]
    true_entry = int(np.argmax(xs >= 1.0))
    lagging = np.r_[np.full(4, v[0]), v[:-4]]
    ev = _eval({"when": BOX})
    fired = []
    for f in range(n):
        st = np.array([[xs[f], 0, 0, lagging[f], 0, 0]])
        fired += [fi.scheduled_frame for fi in ev.step(f, f + 2, np.array([1]), st)]
    assert true_entry == 21 and fired == [true_entry]
    pred_lagging = [f + 2 for f in range(n - 2) if xs[f] + lagging[f] * 0.02 >= 1.0]
    assert pred_lagging[0] <= true_entry - 2  # what the velocity state alone would have done
    s = predict_states(np.array([[1.0, 2, 3, 1, -1, 0.5]]), 0.02, np.array([[0.5, 0, 0]]))
    assert s[0].tolist() == pytest.approx([1.01, 2, 3, 1, -1, 0.5])  # moved by `vel`, keeps its velocity


def test_step_velocities_fall_back_to_the_filter() -> None:
    sv = StepVelocities(0.01)
    st = np.array([[0.0, 0, 0, 0.2, 0, 0], [1.0, 0, 0, 0.3, 0, 0]])
    assert sv(5, np.array([1, 2]), st)[:, 0].tolist() == [0.2, 0.3]  # nothing before: the filter's
    st2 = np.array([[1.5, 0, 0, 0.3, 0, 0], [0.001, 0, 0, 0.2, 0, 0], [9.0, 0, 0, 0.7, 0, 0]])
    v = sv(6, np.array([2, 1, 3]), st2)
    # id 2 jumped 0.5 m in a frame (a new association): the filter's; id 1 stepped 1 mm: 0.1 m/s; id 3 is new.
    assert v[:, 0].tolist() == pytest.approx([0.3, 0.1, 0.7])
    assert sv(6, np.array([2, 1, 3]), st2).tolist() == v.tolist()  # the same frame again: the same answer
    assert sv(8, np.array([1]), np.array([[0.01, 0, 0, 0.4, 0, 0]]))[0, 0] == 0.4  # a frame missed: the filter's


def test_turn_rate_from_history() -> None:
    ev = _eval({"when": {"turn_rate_deg_s": {"min": 500}}})
    fired = []
    for f in range(12):
        ang = 0.0 if f < 8 else math.radians(10 * (f - 7))  # 10 degrees a frame from frame 8 = 1000 deg/s
        st = np.array([[0, 0, 0, math.cos(ang), math.sin(ang), 0]])
        fired += [fi.scheduled_frame for fi in ev.step(f, f, np.array([1]), st)]
    assert fired == [8]


def test_reachable_frame_and_prediction() -> None:
    # Estimate of frame 10 at 3 ms after its trigger, action needs 1 ms: frame 11 (starts at 10 ms).
    assert reachable_frame(10, 0.0, 0.003, 0.001, 0.01) == 11
    # ... with the firmware's one frame of arming lead: frame 12.
    assert reachable_frame(10, 0.0, 0.003, 0.011, 0.01) == 12
    assert reachable_frame(10, 0.0, 0.0125, 0.0, 0.01) == 12  # estimate itself a frame late
    assert reachable_frame(10, math.nan, 0.0, 0.0, 0.01) == 11
    s = predict_states(np.array([[1.0, 2, 3, 1, -1, 0.5]]), 0.02)
    assert s[0, :3].tolist() == pytest.approx([1.02, 1.98, 3.01])


def test_engine_forgets_histories_when_trigger_frames_restart(act) -> None:  # noqa: ANN001
    eng = act.engine([], [], rule={**act.BOX_RULE, "dry_run": True, "cooldown_s": 0.1})
    act.drive_entries(eng, 3)  # entries at frames 30, 65, 100
    assert len(eng.fires) == 3
    # The trigger re-armed (frame 0 again, a new tracker): the entry at the new frame 30 fires. Without the
    # reset the last firing "at frame 101" would keep the cooldown on until the count passed it again.
    act.drive_entries(eng, 1)
    assert [f.condition_frame for f in eng.fires] == [30, 65, 100, 30]
