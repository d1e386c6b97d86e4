"""TriggerDevice against the pure-Python SoftwareTrigger over a real pty, and the driver's errors."""

from __future__ import annotations

import os
import time
import tty

import pytest

from flytrack_host.protocol import trigger_link as tl
from flytrack_host.trigger.common import RateChoice, TriggerError, choose_rate
from flytrack_host.trigger.device import TriggerDevice
from flytrack_host.trigger.software import SoftwareTrigger


def test_driver_against_software_trigger() -> None:
    with SoftwareTrigger() as sw, TriggerDevice(sw.port, reset_wait_s=0) as dev:
        assert dev.info().name == "software-trigger"
        assert dev.set_rate(250.0) == pytest.approx(250.0)
        dev.start()
        dev.start_clock_thread(0.01)
        # At least 0.4 s of queries, longer while the fit uses fewer than 5 (a loaded host).
        t_end, t_max = time.monotonic() + 0.4, time.monotonic() + 10.0
        while time.monotonic() < t_max and (time.monotonic() < t_end or dev.model.n_samples < 5):
            time.sleep(0.05)
        dev.stop_clock_thread()
        assert dev.model.fitted and dev.model.n_samples >= 5
        assert abs(dev.model.gain - 1) < 0.05
        r = dev.query_clock()
        assert r.running and r.frame_count > 0
        ticks = dev.pulse(0, frame=r.frame_count + 50, width_s=0.0005)
        assert sw.pulses == [(r.frame_count + 50, ticks)]
        with pytest.raises(TriggerError, match="BAD_ARG"):
            dev.pulse(0, frame=0, width_s=0.0005)
        with pytest.raises(TriggerError, match="BUSY"):
            dev.set_rate(100.0)
        dev.set_output(2, 1)
        assert sw.outputs == {2: 1}
        sw.inject_event(edge=1)
        evs = dev.events()
        t_max = time.monotonic() + 5.0
        while not evs and time.monotonic() < t_max:  # the reader thread may be slow to run on a loaded host
            time.sleep(0.01)
            evs = dev.events()
        assert len(evs) == 1 and evs[0].edge == 1 and evs[0].host_time is not None
        dev._ser.write(b"\x05\x07garbage\x00\x01\x02")  # noise between requests
        assert dev.info().protocol_version == tl.SERIAL_VERSION
        dev.stop_reset()
        assert dev.query_clock().frame_count == 0


def test_missing_port_is_a_clear_error() -> None:
    with pytest.raises(TriggerError, match="does not exist"):
        TriggerDevice("/dev/flytrack-no-such-port", reset_wait_s=0)


def test_busy_port_is_a_clear_error() -> None:
    with SoftwareTrigger() as sw, TriggerDevice(sw.port, reset_wait_s=0):
        with pytest.raises(TriggerError, match="busy"):
            TriggerDevice(sw.port, reset_wait_s=0)


def test_device_speaking_something_else() -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    os.write(master, b"Hello from some other sketch\r\n" * 3)
    try:
        with pytest.raises(TriggerError, match="does not answer the FlyTrack trigger protocol"):
            TriggerDevice(os.ttyname(slave), reset_wait_s=0, timeout_s=0.2, connect_attempts=2)
    finally:
        os.close(master)
        os.close(slave)


def test_silence_at_another_baud_names_the_firmware_rate() -> None:
    """An old rig file with `baud = 115200` and a board flashed with today's firmware (1 Mbaud): the
    error says which rate the firmware talks at; at the firmware's own rate it says nothing of it."""
    from flytrack_host.rig import TriggerConfig
    from flytrack_host.trigger.device import FIRMWARE_BAUD

    assert TriggerConfig().baud == FIRMWARE_BAUD == 1_000_000
    assert TriggerConfig(kind="strawlab").baud == 115_200
    assert TriggerConfig(baud=57_600).baud == 57_600
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        with pytest.raises(TriggerError, match="the port is at 115200 baud, the FlyTrack firmware talks at 1000000"):
            TriggerDevice(os.ttyname(slave), baudrate=115_200, reset_wait_s=0, timeout_s=0.1, connect_attempts=1)
        with pytest.raises(TriggerError) as e:
            TriggerDevice(os.ttyname(slave), reset_wait_s=0, timeout_s=0.1, connect_attempts=1)
        assert "baud" not in str(e.value)
    finally:
        os.close(master)
        os.close(slave)


def test_choose_rate_is_closest_and_reports_exact_rate() -> None:
    c = choose_rate(100.0, 16_000_000)
    assert c.fps == pytest.approx(100.0) and isinstance(c, RateChoice)
    c = choose_rate(59.94, 16_000_000)
    assert abs(c.fps - 59.94) < 1e-3
    with pytest.raises(TriggerError, match="outside"):
        choose_rate(0.01, 16_000_000)
    with pytest.raises(TriggerError, match="outside"):
        choose_rate(50_000, 16_000_000)


def test_software_trigger_rejects_a_name_the_protocol_cannot_carry() -> None:
    with pytest.raises(ValueError, match="longer than 16 bytes"):
        SoftwareTrigger(name="a-name-much-too-long-for-info")


def test_stop_racing_clock_queries_never_counts_frames_twice() -> None:
    """Clock queries from another thread while STOP is handled: the count never goes past what
    the stopped device then reports (the race double-counted the frames of the run)."""
    import threading

    with SoftwareTrigger() as sw, TriggerDevice(sw.port, reset_wait_s=0) as dev:
        dev.set_rate(1000.0)
        for _ in range(5):
            dev.start()
            time.sleep(0.02)
            seen: list[int] = []
            done = threading.Event()

            def poll(seen: list[int] = seen, done: threading.Event = done) -> None:
                while not done.is_set():
                    seen.append(sw.clock()[0])

            t = threading.Thread(target=poll)
            t.start()
            dev.stop()
            done.set()
            t.join()
            final = dev.query_clock().frame_count
            assert max(seen) <= final
