"""The rule engine fires the trigger firmware's pulse output (the high-speed camera line) in simavr:
the pin rises at the start of the trigger frame the animal enters, as the firings table says."""

from __future__ import annotations

import time

import numpy as np
import pytest

from flytrack_host.actuation.devices.base import Job, OutputError
from flytrack_host.actuation.devices.trigger_pulse import TriggerPulseOutput
from flytrack_host.actuation.rules import Action
from flytrack_host.recording.schema import FIRING_FRAME_EXACT
from flytrack_host.rig import ActuatorConfig
from flytrack_host.trigger import simulator
from flytrack_host.trigger.device import TriggerDevice
from flytrack_host.trigger.simulator import SimulatedTrigger, rising
from flytrack_host.util import hostclock
from flytrack_host.util.testing import missing_part

FPS = 100.0


@pytest.fixture(scope="module")
def built() -> tuple:
    if not simulator.tools_available():
        missing_part("avr-gcc / simavr not installed: the firmware cannot run here")
    return simulator.build("atmega328p")


def _entry_run(act, dev: TriggerDevice, predict: bool, v: float = 1.0) -> tuple[int, object]:  # noqa: ANN001
    """One object flying along x at `v` m/s into the box (x >= 1), frames fed in real time ~2 ms after
    each trigger pulse (as the tracker would); returns (true entry frame, engine)."""
    for _ in range(8):
        dev.query_clock()
    model = dev.model
    assert model.fitted
    rule = {"name": "enter", "predict": predict, "when": {"inside": {"box": {"min": [1, -1, -1], "max": [2, 1, 1]}}}}
    # latency_ms: margin for a loaded machine (the PULSE must reach the firmware before the frame ahead of
    # its own starts); the object flies straight, so predicting further is exact here.
    hscam = ActuatorConfig(name="hscam", kind="trigger_pulse", latency_ms=15.0)
    eng = act.engine([{"output": "hscam", "width_ms": 0.5}], [hscam],
                     FPS, context={"trigger": dev, "clock": model}, rule=rule)
    eng.start()
    f0 = int(dev.query_clock().frame_count) + 5
    n = 40
    xs = 0.7 + v / FPS * np.arange(n) + 0.003
    entry = f0 + int(np.argmax(xs >= 1.0))
    late = 0.0
    for k in range(n):
        f = f0 + k
        ft = model.frame_to_host_time(f)
        time.sleep(max(0.0, ft + 0.002 - hostclock.now()))
        now = hostclock.now()
        late = max(late, now - ft - 0.002)
        eng.on_frame(act.result(f, {1: (float(xs[k]), v)}), ft, now)
    act.wait_for(lambda: eng.firings.count >= 1, 5.0)
    eng.close()
    eng.test_late_s = late  # how much later than asked this (possibly loaded) machine gave us the frames
    return entry, eng


def test_pulse_lands_on_the_entry_frame(act, built) -> None:  # noqa: ANN001
    harness, elf = built
    with SimulatedTrigger(elf=elf, harness=harness, realtime=True) as sim:
        dev = TriggerDevice(sim.pty, reset_wait_s=0)
        dev.set_rate(FPS)
        dev.start()
        dev.start_clock_thread(0.1)  # the clock model stays fed, as in a live run (the PULSEs share the link)
        try:
            entry, eng = _entry_run(act, dev, predict=True)
            time.sleep(0.05)
            entry2, eng2 = _entry_run(act, dev, predict=False)
            time.sleep(0.05)
            # A PULSE for a frame that has begun: refused by the firmware, sent again for the earliest
            # frame, and the firing says so with the frame estimated from the trigger clock.
            out = TriggerPulseOutput(ActuatorConfig(name="hscam", kind="trigger_pulse"),
                                     {"trigger": dev, "clock": dev.model})
            now_frame = int(dev.query_clock().frame_count) - 1
            job = Job("late", 1, now_frame - 2, now_frame, hostclock.now(), hostclock.now(), (0.0, 0.0, 0.0),
                      Action(output="hscam"), True)
            late = out.perform(job)
            time.sleep(0.05)
            # One pulse waits at a time: a second one before the first has fired is refused, clearly.
            ahead = int(dev.query_clock().frame_count) + 20
            first = out.perform(Job("busy", 1, ahead - 2, ahead, hostclock.now(), hostclock.now(), (0.0, 0.0, 0.0),
                                    Action(output="hscam"), True))
            with pytest.raises(OutputError, match="one pulse at a time"):
                out.perform(Job("busy", 2, ahead - 1, ahead + 5, hostclock.now(), hostclock.now(), (0.0, 0.0, 0.0),
                                Action(output="hscam"), True))
            time.sleep(0.3)  # the first fires
        finally:
            dev.stop_clock_thread()
            dev.stop()
            dev.close()
    _, edges = sim.edges()
    trig = rising(edges, "trigger")
    pulses = rising(edges, "pulse0")
    assert len(pulses) == 4 and first.frame_exact

    def frame_of(cycle: int) -> int:  # frame n begins at the n+1-th rising edge of the trigger
        return int(np.searchsorted(np.asarray(trig), cycle, side="right")) - 1

    assert late.note.startswith(f"late: frame {now_frame} had passed") and not late.frame_exact
    # The late pulse's frame is estimated from the host clock (when the PULSE reached the firmware):
    # exact in 6 of 6 runs here; a write delayed by a busy machine can move it by one.
    assert abs(late.scheduled_frame - frame_of(pulses[2])) <= 1
    assert frame_of(pulses[3]) == ahead  # the first of the two, on its frame

    t = eng.firings.table()
    assert len(t) == 1 and t["flags"][0] & FIRING_FRAME_EXACT and not t["error"][0]
    assert int(t["scheduled_frame"][0]) == frame_of(pulses[0])  # the table says where the pin fired
    err_pred = frame_of(pulses[0]) - entry
    t2 = eng2.firings.table()
    err_nopred = frame_of(pulses[1]) - entry2
    assert int(t2["scheduled_frame"][0]) == frame_of(pulses[1])
    print(f"\npulse frame - entry frame: with prediction {err_pred:+d}, without {err_nopred:+d}; "
          f"estimate -> ACK {1e3 * (t['time_ack'][0] - t['estimate_time'][0]):.2f} ms")
    # A frame handed over late by less than a period moves the frame the pulse can reach by one at most.
    if eng.test_late_s < 1.0 / FPS:
        assert abs(err_pred) <= 1
    else:  # frames handed over a frame late or more (a loaded machine) can only reach later frames
        print(f"frames came up to {eng.test_late_s * 1e3:.1f} ms late: only checked that it is not early")
        assert err_pred >= -1
    assert err_nopred >= 2  # the firmware arms a frame ahead: the estimate's frame + 2 at the earliest
