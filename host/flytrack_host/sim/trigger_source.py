"""The demo's frame clock: the real trigger firmware in simavr, or the software stand-in.

Either way the host drives it as a lab's host drives a board: `TriggerDevice` on its serial port
(a pty), rate set, clock sampled into the `ClockModel` the synchroniser uses, START. The simulated
cameras learn of each trigger pulse through a FIFO of edge lines that the frame feeder follows:
- simavr: the harness writes every edge of the trigger pin, from the simulated Timer1 hardware;
- software: a bridge thread here watches the stand-in's frame counter and writes one line a frame
  (the stand-in has no pin; its frames come from the host's monotonic clock).
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from pathlib import Path
from typing import Any

from flytrack_host.trigger.clock_model import ClockModel


class TriggerUnavailable(RuntimeError):
    pass


class DemoTrigger:
    """A started-on-demand trigger for the demo; see module docstring for the order of calls."""

    kind = "flytrack"  # the rig file's trigger kind: both speak the FlyTrack serial protocol

    def __init__(self, mode: str, fps: float, out: Path, firmware: Path | None = None):
        self.fps = fps
        self.out = out
        self.fifo = out / "trigger_edges.fifo"
        with contextlib.suppress(FileNotFoundError):
            self.fifo.unlink()
        os.mkfifo(self.fifo)
        self.mode, self.note = self._choose(mode, firmware)
        self.firmware = firmware
        self.sim: Any = None
        self.soft: Any = None
        self.device: Any = None
        self.port = ""
        self.actual_fps = fps
        self._bridge: threading.Thread | None = None
        self._bridge_stop = threading.Event()
        self.bridge_frames = 0
        self.priority_raised = False

    @property
    def kind_label(self) -> str:
        return "firmware in simavr" if self.mode == "simavr" else "software trigger"

    @staticmethod
    def _choose(mode: str, firmware: Path | None) -> tuple[str, str]:
        if mode == "software":
            return "software", "software trigger requested (pure Python, same serial protocol)"
        why = _simavr_missing(firmware)
        if why is None:
            return "simavr", "trigger firmware running in simavr drives the frame clock"
        if mode == "simavr":
            raise TriggerUnavailable(f"simavr trigger requested but {why}")
        return "software", f"{why}: fell back to the software trigger (same serial protocol)"

    # --- lifetime ---------------------------------------------------------------------------------
    def launch(self) -> str:
        """Start the trigger process or stand-in (call after the frame feeder is following the FIFO);
        returns the serial port path."""
        if self.mode == "simavr":
            from flytrack_host.trigger.simulator import SimulatedTrigger

            self.sim = SimulatedTrigger(elf=self.firmware, realtime=True, edge_log=self.fifo)
            self.port = self.sim.pty
            from flytrack_host.sim.frames import raise_priority

            self.priority_raised = raise_priority(self.sim.proc.pid)
        else:
            from flytrack_host.trigger.software import SoftwareTrigger

            self.soft = SoftwareTrigger(name="flytrack-demo")
            self.port = self.soft.port
        return self.port

    def connect(self) -> ClockModel:
        """Open the device as a host would: handshake, stop and zero, set the rate; returns the clock
        model the synchroniser maps frames with (fitted once the clock thread has samples)."""
        from flytrack_host.trigger.device import TriggerDevice

        self.device = TriggerDevice(self.port, reset_wait_s=0.0)
        self.device.stop_reset()
        self.actual_fps = self.device.set_rate(self.fps)
        return self.device.model

    def start(self) -> None:
        self.device.start()
        self.device.start_clock_thread(0.1)
        if self.mode == "software":
            self._bridge = threading.Thread(target=self._software_edges, name="sim-trigger-edges", daemon=True)
            self._bridge.start()

    def stop(self) -> None:
        if self.device is not None:
            with contextlib.suppress(Exception):
                self.device.stop()
        self._bridge_stop.set()
        if self._bridge is not None:
            self._bridge.join(2.0)

    def close(self) -> None:
        self.stop()
        if self.device is not None:
            with contextlib.suppress(Exception):
                self.device.close()
        if self.sim is not None:
            self.sim.stop()
        if self.soft is not None:
            self.soft.close()
        if self.mode == "simavr" and self.sim is None:
            _unblock_fifo_reader(self.fifo)  # the feeder may still wait for a writer
        with contextlib.suppress(FileNotFoundError):
            self.fifo.unlink()

    def clock_summary(self) -> dict[str, float]:
        if self.device is None:
            return {}
        with contextlib.suppress(Exception):
            return dict(self.device.model.summary())
        return {}

    # --- the software trigger's frame edges -----------------------------------------------------
    def _software_edges(self) -> None:
        sw = self.soft
        fd = os.open(self.fifo, os.O_WRONLY)
        try:
            emitted = 0
            while not self._bridge_stop.is_set():
                frames, ticks = sw.clock()  # frames started so far; frame n began when this passed n+1
                lines = b"".join(f"{n}\n".encode() for n in range(emitted, frames))
                if lines:
                    os.write(fd, lines)
                    emitted = frames
                    self.bridge_frames = emitted
                to_next = (sw.top + 1 - ticks) * _tick_s(sw)
                time.sleep(max(5e-5, min(to_next, 0.05)))
        except BrokenPipeError:
            pass  # the feeder has all the frames it wanted
        finally:
            with contextlib.suppress(OSError):
                os.close(fd)


def _tick_s(sw: Any) -> float:
    from flytrack_host.trigger.common import PRESCALERS

    return PRESCALERS[sw.code] / sw.f_cpu


def _unblock_fifo_reader(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
        os.close(fd)


def _simavr_missing(firmware: Path | None) -> str | None:
    """Why the simavr trigger cannot run here, or None when it can."""
    try:
        from flytrack_host.trigger import simulator
    except ImportError as exc:
        return f"the simavr runner is not available ({exc})"
    if not simulator.harness_path().exists() or not (firmware or simulator.firmware_path()).exists():
        if not simulator.tools_available():
            return "the AVR tools (avr-gcc, simavr) are missing"
        return (f"the firmware or the simavr harness is not built ({simulator.firmware_path()}, "
                f"{simulator.harness_path()}); run `make build`")
    return None
