from pathlib import Path

import pytest

from flytrack_host.sim.trigger_source import DemoTrigger, TriggerUnavailable


def test_missing_firmware_falls_back_to_the_software_trigger_and_says_so(tmp_path):
    t = DemoTrigger("auto", 100.0, tmp_path, firmware=Path("/nonexistent/flytrack_trigger.elf"))
    try:
        assert t.mode == "software"
        assert "software trigger" in t.note and ("not built" in t.note or "missing" in t.note)
        assert t.fifo.exists()
    finally:
        t.close()
    assert not t.fifo.exists()


def test_simavr_requested_without_firmware_is_a_clear_error(tmp_path):
    with pytest.raises(TriggerUnavailable, match="simavr"):
        DemoTrigger("simavr", 100.0, tmp_path, firmware=Path("/nonexistent/flytrack_trigger.elf"))


def test_software_trigger_edges_follow_its_frame_counter(tmp_path):
    import os
    import threading
    import time

    from flytrack_host.trigger.device import TriggerDevice
    from flytrack_host.trigger.software import SoftwareTrigger

    t = DemoTrigger("software", 200.0, tmp_path)
    lines: list[bytes] = []

    def read() -> None:
        with open(t.fifo, "rb") as f:
            lines.extend(f.read().split())

    reader = threading.Thread(target=read)
    reader.start()
    soft = SoftwareTrigger()
    dev = TriggerDevice(soft.port, reset_wait_s=0.0)
    try:
        assert t.launch() == "software" and t.kind == "software"
        dev.stop_reset()
        dev.set_rate(200.0)
        t.follow_software(soft)
        time.sleep(0.05)  # stopped: no pulses, no lines
        dev.start()
        time.sleep(0.5)
        dev.stop()
    finally:
        t.close()
        dev.close()
        soft.close()
        reader.join(5)
    frames = [int(x) for x in lines]
    assert frames == list(range(len(frames)))
    assert 60 <= len(frames) <= 110  # 0.5 s at 200 fps, give or take start-up
    assert not os.path.exists(t.fifo)
