"""The DVS USB bridge firmware (firmware/dvs_usb) run in simavr: build, play an AER stream, read the words."""

from .simulator import (
    BridgeRun,
    BridgeStatus,
    aer_events,
    build,
    control_request,
    run_bridge,
    tools_available,
)

__all__ = ["BridgeRun", "BridgeStatus", "aer_events", "build", "control_request", "run_bridge", "tools_available"]
