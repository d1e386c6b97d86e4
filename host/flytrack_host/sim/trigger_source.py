"""The demo's frame clock: the real trigger firmware in simavr, or the software stand-in.

The host drives either exactly as `flytrack run` drives a lab's box: through the host's
`TriggerSession` (handshake, stop-and-reset, exact rate, quiet cameras, frame-0 tie, START, clock
thread feeding the synchroniser's clock). This module only provides the box and tells the simulated
cameras when each pulse happens, through a FIFO of edge lines the frame feeder follows:
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


class TriggerUnavailable(RuntimeError):
    pass


class DemoTrigger:
    """A started-on-demand trigger for the demo; see module docstring for the order of calls."""

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
        self.port = ""
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

    @property
    def kind(self) -> str:
        """The rig file's trigger kind."""
        return "flytrack" if self.mode == "simavr" else "software"

    # --- lifetime ---------------------------------------------------------------------------------
    def launch(self) -> str:
        """Start the simulated box (call after the frame feeder is following the FIFO); returns the
        serial port for the rig file ("software" for the stand-in, which the host opens itself)."""
        if self.mode == "simavr":
            from flytrack_host.trigger.simulator import SimulatedTrigger
            from flytrack_host.util.placement import run_as_hardware

            self.sim = SimulatedTrigger(elf=self.firmware, realtime=True, edge_log=self.fifo)
            self.port = self.sim.pty
            self.priority_raised = run_as_hardware(self.sim.proc.pid)
        else:
            self.port = "software"
        return self.port

    def follow_software(self, soft: Any) -> None:
        """Software mode: write a frame line for each pulse of the host's SoftwareTrigger `soft`
        (start before the trigger starts; the first pulse is frame 0)."""
        if self.mode != "software" or soft is None:
            return
        self.soft = soft
        self._bridge = threading.Thread(target=self._software_edges, name="sim-trigger-edges", daemon=True)
        self._bridge.start()

    def stop(self) -> None:
        self._bridge_stop.set()
        if self._bridge is not None:
            self._bridge.join(2.0)

    def close(self) -> None:
        self.stop()
        if self.sim is not None:
            self.sim.stop()
        _unblock_fifo_reader(self.fifo)  # in case the feeder still waits for a writer
        with contextlib.suppress(FileNotFoundError):
            self.fifo.unlink()

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
