"""The `flytrack trigger` commands and the device-restart path on the real firmware in simavr (the host
tests run them on the Python SoftwareTrigger; here the .elf built by avr-gcc answers, and its output
edges are checked)."""

from __future__ import annotations

import time

import numpy as np
from typer.testing import CliRunner

from flytrack_host.cli import app
from flytrack_host.trigger.clock_model import ClockModel
from flytrack_host.trigger.device import TriggerDevice
from flytrack_host.trigger.simulator import SimulatedTrigger, rising

runner = CliRunner()


def _falling(edges, name):  # noqa: ANN001, ANN202
    return [e.cycle for e in edges if e.signal == name and e.level == 0]


def test_cli_info_start_watch_pulse_stop_on_the_firmware(built) -> None:  # noqa: ANN001
    harness, elf = built
    with SimulatedTrigger(elf=elf, harness=harness, realtime=True) as sim:
        common = ["--port", sim.pty, "--reset-wait", "0"]
        r = runner.invoke(app, ["trigger", "info", *common])
        assert r.exit_code == 0, r.output
        # The firmware's own identity, not the Python stand-in's ("software-trigger").
        assert "name='flytrack-trigger'" in r.output and "f_cpu=16000000" in r.output, r.output
        r = runner.invoke(app, ["trigger", "start", "--fps", "120", *common])
        assert r.exit_code == 0, r.output
        assert "fps (asked 120)" in r.output
        exact = float(r.output.split(" fps (asked 120)")[0].split()[-1])
        r = runner.invoke(app, ["trigger", "watch", "--fps", "120", "--seconds", "1.0", "--period", "0.02", *common])
        assert r.exit_code == 0 and "residual" in r.output, r.output
        r = runner.invoke(app, ["trigger", "pulse", "--width-ms", "0.5", "--fps", "120", *common])
        assert r.exit_code == 0 and "pulse scheduled" in r.output, r.output
        time.sleep(0.3)  # the pulse is scheduled some frames ahead
        r = runner.invoke(app, ["trigger", "stop", *common])
        assert r.exit_code == 0, r.output
        time.sleep(0.1)
    f_cpu, edges = sim.edges()
    rises = np.array(rising(edges, "trigger"), dtype=np.int64)
    assert rises.size > 50
    # The firmware ran at the rate `start` reported, edge for edge; `watch` and `pulse` restart it at
    # the same rate, which leaves a few longer gaps and never a short (runt) period.
    periods = np.diff(rises)
    at_rate = np.abs(f_cpu / periods / exact - 1) < 1e-6
    assert at_rate.mean() > 0.95 and np.all(periods[~at_rate] > f_cpu / exact), np.unique(periods)
    # The pulse came out on its channel, 0.5 ms wide to a timer tick (prescaler 8: 0.5 us).
    up, down = rising(edges, "pulse0"), _falling(edges, "pulse0")
    assert len(up) == 1 and len(down) == 1
    assert abs((down[0] - up[0]) / f_cpu - 0.5e-3) <= 8 / f_cpu
    # After stop: no trigger edge later than the stop's effect (the last edge ends a full period).
    fall = _falling(edges, "trigger")
    assert fall and fall[-1] > rises[-1]


def test_device_restart_on_the_firmware(built) -> None:  # noqa: ANN001
    """stop_reset zeroes the firmware's frame counter; the clock model sees the restart and fits again."""
    harness, elf = built
    with SimulatedTrigger(elf=elf, harness=harness, realtime=True) as sim:
        dev = TriggerDevice(sim.pty, reset_wait_s=0, model=ClockModel(max_rtt_s=0.05))
        dev.set_rate(200.0)
        dev.start()
        for _ in range(30):
            dev.query_clock()
            time.sleep(0.01)
        before = dev.query_clock().frame_count
        assert before > 20 and dev.model.fitted
        dev.stop_reset()
        assert dev.query_clock().frame_count == 0
        restarts = dev.model.restarts
        dev.start()
        for _ in range(30):
            dev.query_clock()
            time.sleep(0.01)
        r = dev.query_clock()
        assert r.running and 0 < r.frame_count < before + 200
        assert dev.model.restarts >= restarts and dev.model.fitted
        dev.stop()
        dev.close()
    f_cpu, edges = sim.edges()
    rises = np.array(rising(edges, "trigger"), dtype=np.int64)
    gaps = np.diff(rises)
    # Two runs at 200 fps with a pause between them: one gap much longer than the period.
    period = round(f_cpu / 200)
    assert np.sum(np.abs(gaps - period) > 8) == 1, np.unique(gaps)
