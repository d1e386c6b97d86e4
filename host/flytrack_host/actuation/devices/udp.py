"""A UDP datagram to HOST:PORT, text formatted from the firing (a stimulus PC listening on a port).

UDP has no acknowledgement: `time_ack` is when `sendto` returned.
"""

from __future__ import annotations

import socket

from flytrack_host.actuation.devices.base import Done, Job, Output, OutputError
from flytrack_host.util import hostclock


class UdpOutput(Output):
    kind = "udp"
    ack_means = "sendto returned (UDP has no acknowledgement)"

    def __init__(self, *args: object, **kw: object):
        super().__init__(*args, **kw)  # type: ignore[arg-type]
        self.sock: socket.socket | None = None
        host, _, port = self.cfg.address.rpartition(":")
        self.dest = (host, int(port))

    def _connect(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def _perform(self, job: Job) -> Done:
        if self.sock is None:
            raise OutputError("not connected")
        text = job.action.payload or "{rule} {obj_id} {frame} {x:.4f} {y:.4f} {z:.4f}"
        x, y, z = job.pos
        data = text.format(rule=job.rule, obj_id=job.obj_id, frame=job.scheduled_frame, x=x, y=y, z=z).encode()
        t0 = hostclock.now()
        self.sock.sendto(data, self.dest)
        t1 = hostclock.now()
        self.written()
        return Done(t0, t1)

    def _close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None
