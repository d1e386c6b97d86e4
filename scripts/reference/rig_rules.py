"""The rig file's and the rules file's reference pages (flytrack_host.rig.RigConfig,
flytrack_host.actuation.rules.RuleSet): their intros and hand-picked examples, the shared tables of the
rules file (a region, a range, a target), and the output kinds an action can drive."""

from __future__ import annotations

import typing
from pathlib import Path
from typing import Any

from .common import _cell
from .models import ModelDocs, model_page

REPO = Path(__file__).resolve().parents[2]  # scripts/reference/ is two folders below the repository


RIG_INTROS = {
    "": "Keys at the top of the file, before the first `[table]` header: TOML puts a key written below a "
        "header in that table (`rules = ...` under the last `[[cameras]]` would be read as that camera's key, "
        "and refused).",
    "cameras": "One table per camera. Every camera needs its own `name` and `index`.",
    "trigger": "The trigger box that clocks the cameras (`flytrack run` opens it before anything is recorded).",
    "host": "What the host listens on and sends to, and how it times frames.",
    "tracking": "Parameters of the 3D tracker. The defaults are Braid's (flydra's successor); change them "
                "only with a reason, and try the change offline first with `flytrack retrack --set NAME=VALUE`.",
    "recording": "Where recordings go and how often they reach the disk.",
    "actuators": "Devices that closed-loop rules drive (see [the rules file](rules-file.md)). Which keys "
                 "apply depends on `kind`; the description of each says which kind it is for.",
}
RIG_EXAMPLES: dict[str, Any] = {
    "calibration": "calibration.xml",
    "rules": "closed_loop.toml",
    "cameras.calibration_id": "Basler_21234567",
    "cameras.kind": "dvs",
    "actuators.baud": 19200,
    "actuators.bitrate": 500000,
    "actuators.vendor_id": 0x16C0,
    "actuators.product_id": 0x05DF,
    "actuators.latency_ms": 2.0,
    "host.control_port": 7001,
}

RULES_SHARED = {"Region": "region", "Box": "region.box", "Cylinder": "region.cylinder", "Sphere": "region.sphere",
                "Polygon": "region.polygon", "_Range": "range", "Target": "target"}
RULES_INTROS = {
    "": "The file is a list of `[[rules]]`.",
    "rules": "One table per rule.",
    "rules.when": "The condition: every part given must hold on the object (AND); give at least one of "
                  "`inside`, `outside`, `speed_m_s`, `altitude_m`, `distance_m`, `closing_speed_m_s`, "
                  "`turn_rate_deg_s`. `hold_ms` and `after_false_ms` give it a history.",
    "rules.actions": "One table per thing to do when the rule fires. `output` names an `[[actuators]]` entry "
                     "of the rig file; the other keys depend on that actuator's `kind` (the description of "
                     "each says which kind takes it; `flytrack rules check --rig RIG` refuses a key the "
                     "kind does not take).",
    "region": "A region (for `inside` and `outside`) is exactly one of `box`, `cylinder`, `sphere`, "
              "`polygon`, written as an inline table: `inside = { box = { min = [...], max = [...] } }`.",
    "region.box": "An axis-aligned box: every coordinate between `min` and `max`.",
    "region.cylinder": "A vertical cylinder: within `radius` of the axis through `center`, with z in `z`.",
    "region.sphere": "Within `radius` of `center`.",
    "region.polygon": "Inside the floor plan (even-odd rule) with z in `z`.",
    "range": "A range (for `speed_m_s`, `altitude_m`, `turn_rate_deg_s` and a cylinder's or polygon's `z`) "
             "is `[min, max]` or `{ min = ..., max = ... }`; a side left out is unbounded.",
    "target": "A target (for `distance_m` and `closing_speed_m_s`) is exactly one of `point` or `post`, "
              "with the range the quantity must be in: `distance_m = { post = [0.0, 0.0], max = 0.05 }`.",
}
RULES_EXAMPLES: dict[str, Any] = {
    "rules.when.outside": {"cylinder": {"center": [0.0, 0.0], "radius": 0.1}},
    "rules.objects": "any",
    "rules.armed_after_s": 5.0,
    "rules.armed_until_s": 600.0,
    "rules.max_per_minute": 120,
    "rules.actions.level": 1,
    "rules.actions.register": 40,
    "rules.actions.extended": False,
    "rules.actions.report_id": 0,
    "rules.actions.request_type": 0x40,
    "rules.actions.request": 1,
    "rules.actions.w_value": 1,
    "rules.actions.w_index": 0,
    "rules.actions.endpoint": 1,
    "rules.actions.payload": "{rule} {obj_id} {frame} {x} {y} {z}",
    "rules.actions.params": {"channel": 2},
    "rules.when.speed_m_s": [0.05, 1.0],
    "rules.when.altitude_m": {"min": 0.05},
    "rules.when.distance_m": {"post": [0.0, 0.0], "max": 0.05},
    "rules.when.closing_speed_m_s": {"point": [0.0, 0.0, 0.1], "min": 0.2},
    "rules.when.turn_rate_deg_s": {"min": 500.0},
    "rules.when.hold_ms": 50.0,
    "region.box.min": [0.0, -0.2, -0.1],
    "region.box.max": [0.15, 0.2, 0.4],
    "region.cylinder.center": [0.0, 0.0],
    "region.cylinder.radius": 0.05,
    "region.cylinder.z": [0.0, 0.3],
    "region.sphere.center": [0.0, 0.0, 0.15],
    "region.sphere.radius": 0.03,
    "region.polygon.points": [[0.0, 0.0], [0.1, 0.0], [0.05, 0.1]],
    "region.polygon.z": {"max": 0.2},
    "range.min": 0.05,
    "range.max": 1.0,
    "target.point": [0.0, 0.0, 0.1],
    "target.post": [0.0, 0.0],
    "target.min": 0.0,
    "target.max": 0.05,
}


