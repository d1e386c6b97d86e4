"""The closed-loop rules file: what to watch on each live object and what to drive when it happens.

    [[rules]]
    name = "enters_box"
    objects = "any"                  # any | first (the oldest live track) | a track id
    cooldown_s = 1.0                 # at most one firing a second, whichever object
    [rules.when]
    inside = { box = { min = [-0.05, -0.05, 0.05], max = [0.05, 0.05, 0.15] } }
    hold_ms = 0                      # true this long ...
    after_false_ms = 300             # ... after at least this long false (an *entry*)
    [[rules.actions]]
    output = "hscam"                 # an actuator of the rig file

`load_rules` validates the file with pydantic; every problem is a `RulesError` line naming the file,
the rule (by name when it has one) and the field. `bind_rules` then checks the actions against the
rig's actuators (an unknown output, a field the output's kind does not take) the same way.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Annotated, Any

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, field_validator, model_validator

from flytrack_host.rig import ActuatorConfig


class RulesError(Exception):
    """A rules file that cannot be used; `str()` is one problem per line, each naming file and rule."""

    def __init__(self, path: Path | str, problems: list[str]):
        self.path = Path(path)
        self.problems = problems
        super().__init__("\n".join(f"{self.path}: {p}" for p in problems))


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _finite(v: float) -> float:
    if not math.isfinite(v):
        raise ValueError(f"{v} is not a finite number")
    return v


Finite = Annotated[float, BeforeValidator(lambda v: _finite(float(v)) if isinstance(v, int | float) else v)]
Vec3 = Annotated[tuple[Finite, Finite, Finite], Field(description="x, y, z in metres")]
Vec2 = Annotated[tuple[Finite, Finite], Field(description="x, y in metres")]


def _range_input(v: Any) -> Any:
    if isinstance(v, list | tuple):
        if len(v) != 2:
            raise ValueError("a range is [min, max] or { min = ..., max = ... }")
        return {"min": v[0], "max": v[1]}
    return v


class _Range(_Strict):
    min: Finite = Field(-math.inf, description="lowest value that holds, in the unit of the quantity")
    max: Finite = Field(math.inf, description="highest value that holds, in the unit of the quantity")

    @model_validator(mode="after")
    def _order(self) -> _Range:
        if self.min > self.max:
            raise ValueError(f"min {self.min} is above max {self.max}")
        return self


Range = Annotated[_Range, BeforeValidator(_range_input)]


class Box(_Strict):
    min: Vec3
    max: Vec3

    @model_validator(mode="after")
    def _order(self) -> Box:
        if any(a >= b for a, b in zip(self.min, self.max, strict=True)):
            raise ValueError(f"box min {list(self.min)} must be below max {list(self.max)} on every axis")
        return self


class Cylinder(_Strict):
    center: Vec2 = Field(description="axis position (x, y); the axis is vertical")
    radius: float = Field(gt=0, description="radius about the axis, metres")
    z: Range = Field(default_factory=_Range, description="height range of the cylinder (z), metres; none: all heights")


class Sphere(_Strict):
    center: Vec3
    radius: float = Field(gt=0, description="radius, metres")


class Polygon(_Strict):
    points: list[Vec2] = Field(min_length=3, description="corners (x, y) of the floor plan, in order")
    z: Range = Field(default_factory=_Range, description="height range of the prism (z), metres; none: all heights")


class Region(_Strict):
    box: Box | None = Field(None, description="an axis-aligned box between two corners")
    cylinder: Cylinder | None = Field(None, description="a vertical cylinder")
    sphere: Sphere | None = Field(None, description="a ball about a centre")
    polygon: Polygon | None = Field(None, description="a floor plan (x, y) extruded over a height range")

    @model_validator(mode="after")
    def _one(self) -> Region:
        given = [k for k in ("box", "cylinder", "sphere", "polygon") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(f"a region is exactly one of box, cylinder, sphere, polygon (got {given or 'none'})")
        return self


class Target(_Strict):
    """A point, or a vertical post (a line through (x, y)), with the range a quantity must be in."""

    point: Vec3 | None = Field(None, description="a point (x, y, z), metres")
    post: Vec2 | None = Field(None, description="a vertical post through (x, y), metres: distances are horizontal")
    min: Finite = Field(-math.inf, description="lowest value that holds (m for distance_m, m/s for closing_speed_m_s)")
    max: Finite = Field(math.inf, description="highest value that holds (m for distance_m, m/s for closing_speed_m_s)")

    @model_validator(mode="after")
    def _one(self) -> Target:
        if (self.point is None) == (self.post is None):
            raise ValueError("give exactly one of point = [x, y, z] or post = [x, y]")
        if self.min > self.max:
            raise ValueError(f"min {self.min} is above max {self.max}")
        return self


class Condition(_Strict):
    """All given parts must hold (AND)."""

    inside: Region | None = Field(None, description="the object is inside this region")
    outside: Region | None = Field(None, description="the object is outside this region")
    speed_m_s: Range | None = Field(None, description="the object's speed is in this range, m/s")
    altitude_m: Range | None = Field(None, description="the object's height z is in this range, metres")
    distance_m: Target | None = Field(None, description="the object's distance to a point or post is in the "
                                      "target's range, metres")
    closing_speed_m_s: Target | None = Field(None, description="the object's speed towards a point or post is in "
                                             "the target's range, m/s (negative: moving away)")
    turn_rate_deg_s: Range | None = Field(None, description="the angle between the object's successive velocities, "
                                          "per second, is in this range, deg/s")
    hold_ms: float = Field(0.0, ge=0, description="the condition holds this long before the rule fires")
    after_false_ms: float = Field(0.0, ge=0, description="... after it was false at least this long")

    @model_validator(mode="after")
    def _some(self) -> Condition:
        parts = ("inside", "outside", "speed_m_s", "altitude_m", "distance_m", "closing_speed_m_s", "turn_rate_deg_s")
        if all(getattr(self, p) is None for p in parts):
            raise ValueError(f"a condition needs at least one of {', '.join(parts)}")
        return self


class Action(_Strict):
    """One thing to do when the rule fires; which fields apply depends on the output's kind."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    output: str = Field(min_length=1, description="name of an actuator of the rig file")
    width_ms: float | None = Field(None, gt=0, description="trigger_pulse: pulse width (default 1 ms)")
    level: int | None = Field(None, ge=0, le=1, description="trigger_pulse on channels 1-3: set the line")
    coil: int | None = Field(None, ge=0, le=0xFFFF, description="modbus: coil address")
    # `register` in the file; BaseModel has a `register` attribute, so the field itself is `reg`.
    reg: int | None = Field(None, alias="register", ge=0, le=0xFFFF, description="modbus: holding register address")
    value: int | None = Field(None, ge=0, le=0xFFFF, description="modbus: value to write (coil: 0 or 1)")
    can_id: int | None = Field(None, ge=0, le=0x1FFFFFFF, description="can: arbitration id")
    extended: bool = Field(False, description="can: 29-bit id")
    data: list[int] | None = Field(None, description="can/hid/usb: payload bytes")
    report_id: int | None = Field(None, ge=0, le=255, description="hid: output report id")
    request_type: int | None = Field(None, ge=0, le=255, description="usb: control transfer bmRequestType")
    request: int | None = Field(None, ge=0, le=255, description="usb: control transfer bRequest")
    w_value: int | None = Field(None, ge=0, le=0xFFFF, description="usb: control transfer wValue")
    w_index: int | None = Field(None, ge=0, le=0xFFFF, description="usb: control transfer wIndex")
    endpoint: int | None = Field(None, ge=0, le=255, description="usb: bulk OUT endpoint (instead of control)")
    payload: str | None = Field(None, description="udp: text, with {rule} {obj_id} {frame} {x} {y} {z}")
    params: dict[str, Any] = Field(default_factory=dict, description="python: keyword arguments of the hook")

    @model_validator(mode="after")
    def _bytes(self) -> Action:
        if self.data is not None and any(not 0 <= b <= 255 for b in self.data):
            raise ValueError("data must be bytes: integers 0..255")
        return self


