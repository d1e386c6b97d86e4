"""The host's PM QoS request (pipeline/cpu_latency.py): held while a pipeline that drives devices runs,
given back when it stops, never asked by a rig without actuators, and a clear line when the kernel's
device cannot be opened. The kernel's own /dev/cpu_dma_latency is used where this process may write it
(root); its aggregate value, read back, shows the request took effect."""

from __future__ import annotations

import os

import pytest

from flytrack_host.pipeline import HostPipeline
from flytrack_host.pipeline.cpu_latency import DEVICE, CpuWakeLatency, current_us, wanted_us
from flytrack_host.rig import ActuatorConfig, RigError, parse_rig

writable = pytest.mark.skipif(not os.access(DEVICE, os.W_OK), reason=f"{DEVICE} not writable here (needs root)")


def test_auto_asks_only_for_a_closed_loop_off_never_a_number_always():
    assert wanted_us("auto", drives_devices=True) == 0
    assert wanted_us("auto", drives_devices=False) is None
    assert wanted_us("off", drives_devices=True) is None
    assert wanted_us(25, drives_devices=False) == 25


def test_the_rig_file_takes_auto_off_or_microseconds_and_names_a_bad_value(helpers):
    rig = helpers.make_rig(2)
    assert rig.host.cpu_wake_latency_us == "auto"
    d = rig.model_dump()
    for ok in ("off", 0, 50):
        d["host"]["cpu_wake_latency_us"] = ok
        assert parse_rig(d).host.cpu_wake_latency_us == ok
    for bad in ("fast", -1):
        d["host"]["cpu_wake_latency_us"] = bad
        with pytest.raises(RigError, match="cpu_wake_latency_us"):
            parse_rig(d)


def test_a_device_that_cannot_be_opened_is_said_and_nothing_is_held(tmp_path):
    missing = tmp_path / "no" / "cpu_dma_latency"
    q = CpuWakeLatency(0, device=missing)
    note = q.hold()
    assert not q.held
    assert "not held" in note and str(missing) in note
    assert q.summary() == {"requested_us": 0, "held": False, "note": note}
    q.release()  # nothing to give back: no error


@writable
def test_the_request_holds_until_released():
    before = current_us()
    assert before is not None
    q = CpuWakeLatency(123)
    assert "held at 123 us" in q.hold()
    assert q.held and current_us() == min(before, 123)
    q.release()
    assert not q.held and current_us() == before


@writable
def test_a_pipeline_driving_devices_holds_it_while_running_and_gives_it_back(helpers, tmp_path):
    before = current_us()
    assert before is not None
    d = helpers.make_rig(2).model_dump()
    d["rules"] = "rules.toml"
    d["actuators"] = [ActuatorConfig(name="valve", kind="udp", address="127.0.0.1:9").model_dump()]
    d["host"]["cpu_wake_latency_us"] = "auto"
    rig = parse_rig(d)
    pipe = HostPipeline(rig, cameras={0: None, 1: None}, tracker_factory=helpers.factory,
                        recording_path=tmp_path / "r", bind="127.0.0.1:0")
    pipe.start()
    try:
        assert current_us() == 0
        assert any("CPU wake-up latency held at 0 us" in e for e in pipe.events)
    finally:
        s = pipe.stop()
    assert current_us() == before
    assert s["cpu_wake_latency"]["requested_us"] == 0 and s["cpu_wake_latency"]["held"] is True  # while running

    plain = HostPipeline(helpers.make_rig(2), cameras={0: None, 1: None}, tracker_factory=helpers.factory,
                         record=False, bind="127.0.0.1:0")
    plain.start()
    try:
        assert current_us() == before  # tracking alone does not ask (auto)
    finally:
        s = plain.stop()
    assert s["cpu_wake_latency"] is None
