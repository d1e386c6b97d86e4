"""Modbus coil or holding-register writes over TCP or RTU (pymodbus 3.x synchronous client).

The acknowledgement is the server's response to the write (FC05 / FC06), so `time_ack` is when the
device confirmed it. pymodbus's own retries are off: a lost device fails the command at once and the
worker reconnects, rather than the command arriving seconds late.
"""

from __future__ import annotations

from flytrack_host import hostclock
from flytrack_host.actuation.devices.base import Done, Job, Output, OutputError


class ModbusOutput(Output):
    kind = "modbus"
    initial_lead_s = 0.002

    def __init__(self, *args: object, **kw: object):
        super().__init__(*args, **kw)  # type: ignore[arg-type]
        self.client = None

    def _connect(self) -> None:
        from pymodbus.client import ModbusSerialClient, ModbusTcpClient

        c = self.cfg
        if c.transport == "tcp":
            host, _, port = c.address.rpartition(":")
            client = ModbusTcpClient(host, port=int(port), timeout=c.timeout_s, retries=0,
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
        t0 = hostclock.now()
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
        return Done(t0, t1)

    def _close(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None