class Rule(_Strict):
    name: str = Field(min_length=1, max_length=32, pattern=r"^[A-Za-z0-9_.\-]+$",
                      description="the rule's name (letters, digits, _ . -; at most 32), in logs and recordings")
    when: Condition = Field(description="what must hold on an object for the rule to fire")
    actions: list[Action] = Field(default_factory=list, description="what to drive when the rule fires")
    objects: str | int = Field("any", description="any object, the oldest track (first), or a track id")
    cooldown_s: float = Field(0.0, ge=0, description="no firing within this long of the last one")
    max_per_minute: float | None = Field(None, gt=0, description="at most this many firings in any 60 s")
    armed_after_s: float = Field(0.0, ge=0, description="arming window: seconds after the run started ...")
    armed_until_s: float | None = Field(None, gt=0, description="... until this many seconds (none: forever)")
    dry_run: bool = Field(False, description="record when the rule would fire; send nothing")
    predict: bool = Field(True, description="evaluate on the state predicted to the frame the action reaches")
    max_predict_ms: float = Field(
        50.0, ge=0, le=1000, description="predict at most this far ahead; when the action can only land later "
        "(a stalled host), the rule is judged at this horizon rather than on a long extrapolation")

    @field_validator("objects", mode="before")
    @classmethod
    def _objects(cls, v: object) -> object:
        if v in ("any", "first") or (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
            return v
        raise ValueError(f"objects is \"any\", \"first\" or a track id (an integer >= 0), not {v!r}")

    @model_validator(mode="after")
    def _window(self) -> Rule:
        if self.armed_until_s is not None and self.armed_until_s <= self.armed_after_s:
            raise ValueError("armed_until_s must be after armed_after_s")
        if not self.actions and not self.dry_run:
            raise ValueError("a rule needs at least one [[rules.actions]] (or dry_run = true)")
        return self


class RuleSet(_Strict):
    rules: list[Rule] = Field(min_length=1, description="the rules, each evaluated on every tracked frame")

    @model_validator(mode="after")
    def _unique(self) -> RuleSet:
        names = [r.name for r in self.rules]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"rule names {dup} are used twice; every rule needs its own name")
        return self


