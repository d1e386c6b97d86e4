"""Output devices against real peers: a pymodbus server (TCP, RTU over a pty pair), python-can buses
(virtual, udp_multicast on loopback), a UDP socket, a Python hook; HID and USB through their seams.
Faults: a device absent at start, killed mid-run and restarted, a slow one, a full queue."""

from __future__ import annotations

import socket
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from flytrack_host.actuation.devices.hid import HidOutput
from flytrack_host.actuation.devices.usb import UsbOutput
from flytrack_host.actuation.peers import CanListener, ModbusPeer, PtyPair, free_tcp_port
from flytrack_host.recording.schema import FIRING_FAILED, FIRINGS
from flytrack_host.rig import ActuatorConfig

COIL = [{"output": "valve", "coil": 2, "value": 1}]


def _errors(eng) -> list[str]:  # noqa: ANN001
    t = eng.firings.table()
    return [e.decode() for e in t["error"] if e]


def test_modbus_tcp_writes_each_entry(act) -> None:  # noqa: ANN001
    peer = ModbusPeer().start()
    try:
        eng = act.engine(COIL, [ActuatorConfig(name="valve", kind="modbus", address=peer.address)])
        eng.start()
        act.drive_entries(eng, 3)
        assert act.wait_for(lambda: len(peer.coil_writes(2)) == 3)
        eng.close()
        t = eng.firings.table()
        assert t.dtype == FIRINGS and len(t) == 3
        # The object jumps in (no velocity to predict from): fired on the entry frame's estimate, for the next.
        assert [int(f) for f in t["condition_frame"]] == [30, 65, 100]
        assert [int(f) for f in t["scheduled_frame"]] == [31, 66, 101]
        assert np.all(t["time_ack"] >= t["time_sent"]) and not _errors(eng)
        s = eng.summary()
        assert s["rules"]["enter"]["fired"] == 3 and s["outputs"]["valve"]["ok"] == 3
    finally:
        peer.stop()


def test_modbus_absent_at_start_then_killed_and_back(act) -> None:  # noqa: ANN001
    port = free_tcp_port()
    logs: list[str] = []
    eng = act.engine(COIL, [ActuatorConfig(name="valve", kind="modbus", address=f"127.0.0.1:{port}", timeout_s=0.3)])
    eng._log = logs.append  # the pipeline's log in a live run
    eng.warn.log = logs.append
    eng.start()
    peer = ModbusPeer(port=port)
    durations = act.drive_entries(eng, 1)  # nobody listens: the firing fails, tracking goes on
    assert act.wait_for(lambda: eng.firings.count == 1)
    assert "not connected" in _errors(eng)[0] and "no Modbus TCP device" in _errors(eng)[0]
    assert any("cannot connect" in m and "valve" in m for m in logs)
    assert eng.workers["valve"].stats.connect_failures >= 1
    peer.start()
    assert act.wait_for(lambda: eng.workers["valve"].output.connected, 5.0)  # reconnected on its own
    act.drive_entries(eng, 1)
    assert act.wait_for(lambda: len(peer.coil_writes(2)) == 1)
    peer.stop()  # switched off mid-run
    durations += act.drive_entries(eng, 1)
    assert act.wait_for(lambda: eng.firings.count == 3)
    peer = ModbusPeer(port=port).start()  # and back
    assert act.wait_for(lambda: eng.workers["valve"].output.connected, 5.0)
    act.drive_entries(eng, 1)
    assert act.wait_for(lambda: len(peer.coil_writes(2)) == 1)
    eng.close()
    peer.stop()
    t = eng.firings.table()
    failed = (t["flags"] & FIRING_FAILED) != 0
    assert failed.tolist() == [True, False, True, False]
    assert eng.summary()["outputs"]["valve"]["errors"] == 2
    # The tracking thread's part never waited for the dead device.
    assert max(durations) < 0.2, max(durations)


def test_slow_device_never_delays_tracking_and_full_queue_is_counted(act) -> None:  # noqa: ANN001
    peer = ModbusPeer(delay_s=0.3).start()
    try:
        eng = act.engine(COIL, [ActuatorConfig(name="valve", kind="modbus", address=peer.address, queue=1,
                                               timeout_s=2.0)])
        eng.start()
        assert act.wait_for(lambda: eng.workers["valve"].output.connected, 5.0)
        durations = act.drive_entries(eng, 4, frames_out=3, frames_in=2)
        assert max(durations) < 0.2, max(durations)  # 4 writes of 0.3 s each (1.2 s) were asked within 20 frames
        eng.close()
        s = eng.summary()["outputs"]["valve"]
        assert s["dropped"] >= 1 and "queue full" in s["last_error"]
        assert s["ok"] + s["dropped"] == 4
        ok = eng.firings.table()
        ok = ok[(ok["flags"] & FIRING_FAILED) == 0]
        assert np.all(ok["time_ack"] - ok["time_sent"] >= 0.25)  # the device's slowness is measured
    finally:
        peer.stop()


def test_modbus_rtu_over_a_pty_pair(act) -> None:  # noqa: ANN001
    pair = PtyPair()
    peer = ModbusPeer(serial_port=pair.port1, baudrate=115200).start()
    try:
        eng = act.engine([{"output": "plc", "register": 7, "value": 1234}],
                         [ActuatorConfig(name="plc", kind="modbus", transport="rtu", address=pair.port2,
                                         baud=115200, unit=1)])
        eng.start()
        act.drive_entries(eng, 2)
        assert act.wait_for(lambda: len(peer.writes) == 2)
        eng.close()
        assert [(w.func_code, w.address, w.values) for w in peer.writes] == [(6, 7, [1234])] * 2
        assert not _errors(eng)
    finally:
        peer.stop()
        pair.close()


