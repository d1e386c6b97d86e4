"""Trigger devices: the FlyTrack firmware driver, the strawlab triggerbox driver, the simavr runner,
a software stand-in, and the clock model they share.

May import: util, protocol, rig.
"""

from .clock_model import ClockModel
from .common import TriggerError

__all__ = ["ClockModel", "TriggerError"]