def _where(data: dict, loc: tuple) -> str:
    """Location of a validation error, with the rule's name when it has one: rules[0] 'enters_box'.when."""
    out = ""
    node: Any = data
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
            if isinstance(node, list) and part < len(node):
                node = node[part]
                if isinstance(node, dict) and isinstance(node.get("name"), str) and out.startswith("rules["):
                    if out.count("[") == 1:
                        out += f" {node['name']!r}"
            else:
                node = None
        else:
            out += f".{part}" if out else str(part)
            node = node.get(part) if isinstance(node, dict) else None
    return out or "(top level)"


def parse_rules(data: dict, path: Path | str = "<rules>") -> RuleSet:
    try:
        return RuleSet.model_validate(data)
    except ValidationError as exc:
        problems = []
        for err in exc.errors():
            loc = tuple(p for p in err["loc"] if not (isinstance(p, str) and p.startswith(("function-", "tuple["))))
            msg = err["msg"].removeprefix("Value error, ")
            hint = " (remove it or check its spelling)" if err.get("type") == "extra_forbidden" else ""
            problems.append(f"{_where(data, loc)}: {msg}{hint}")
        raise RulesError(path, problems) from None


def load_rules(path: Path | str) -> RuleSet:
    from flytrack_host.rig import read_toml_file

    path = Path(path)
    data, problem = read_toml_file(path, "rules", "examples/closed_loop.toml")
    if data is None:
        raise RulesError(path, [problem or "unreadable"])
    return parse_rules(data, path)


# Fields of an action each output kind takes (besides `output`).
KIND_FIELDS: dict[str, set[str]] = {
    "trigger_pulse": {"width_ms", "level"},
    "modbus": {"coil", "register", "value"},
    "can": {"can_id", "extended", "data"},
    "hid": {"report_id", "data"},
    "usb": {"request_type", "request", "w_value", "w_index", "endpoint", "data"},
    "udp": {"payload"},
    "python": {"params"},
}