def rig_docs() -> ModelDocs:
    from flytrack_host.rig import RigConfig

    return ModelDocs(RigConfig, [REPO / "examples" / "rig.toml"], {}, RIG_EXAMPLES, RIG_INTROS)


def rules_docs() -> ModelDocs:
    from flytrack_host.actuation.rules import RuleSet

    return ModelDocs(RuleSet, [REPO / "examples" / "closed_loop.toml"], RULES_SHARED, RULES_EXAMPLES, RULES_INTROS)


def rig_page() -> str:
    return model_page(
        rig_docs(), "The rig file",
        "One TOML file describes a rig: its cameras and where their feature datagrams come from, the "
        "trigger box, the calibration, the tracking parameters, where recordings go and the devices "
        "closed-loop rules drive. `flytrack run RIG.toml` runs it; `flytrack rig check RIG.toml` "
        "checks it and names the file, the field and the fix of every problem. Paths in it are "
        "relative to the rig file's folder. A key the file does not know is an error (a misspelt key "
        "never passes silently).",
        "A complete, commented example is `examples/rig.toml` in the repository; the examples below "
        "are taken from it where it has the key.")


def output_kinds() -> list[tuple[str, list[str], str, str]]:
    """(kind, the action keys it takes, what the actuator's `address` is, what its acknowledgement is)
    for every output kind the rig file allows."""
    import importlib

    from flytrack_host.actuation.devices.base import Output
    from flytrack_host.actuation.rules import KIND_FIELDS
    from flytrack_host.rig import _ADDRESS_NEEDED, ActuatorKind

    ack: dict[str, str] = {}
    for mod in ("trigger_pulse", "modbus", "can_bus", "hid", "usb", "udp", "python_hook"):
        m = importlib.import_module(f"flytrack_host.actuation.devices.{mod}")
        for obj in vars(m).values():
            if isinstance(obj, type) and issubclass(obj, Output) and obj is not Output:
                ack[obj.kind] = obj.ack_means
    address = dict(_ADDRESS_NEEDED, trigger_pulse="not used (the rig's trigger box)",
                   hid="the device path hidapi lists, or leave it out and give vendor_id and product_id",
                   usb="not used: give vendor_id and product_id")
    return [(k, sorted(KIND_FIELDS[k]), address.get(k, ""), ack.get(k, "")) for k in typing.get_args(ActuatorKind)]


def rules_page() -> str:
    kinds = ["## Output kinds {#output-kinds}", "",
             "An action's keys besides `output` depend on the kind of the actuator it names (the rig file's "
             "`[[actuators]]` `kind`). The acknowledgement is the time recorded as `time_ack` in "
             "`actuation_firings`.", "",
             "| kind | action keys it takes | the actuator's `address` | acknowledged when |", "|---|---|---|---|"]
    for kind, keys, addr, ack in output_kinds():
        kinds.append(f"| `{kind}` | {', '.join(f'[`{k}`](#rules-actions-{k})' for k in keys)} | {_cell(addr)} | "
                     f"{_cell(ack)} |")
    return _rules_fields_page() + "\n" + "\n".join(kinds) + "\n"


def _rules_fields_page() -> str:
    return model_page(
        rules_docs(), "The rules file",
        "A rules file says what to watch on each tracked object and what to drive when it happens. "
        "The rig file names it (`rules = \"closed_loop.toml\"`), or `flytrack run RIG.toml --rules FILE` "
        "does. `flytrack rules check FILE --rig RIG.toml` names the file, the rule and the field of "
        "every problem. Positions are in the calibration's world frame, in metres (z up after "
        "`flytrack calibrate align`).",
        "A complete example is `examples/closed_loop.toml` in the repository; the examples below are "
        "taken from it where it has the key.")
