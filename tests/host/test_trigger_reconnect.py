"""A trigger board unplugged mid-run and plugged back: the README says the host re-opens the port every
2 s and, once the board answers, re-arms it. The firmware runs in simavr; the rig's port is a symlink,
as /dev/ttyUSB0 or a udev name would be, re-pointed at a second simulator (the board plugged back).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from flytrack_host.geometry.camera import Camera
from flytrack_host.pipeline import HostPipeline
from flytrack_host.rig import parse_rig
from flytrack_host.trigger import simulator
from flytrack_host.trigger.session import TriggerSession
from flytrack_host.util.testing import missing_part


def _wait(cond, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.05)
    return bool(cond())


def test_a_trigger_plugged_back_is_reopened_and_rearmed(tmp_path: Path) -> None:
    if not simulator.tools_available():
        missing_part("avr-gcc / simavr not installed: the firmware cannot run here")
    harness, elf = simulator.build("atmega328p")
    port = tmp_path / "ttyTRIGGER"
    rig = parse_rig({
        "name": "reconnect",
        "trigger": {"kind": "flytrack", "port": str(port), "fps": 100.0, "clock_query_interval_s": 0.1},
        "host": {"listen": "127.0.0.1:7000"},
        "recording": {"folder": str(tmp_path / "rec"), "flush_interval_s": 0.5},
        "cameras": [{"name": "cam0", "index": 0, "edge": "127.0.0.1"}],
    })
    cameras = {0: Camera.look_at("cam0", (1.2, 0.0, 0.5), (0.0, 0.0, 0.2), 640, 480, 500.0)}
    first = simulator.SimulatedTrigger(elf=elf, harness=harness, realtime=True)
    second = None
    os.symlink(first.pty, port)
    session = TriggerSession(rig.trigger, reset_wait_s=0.0)
    pipe = None
    try:
        session.open()
        pipe = HostPipeline(rig, cameras, clock=session.clock, fps=session.fps, hold_until_synchronized=True,
                            recording_path=tmp_path / "run.flytrack", bind="127.0.0.1:0")
        pipe.start()
        session.attach(pipe)
        session.start(pipe)
        time.sleep(0.5)
        first.proc.kill()  # unplugged
        assert _wait(lambda: session.lost_since is not None, 5.0), "the lost trigger was not noticed"
        time.sleep(2.5)  # at least one re-open fails while nothing is there
        assert session.stats.reconnects == 0 and session.lost_since is not None
        second = simulator.SimulatedTrigger(elf=elf, harness=harness, realtime=True)
        os.unlink(port)
        os.symlink(second.pty, port)  # plugged back, same name
        assert _wait(lambda: session.stats.reconnects == 1 and session.stats.rearms == 1, 10.0), (
            session.stats, "\n".join(list(pipe.events)[-8:]))
        assert session.lost_since is None
        # Re-armed: the new board runs and its pulses come at the rate set again.
        assert _wait(lambda: len(simulator.rising(second.edges()[1], "trigger")) >= 20, 10.0)
        assert any("re-opened" in ev for ev in pipe.events)
        assert "LOST" not in session.status()
    finally:
        session.stop()
        if pipe is not None:
            pipe.stop()
        first.close()
        if second is not None:
            second.close()