def _action_problem(a: Action, kind: str, act: ActuatorConfig) -> str | None:
    given = {"register" if k == "reg" else k for k in a.model_fields_set if k != "output"}
    extra = given - KIND_FIELDS[kind]
    if extra:
        takes = ", ".join(sorted(KIND_FIELDS[kind]))
        return f"{', '.join(sorted(extra))} do(es) not apply to a {kind} output (it takes {takes})"
    if kind == "trigger_pulse":
        if act.channel == 0 and a.level is not None:
            return "channel 0 takes exact pulses (width_ms); `level` is for the stimulus lines 1-3"
        if act.channel != 0 and a.level is None:
            return f"output channel {act.channel} can only be set (level = 0 or 1); exact pulses are on channel 0"
    if kind == "modbus":
        if (a.coil is None) == (a.reg is None):
            return "give exactly one of coil or register"
        if a.value is None:
            return "give the value to write"
        if a.coil is not None and a.value not in (0, 1):
            return "a coil takes value 0 or 1"
    if kind == "can" and a.can_id is None:
        return "give can_id"
    if kind == "can" and a.data is not None and len(a.data) > 8:
        return "a classic CAN frame carries at most 8 data bytes"
    if kind == "can" and not a.extended and a.can_id is not None and a.can_id > 0x7FF:
        return f"can_id {a.can_id:#x} needs extended = true (11-bit ids end at 0x7ff)"
    if kind == "hid" and not a.data:
        return "give the report's data bytes"
    if kind == "usb":
        if a.endpoint is None and (a.request_type is None or a.request is None):
            return "give request_type and request (control transfer) or endpoint (bulk transfer)"
    return None


def _bind_problems(rules: list[Rule], actuators: list[ActuatorConfig], first: int = 0) -> list[tuple[int, str]]:
    by_name = {a.name: a for a in actuators}
    problems = []
    for i, r in enumerate(rules, start=first):
        for j, a in enumerate(r.actions):
            where = f"rules[{i}] {r.name!r}.actions[{j}]"
            act = by_name.get(a.output)
            if act is None:
                known = ", ".join(sorted(by_name)) or "none: add [[actuators]] to the rig file"
                problems.append((i, f"{where}.output: {a.output!r} is not an actuator of the rig (known: {known})"))
                continue
            why = _action_problem(a, act.kind, act)
            if why:
                problems.append((i, f"{where}: {why}"))
    return problems


def bind_rules(rules: RuleSet, actuators: list[ActuatorConfig], path: Path | str = "<rules>") -> None:
    """Check every action against the rig's actuators; raises RulesError listing all problems."""
    problems = _bind_problems(rules.rules, actuators)
    if problems:
        raise RulesError(path, [p for _, p in problems])


def load_rules_skipping(path: Path | str, actuators: list[ActuatorConfig]) -> tuple[RuleSet | None, list[str]]:
    """For a run that must go on whatever the rules file holds: every rule that validates and binds,
    and one line (file, rule, field) per problem of the others. (None, problems) when nothing is usable."""
    path = Path(path)
    try:
        return _only_good(list(enumerate(load_rules(path).rules)), actuators, path)
    except RulesError as exc:
        first = exc
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return None, [str(first)]
    raw = data.get("rules") if isinstance(data, dict) else None
    if not isinstance(raw, list):
        return None, [str(first)]
    good: list[tuple[int, Rule]] = []
    problems = []
    for i, item in enumerate(raw):
        try:
            r = parse_rules({"rules": [item]}, path).rules[0]
        except RulesError as exc:
            problems += [f"{path}: " + p.replace("rules[0]", f"rules[{i}]", 1) for p in exc.problems]
            continue
        if any(r.name == g.name for _, g in good):
            problems.append(f"{path}: rules[{i}] {r.name!r}: a rule of that name comes earlier; this one is left out")
            continue
        good.append((i, r))
    rs, more = _only_good(good, actuators, path)
    return rs, problems + more


def _only_good(rules: list[tuple[int, Rule]], actuators: list[ActuatorConfig],
               path: Path) -> tuple[RuleSet | None, list[str]]:
    keep, problems = [], []
    for i, r in rules:
        bad = _bind_problems([r], actuators, first=i)
        problems += [f"{path}: {p}" for _, p in bad]
        if not bad:
            keep.append(r)
    return (RuleSet(rules=keep) if keep else None), problems
