"""Modbus coil or holding-register writes over TCP or RTU (pymodbus 3.x synchronous client).

The acknowledgement is the server's response to the write (FC05 / FC06). Over TCP `time_ack` is the
kernel's receive stamp of that response (SO_TIMESTAMPNS, as the receiver stamps camera frames): when
the device's confirmation reached this host, not when a Python thread got round to reading it (the
GIL can hold the device thread for a while; that wait is the host's, not the device's). Over RTU, and
should the kernel give no stamp, it is when the response was read. pymodbus's own retries are off: a
lost device fails the command at once and the worker reconnects, rather than the command arriving
seconds late. The request's socket has TCP_NODELAY (no Nagle wait behind a previous segment).
"""

from __future__ import annotations

import math
import select
import socket
import struct
import time
from typing import Any

from flytrack_host.actuation.devices.base import Done, Job, Output, OutputError
from flytrack_host.util import hostclock

_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux


def _stamped_tcp_client(output: ModbusOutput, **kw: Any) -> Any:
    """A pymodbus TCP client that tells `output` when a request left (`send`) and stamps the first
    bytes of each response with the kernel's receive time (`recv`, the path pymodbus's synchronous
    transaction takes: size None, whatever is there)."""
    from pymodbus.client import ModbusTcpClient
    from pymodbus.exceptions import ConnectionException

    class StampedTcpClient(ModbusTcpClient):
        _configured: Any = None  # the socket the options below were set on

        def connect(self) -> bool:
            ok = super().connect()
            # pymodbus calls connect() before every request: the options are set once per socket.
            if ok and self.socket is not None and self.socket is not self._configured:
                self.socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                try:
                    self.socket.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
                except OSError:
                    pass  # no kernel stamps: the read time is the acknowledgement
                self._configured = self.socket
            return ok

        def send(self, request: bytes, addr: tuple | None = None) -> int:
            n = super().send(request, addr)
            output.written()
            return n

        def recv(self, size: int | None) -> bytes:
            if size is not None or self.socket is None:
                return super().recv(size)
            sock = self.socket
            sock.setblocking(False)
            r, _, _ = select.select([sock], [], [], self.comm_params.timeout_connect or 0)
            if not r:
                return b""
            now = hostclock.now()
            wall_to_host = now - time.time()  # noqa: TID251 - the kernel stamps on the real wall clock
            try:
                data, anc, _flags, _addr = sock.recvmsg(4096, 64)
            except (BlockingIOError, InterruptedError):
                return b""
            except OSError:
                self.close()
                raise ConnectionException(str(self)) from None
            if data == b"":
                self.close()
                raise ConnectionException(f"{self}: the device closed the connection")
            t = now
            for level, kind, cdata in anc:
                if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(cdata) >= 16:
                    sec, nsec = struct.unpack_from("qq", cdata)
                    k = sec + nsec * 1e-9 + wall_to_host
                    if now - 60.0 < k <= now:
                        t = k
            if not math.isfinite(output.reply_at):
                output.reply_at = t
            return data

    return StampedTcpClient(**kw)


class ModbusOutput(Output):
    kind = "modbus"
    ack_means = "the server's response to the write (FC05/FC06), kernel receive stamp over TCP"
    initial_lead_s = 0.002

    def __init__(self, *args: object, **kw: object):
        super().__init__(*args, **kw)  # type: ignore[arg-type]
        self.client = None
        self.reply_at = math.nan  # kernel stamp of the current request's response (TCP)

    def _connect(self) -> None:
        from pymodbus.client import ModbusSerialClient

        c = self.cfg
        if c.transport == "tcp":
            host, _, port = c.address.rpartition(":")
            client = _stamped_tcp_client(self, host=host, port=int(port), timeout=c.timeout_s, retries=0,
                                         reconnect_delay=0, reconnect_delay_max=0)
        else:
            client = ModbusSerialClient(c.address, baudrate=c.baud, timeout=c.timeout_s, retries=0,
                                        reconnect_delay=0, reconnect_delay_max=0)
        if not client.connect():
            client.close()
            raise OutputError(f"no Modbus {c.transport.upper()} device at {c.address}")
        self.client = client

    def _perform(self, job: Job) -> Done:
        from pymodbus.exceptions import ModbusException

        a = job.action
        client = self.client
        if client is None:
            raise OutputError("not connected")
        self.reply_at = math.nan
        t0 = hostclock.now()
        if self.cfg.transport != "tcp":
            self.written()  # RTU: a serial round trip of several ms; the tracking thread does not wait for it
        try:
            if a.coil is not None:
                rr = client.write_coil(a.coil, bool(a.value), device_id=self.cfg.unit)
            else:
                rr = client.write_register(a.reg, int(a.value or 0), device_id=self.cfg.unit)
        except ModbusException as exc:
            raise OutputError(f"Modbus write failed: {exc}") from None
        t1 = hostclock.now()
        if rr.isError():
            raise OutputError(f"device refused the write: {rr}")
        ack = self.reply_at if t0 <= self.reply_at <= t1 else t1
        return Done(t0, ack)

    def _close(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None
