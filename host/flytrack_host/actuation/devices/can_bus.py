"""CAN frames through python-can (socketcan on a rig; virtual and udp_multicast in tests and the demo).

CAN's acknowledgement is a bit the receiving controllers set on the wire, which the host's API does
not report per frame: `time_ack` is when `Bus.send` returned (the frame was handed to the controller,
or put on the bus for the virtual and UDP interfaces).
"""

from __future__ import annotations

from flytrack_host.actuation.devices.base import Done, Job, Output, OutputError
from flytrack_host.util import hostclock


class CanOutput(Output):
    kind = "can"
    ack_means = "Bus.send returned: the frame was handed to the bus (CAN acknowledges on the wire, unreported)"

    def __init__(self, *args: object, **kw: object):
        super().__init__(*args, **kw)  # type: ignore[arg-type]
        self.bus = None

    def _connect(self) -> None:
        import can

        kw: dict = {"bitrate": self.cfg.bitrate} if self.cfg.bitrate else {}
        channel = self.cfg.address
        if self.cfg.interface == "udp_multicast" and channel.count(":") == 1:  # GROUP:PORT (IPv4)
            channel, port = channel.split(":")
            kw["port"] = int(port)
        try:
            self.bus = can.Bus(interface=self.cfg.interface, channel=channel, **kw)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise OutputError(f"cannot open CAN {self.cfg.interface} channel {self.cfg.address}: {exc}") from None

    def _perform(self, job: Job) -> Done:
        import can

        a = job.action
        if self.bus is None:
            raise OutputError("not connected")
        msg = can.Message(arbitration_id=int(a.can_id or 0), data=bytes(a.data or []), is_extended_id=a.extended)
        t0 = hostclock.now()
        try:
            self.bus.send(msg, timeout=self.cfg.timeout_s)
        except can.CanError as exc:
            raise OutputError(f"CAN send failed: {exc}") from None
        t1 = hostclock.now()
        self.written()
        return Done(t0, t1)

    def _close(self) -> None:
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None