@pytest.mark.parametrize("interface", ["virtual", "udp_multicast"])
def test_can_frames_reach_the_bus(act, interface: str) -> None:  # noqa: ANN001
    if interface == "virtual":
        channel, kw, address = f"ft-{uuid.uuid4().hex[:8]}", {}, None
    else:  # a group and port of this test's own, so parallel runs do not hear each other
        port = 43113 + (uuid.uuid4().int % 1000)
        channel, kw, address = "239.74.163.2", {"port": port}, f"239.74.163.2:{port}"
    try:
        listener = CanListener(interface, channel, **kw)
    except Exception as exc:  # udp_multicast needs a multicast route on loopback
        pytest.skip(f"{interface} bus not available here: {exc}")
    try:
        act_cfg = ActuatorConfig(name="stim", kind="can", interface=interface, address=address or channel)
        eng = act.engine([{"output": "stim", "can_id": 0x123, "data": [1, 2, 3]}], [act_cfg])
        eng.start()
        act.drive_entries(eng, 2)
        assert act.wait_for(lambda: len(listener.frames) == 2)
        eng.close()
        assert [(i, d) for _, i, d in listener.frames] == [(0x123, b"\x01\x02\x03")] * 2
    finally:
        listener.close()


def test_udp_and_python_hook(act, tmp_path: Path) -> None:  # noqa: ANN001
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(5)
    hook = tmp_path / "stim.py"
    hook.write_text("CALLS = []\ndef go(firing, colour):\n    CALLS.append((firing['obj_id'], colour))\n"
                    "    if len(CALLS) == 2:\n        raise ValueError('lamp broke')\n")
    acts = [ActuatorConfig(name="pc", kind="udp", address=f"127.0.0.1:{rx.getsockname()[1]}"),
            ActuatorConfig(name="lamp", kind="python", address="stim.py:go")]
    eng = act.engine([{"output": "pc", "payload": "{rule} {obj_id} {frame}"},
                      {"output": "lamp", "params": {"colour": "blue"}}], acts, context={"base_dir": tmp_path})
    eng.start()
    act.drive_entries(eng, 2)
    assert rx.recv(100) == b"enter 1 31"
    assert rx.recv(100) == b"enter 1 66"
    assert act.wait_for(lambda: eng.firings.count == 4)
    eng.close()
    rx.close()
    errs = _errors(eng)
    assert errs == ["ValueError: lamp broke"]  # the hook's exception: a failed action, counted
    assert eng.summary()["outputs"]["lamp"]["errors"] == 1


class _FakeHid:
    """Stand-in for a HID device (none can exist on this machine): records the reports written."""

    def __init__(self) -> None:
        self.reports: list[bytes] = []
        self.opened = 0

    def open(self, vendor_id, product_id, path):  # noqa: ANN001, ANN201
        self.opened += 1
        return self

    def write(self, data: bytes) -> int:
        self.reports.append(bytes(data))
        return len(data)

    def close(self) -> None:
        pass


class _FakeUsb:
    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def open(self, vendor_id, product_id):  # noqa: ANN001, ANN201
        return self

    def close(self, handle) -> None:  # noqa: ANN001
        pass

    def ctrl_transfer(self, *args):  # noqa: ANN002, ANN201
        self.calls.append(("ctrl", *args))
        return len(args[4])

    def write(self, endpoint, data, timeout):  # noqa: ANN001, ANN201
        self.calls.append(("bulk", endpoint, bytes(data)))
        return len(data)


def test_hid_and_usb_through_their_seams(act) -> None:  # noqa: ANN001
    hid, usb = _FakeHid(), _FakeUsb()
    acts = [ActuatorConfig(name="pad", kind="hid", vendor_id=0x16C0, product_id=0x0486),
            ActuatorConfig(name="box", kind="usb", vendor_id=0x16C0, product_id=0x05DC)]
    eng = act.engine([{"output": "pad", "report_id": 2, "data": [9, 8]},
                      {"output": "box", "request_type": 0x40, "request": 1, "w_value": 5, "data": [7]}],
                     acts, context={"hid_backend": hid, "usb_backend": usb})
    assert isinstance(eng.outputs["pad"], HidOutput) and isinstance(eng.outputs["box"], UsbOutput)
    eng.start()
    act.drive_entries(eng, 1)
    assert act.wait_for(lambda: eng.firings.count == 2)
    eng.close()
    assert hid.reports == [b"\x02\x09\x08"]
    assert usb.calls == [("ctrl", 0x40, 1, 5, 0, b"\x07", 500)]


def test_real_hid_backend_says_no_device(act) -> None:  # noqa: ANN001
    # The real hidapi backend on this machine: no such device, a clear failed firing.
    eng = act.engine([{"output": "pad", "data": [1]}],
                     [ActuatorConfig(name="pad", kind="hid", vendor_id=0x16C0, product_id=0x0486)])
    eng.start()
    act.drive_entries(eng, 1)
    assert act.wait_for(lambda: eng.firings.count == 1)
    eng.close()
    assert "no HID device 16c0:0486" in _errors(eng)[0]


def test_dry_run_records_and_sends_nothing(act) -> None:  # noqa: ANN001
    peer = ModbusPeer().start()
    try:
        rule = {"name": "enter", "dry_run": True, "when": {"inside": {"box": {"min": [1, -1, -1], "max": [2, 1, 1]}}}}
        eng = act.engine(COIL, [ActuatorConfig(name="valve", kind="modbus", address=peer.address)], rule=rule)
        eng.start()
        act.drive_entries(eng, 2)
        time.sleep(0.2)
        eng.close()
        assert peer.writes == []
        t = eng.firings.table()
        assert len(t) == 2 and all(e == b"dry run" for e in t["error"])
    finally:
        peer.stop()
