"""Real protocol peers for the demo and the tests: a pymodbus server (TCP, or RTU on a serial port)
that notes every write with its host time, and a python-can listener that notes every frame.

These are the devices' stand-ins on this machine: real pymodbus and python-can stacks on the other
end of the wire, started and stopped (killed) at will to show what a vanished device does.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import threading
import time
import tty
from dataclasses import dataclass

from flytrack_host.util import hostclock

log = logging.getLogger("flytrack.actuation.peers")


def free_tcp_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


@dataclass
class Write:
    t: float
    func_code: int
    address: int
    values: list


class ModbusPeer:
    """A Modbus server with 100 coils and 100 holding registers in a thread of its own.

    `delay_s` makes it answer slowly (a sluggish PLC); `stop()` then `start()` again is a device that
    went away and came back (same address)."""

    def __init__(self, host: str = "127.0.0.1", port: int | None = None, serial_port: str | None = None,
                 baudrate: int = 19200, delay_s: float = 0.0):
        self.host = host
        self.port = port or (None if serial_port else free_tcp_port(host))
        self.serial_port = serial_port
        self.baudrate = baudrate
        self.delay_s = delay_s
        self.writes: list[Write] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    @property
    def address(self) -> str:
        return self.serial_port or f"{self.host}:{self.port}"

    async def _action(self, func_code: int, start: int, address: int, count: int, registers: list,
                      values: list | None) -> None:
        if values is not None:
            self.writes.append(Write(hostclock.now(), func_code, address, list(values)))
        if self.delay_s:
            await asyncio.sleep(self.delay_s)

    def _device(self):  # noqa: ANN202 - pymodbus SimDevice
        from pymodbus.simulator import DataType, SimData, SimDevice

        def block(dt: DataType) -> list:
            return [SimData(0, count=100, values=0, datatype=dt)]

        bits = DataType.BITS
        return SimDevice(id=0, simdata=(block(bits), block(bits), block(DataType.REGISTERS),
                                        block(DataType.REGISTERS)), action=self._action)

    def _run(self) -> None:
        from pymodbus.server import ModbusSerialServer, ModbusTcpServer

        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)

        async def main() -> None:
            if self.serial_port:
                self._server = ModbusSerialServer(self._device(), port=self.serial_port, baudrate=self.baudrate)
            else:
                self._server = ModbusTcpServer(self._device(), address=(self.host, self.port))
            task = asyncio.create_task(self._server.serve_forever())
            for _ in range(200):  # until it listens
                if self._server.is_active():
                    break
                await asyncio.sleep(0.01)
            self._ready.set()
            await task

        try:
            loop.run_until_complete(main())
        except BaseException as exc:  # reported by start()
            self._error = exc
            self._ready.set()
        finally:
            loop.close()

    def start(self, timeout_s: float = 5.0) -> ModbusPeer:
        self._ready.clear()
        self._error = None
        self._thread = threading.Thread(target=self._run, name="modbus-peer", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s) or self._error is not None:
            raise RuntimeError(f"Modbus server on {self.address} did not start: {self._error!r}")
        if not self.serial_port:  # wait until it accepts
            end = time.monotonic() + timeout_s
            while time.monotonic() < end:
                with contextlib.suppress(OSError), socket.create_connection((self.host, self.port), 0.2):
                    break
                time.sleep(0.02)
        return self

    def stop(self) -> None:
        """Shut the server down (clients see the connection drop), like a device switched off."""
        if self._loop is not None and self._server is not None and self._thread is not None:
            with contextlib.suppress(RuntimeError):
                fut = asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop)
                with contextlib.suppress(Exception):
                    fut.result(5.0)
            self._thread.join(5.0)
        self._server = None

    def coil_writes(self, address: int = 0) -> list[Write]:
        return [w for w in self.writes if w.func_code in (5, 15) and w.address == address]


class ModbusPeerProcess:
    """A `ModbusPeer` in a process of its own (as a PLC is a machine of its own): the host process's
    threads do not share Python's GIL with the server. Its writes are read back from a log file."""

    def __init__(self, host: str = "127.0.0.1", port: int | None = None, log_dir: str | os.PathLike | None = None):
        import tempfile

        self.host = host
        self.port = port or free_tcp_port(host)
        d = str(log_dir) if log_dir is not None else tempfile.mkdtemp(prefix="flytrack-modbus-")
        self.log_path = os.path.join(d, "modbus_writes.log")
        with open(self.log_path, "w"):
            pass  # this run's writes only
        self.proc = None

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    def start(self, timeout_s: float = 10.0) -> ModbusPeerProcess:
        import subprocess
        import sys

        from flytrack_host.util import children

        # Through util.children: the server ends with this process, however it ends.
        self.proc = children.popen([sys.executable, "-m", "flytrack_host.actuation.peers", self.host,
                                    str(self.port), self.log_path], stdout=subprocess.DEVNULL,
                                   stderr=subprocess.DEVNULL)
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"Modbus server process exited with {self.proc.returncode}")
            with contextlib.suppress(OSError), socket.create_connection((self.host, self.port), 0.2):
                return self
            time.sleep(0.05)
        self.stop()
        raise RuntimeError(f"Modbus server process did not listen on {self.address} within {timeout_s} s")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5.0)
            except Exception:
                self.proc.kill()
                self.proc.wait(5.0)

    @property
    def writes(self) -> list[Write]:
        out = []
        with contextlib.suppress(FileNotFoundError), open(self.log_path) as f:
            for line in f:
                parts = line.split()
                if len(parts) >= 3:
                    out.append(Write(float(parts[0]), int(parts[1]), int(parts[2]), [int(v) for v in parts[3:]]))
        return out

    def coil_writes(self, address: int = 0) -> list[Write]:
        return [w for w in self.writes if w.func_code in (5, 15) and w.address == address]


