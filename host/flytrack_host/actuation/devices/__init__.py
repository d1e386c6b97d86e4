"""One module per kind of output device; `make_output` builds the right one for an actuator."""

from __future__ import annotations

from typing import Any

from flytrack_host.actuation.devices.base import Output, OutputError
from flytrack_host.rig import ActuatorConfig


def make_output(cfg: ActuatorConfig, context: dict[str, Any] | None = None) -> Output:
    if cfg.kind == "trigger_pulse":
        from flytrack_host.actuation.devices.trigger_pulse import TriggerPulseOutput as cls
    elif cfg.kind == "modbus":
        from flytrack_host.actuation.devices.modbus import ModbusOutput as cls
    elif cfg.kind == "can":
        from flytrack_host.actuation.devices.can_bus import CanOutput as cls
    elif cfg.kind == "hid":
        from flytrack_host.actuation.devices.hid import HidOutput as cls
    elif cfg.kind == "usb":
        from flytrack_host.actuation.devices.usb import UsbOutput as cls
    elif cfg.kind == "udp":
        from flytrack_host.actuation.devices.udp import UdpOutput as cls
    elif cfg.kind == "python":
        from flytrack_host.actuation.devices.python_hook import PythonHookOutput as cls
    else:  # the rig schema allows no other kind
        raise OutputError(f"unknown output kind {cfg.kind!r}")
    return cls(cfg, context)


__all__ = ["Output", "OutputError", "make_output"]
