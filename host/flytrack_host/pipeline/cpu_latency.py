"""Keeping the CPUs out of deep idle states while a closed loop runs (Linux PM QoS).

A frame's datagrams, a device thread's command and a PLC's reply each wake a sleeping thread, often on
an idle CPU. A CPU in a deep idle state (a C-state on bare metal, a halted vCPU in a virtual machine)
takes tens to hundreds of microseconds to come back: on this project's 2-vCPU test machine a Modbus
request to a process on an idle CPU took 0.45-0.52 ms P50 with the CPUs free to sleep and 0.24-0.32 ms
with them held at 0 us exit latency; in the closed-loop demo (seeds 0-4) the rule's acknowledgement P50
went 1.80 -> 1.68 ms median and the host's trigger -> 3D P50 1.05 -> 0.85 ms.

The kernel's interface is /dev/cpu_dma_latency: write a 32-bit target (us) and keep the file open; the
request holds until it is closed (also when the process dies). The price is power: idle CPUs poll
instead of sleeping. So the host asks only while it runs, by default only when it drives devices
(`host.cpu_wake_latency_us = "auto"` in the rig file), and says whether it got it. Opening the device
needs root or write access to it (a udev rule); without, the host runs as before and says why.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

DEVICE = Path("/dev/cpu_dma_latency")


def wanted_us(setting: int | str, drives_devices: bool) -> int | None:
    """The target to ask for from the rig's `host.cpu_wake_latency_us`: "auto" is 0 when the host drives
    devices (a closed loop) and nothing otherwise, "off" nothing, a number that number."""
    if setting == "off":
        return None
    if setting == "auto":
        return 0 if drives_devices else None
    return int(setting)


class CpuWakeLatency:
    """One PM QoS request, held from `hold()` to `release()`."""

    def __init__(self, target_us: int, device: Path | str = DEVICE):
        self.target_us = int(target_us)
        self.device = Path(device)
        self._fd: int | None = None
        self.was_held = False  # held at some time (the summary's "held": during the run)
        self.note = ""

    @property
    def held(self) -> bool:
        return self._fd is not None

    def hold(self) -> str:
        """Asks for the target; returns a line for the log saying whether it is held, and if not why."""
        if self._fd is not None:
            return self.note
        try:
            fd = os.open(self.device, os.O_WRONLY)
        except OSError as exc:
            why = ("needs root or write access to it, e.g. a udev rule" if isinstance(exc, PermissionError)
                   else exc.strerror or str(exc))
            self.note = (f"CPU wake-up latency not held: cannot open {self.device} ({why}); CPUs may sleep "
                         f"deeply between frames, and waking them adds to the closed loop's latency")
            return self.note
        try:
            os.write(fd, struct.pack("i", self.target_us))
        except OSError as exc:
            os.close(fd)
            self.note = f"CPU wake-up latency not held: {self.device} refused {self.target_us} us ({exc.strerror})"
            return self.note
        self._fd = fd
        self.was_held = True
        self.note = (f"CPU wake-up latency held at {self.target_us} us ({self.device}, PM QoS) while running: "
                     "idle CPUs poll instead of sleeping deeply")
        return self.note

    def release(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            os.close(fd)

    def summary(self) -> dict[str, object]:
        """For the run's summary: what was asked, whether it was held while running, the log line."""
        return {"requested_us": self.target_us, "held": self.was_held, "note": self.note}


def current_us(device: Path | str = DEVICE) -> int | None:
    """The kernel's current aggregate target (the strictest request held), or None if unreadable."""
    try:
        fd = os.open(device, os.O_RDONLY)
    except OSError:
        return None
    try:
        data = os.read(fd, 4)
    finally:
        os.close(fd)
    return struct.unpack("i", data)[0] if len(data) == 4 else None