def _serve_logged(host: str, port: int, log_path: str) -> None:
    """The child process of ModbusPeerProcess: serve until terminated, one log line per write."""
    import signal

    peer = ModbusPeer(host, port)
    f = open(log_path, "a", buffering=1)  # noqa: SIM115 - open for the life of the process

    async def action(func_code: int, start: int, address: int, count: int, registers: list,
                     values: list | None) -> None:
        if values is not None:
            # Stamped now, written to the log after the answer went out (the loop's next turn): the
            # device's answer does not wait for this stand-in's bookkeeping (a write call per request,
            # ~0.05 ms of the round trip measured here).
            line = f"{hostclock.now():.6f} {func_code} {address} {' '.join(str(int(v)) for v in values)}\n"
            asyncio.get_running_loop().call_soon(f.write, line)

    peer._action = action  # type: ignore[method-assign]
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    peer.start()
    stop.wait()
    peer.stop()
    f.close()


class PtyPair:
    """Two pseudo-terminals joined back to back by a thread: a serial line on which a Modbus RTU server
    and client talk (each opens one end by its /dev/pts path)."""

    def __init__(self) -> None:
        self.m1, s1 = os.openpty()
        self.m2, s2 = os.openpty()
        for fd in (s1, s2):
            tty.setraw(fd)
        self.port1, self.port2 = os.ttyname(s1), os.ttyname(s2)
        self._slaves = (s1, s2)  # held open so the ptys stay usable between opens
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._pump, name="pty-pair", daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        import select

        peer = {self.m1: self.m2, self.m2: self.m1}
        while not self._stop.is_set():
            ready, _, _ = select.select(list(peer), [], [], 0.1)
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                    os.write(peer[fd], data)
                except OSError:
                    continue

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        for fd in (self.m1, self.m2, *self._slaves):
            with contextlib.suppress(OSError):
                os.close(fd)


class CanListener:
    """Receives every frame on a python-can bus in a thread, with the host time it arrived."""

    def __init__(self, interface: str, channel: str, **kw: object):
        import can

        self.bus = can.Bus(interface=interface, channel=channel, **kw)
        self.frames: list[tuple[float, int, bytes]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="can-listener", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.1)
            if msg is not None:
                self.frames.append((hostclock.now(), int(msg.arbitration_id), bytes(msg.data)))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.bus.shutdown()


if __name__ == "__main__":  # python -m flytrack_host.actuation.peers HOST PORT LOG: the server process
    import sys

    _serve_logged(sys.argv[1], int(sys.argv[2]), sys.argv[3])
