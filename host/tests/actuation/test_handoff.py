"""The hand-off from the tracking thread to the device threads, and what each stage of trigger -> device
acknowledgement is stamped with (real peers: a UDP socket, a pymodbus server in its own process)."""

from __future__ import annotations

import math
import os
import select
import socket
import threading
import time

import numpy as np

from flytrack_host.actuation.devices import base
from flytrack_host.actuation.devices.base import Handoff
from flytrack_host.actuation.firings import STAGES, send_split, stage_latencies
from flytrack_host.actuation.peers import ModbusPeerProcess, free_tcp_port
from flytrack_host.rig import ActuatorConfig
from flytrack_host.util import hostclock


def _udp_engine(act, rx: socket.socket):  # noqa: ANN001, ANN202
    port = rx.getsockname()[1]
    eng = act.engine([{"output": "pc", "payload": "go"}], [ActuatorConfig(name="pc", kind="udp",
                                                                        address=f"127.0.0.1:{port}")])
    eng.start()
    assert act.wait_for(lambda: eng.workers["pc"].ready, 5.0)
    return eng


def test_command_is_on_the_wire_when_on_frame_returns(act) -> None:  # noqa: ANN001
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    try:
        eng = _udp_engine(act, rx)
        eng.handoff_max_s = 5.0  # a generous bound here (the machine may be loaded): it ends when the datagram left
        f = 0
        returned = []
        for x in [0.0] * 30 + [1.5] * 3:
            eng.on_frame(act.result(f, {1: (x, 0.0)}), hostclock.now(), hostclock.now())
            returned.append(hostclock.now())
            if f == 30:  # the entry: fired
                # No GIL release between on_frame's return and this check: the datagram is already here.
                r, _, _ = select.select([rx], [], [], 0)
                assert r == [rx]
            f += 1
        assert rx.recv(64) == b"go"
        assert act.wait_for(lambda: eng.firings.count == 1)
        eng.close()
        rule, out, frame, trig, est, queued, started, sent, ack = eng.stages[0]
        assert (rule, out, frame) == ("enter", "pc", 30)
        assert trig <= est <= queued <= started <= sent <= ack <= returned[30]
        h = eng.summary()["handoff"]
        assert h["frames"] == 1 and h["timeouts"] == 0
    finally:
        rx.close()


def test_no_wait_for_a_device_that_is_down(act) -> None:  # noqa: ANN001
    port = free_tcp_port()  # nobody listens
    eng = act.engine([{"output": "valve", "coil": 0, "value": 1}],
                     [ActuatorConfig(name="valve", kind="modbus", address=f"127.0.0.1:{port}", timeout_s=0.3)])
    eng.warn.log = lambda m: None
    eng.start()
    act.drive_entries(eng, 2)
    assert act.wait_for(lambda: eng.firings.count == 2)
    eng.close()
    # Not connected: not ready, so the tracking thread queued the command and went on.
    assert eng.summary()["handoff"]["frames"] == 0
    assert eng.summary()["outputs"]["valve"]["errors"] == 2


def test_handoff_counts_and_bounds() -> None:
    h = Handoff()
    assert h.wait(0.0)  # nothing to wait for
    h.add()
    h.add()
    h.done()
    assert not h.wait(0.01)  # one command still to leave: the bound ends the wait
    h.done()
    assert h.wait(0.0)
    assert base.HANDOFF_MAX_S <= 0.005  # the most a firing frame can hold the tracking thread


def test_modbus_ack_is_the_kernel_stamp_of_the_response(act) -> None:  # noqa: ANN001
    peer = ModbusPeerProcess().start()
    try:
        eng = act.engine([{"output": "valve", "coil": 3, "value": 1}],
                         [ActuatorConfig(name="valve", kind="modbus", address=peer.address)])
        eng.start()
        assert act.wait_for(lambda: eng.workers["valve"].ready, 5.0)
        out = eng.outputs["valve"]
        sock = out.client.socket
        assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY)
        act.drive_entries(eng, 3)
        assert act.wait_for(lambda: eng.firings.count == 3)
        assert out.client.socket is sock and out.client._configured is sock  # options set once, same socket
        eng.close()
        assert act.wait_for(lambda: len(peer.coil_writes(3)) == 3, 5.0)  # logged by the server after it answered
        for _, _, _, _, _, queued, started, sent, ack in eng.stages:
            assert queued <= started <= sent <= ack
        # When each request left (the send returned), for the JSON's split of sent -> ack.
        assert len(eng.sends) == 3 and all(s <= w for _, _, s, w, _ in eng.sends)
        # The response's arrival as the kernel stamped it (after the request was sent: sent <= ack above)
        # is the acknowledgement the firing recorded. It can come before the device thread, back from
        # its send, has the GIL again to stamp `time_written`: why the reply is stamped by the kernel.
        assert math.isfinite(out.reply_at) and eng.stages[-1][-1] == out.reply_at
        t = eng.firings.table()
        assert np.all(t["time_ack"] >= t["time_sent"]) and not any(t["error"])
    finally:
        peer.stop()


def test_stage_latencies_per_output() -> None:
    rows = [("r", "a", 10, 0.0, 0.002, 0.0021, 0.0025, 0.0026, 0.0030),
            ("r", "a", 20, 1.0, 1.004, 1.0041, 1.0045, 1.0046, 1.0060),
            ("r", "b", 10, 0.0, 0.002, 0.0021, 0.0030, 0.0031, 0.0031),
            ("other", "a", 5, 0.0, 0.1, 0.1, 0.1, 0.1, 0.1)]
    s = stage_latencies(rows, "r")
    assert sorted(s) == ["a", "b"] and list(s["a"]) == list(STAGES)
    assert s["a"]["trigger_to_estimate"]["n"] == 2
    assert math.isclose(s["a"]["trigger_to_estimate"]["p50"], 3.0)
    assert math.isclose(s["a"]["sent_to_ack"]["max"], 1.4, rel_tol=1e-6)
    assert math.isclose(s["a"]["trigger_to_ack"]["p50"], 4.5, rel_tol=1e-6)
    assert math.isclose(s["b"]["queued_to_worker"]["p50"], 0.9, rel_tol=1e-6)


def test_send_split_per_output() -> None:
    rows = [("r", "valve", 1.0, 1.0001, 1.0004), ("r", "valve", 2.0, 2.0002, 2.0008),
            ("r", "can", 3.0, 3.00005, 3.00005), ("other", "valve", 0.0, 1.0, 2.0)]
    s = send_split(rows, "r")
    assert sorted(s) == ["can", "valve"]
    assert s["valve"]["sent_to_written"]["n"] == 2
    assert math.isclose(s["valve"]["sent_to_written"]["p50"], 0.15, rel_tol=1e-6)
    assert math.isclose(s["valve"]["written_to_ack"]["max"], 0.6, rel_tol=1e-6)
    assert math.isclose(s["can"]["written_to_ack"]["p50"], 0.0, abs_tol=1e-9)


def test_devices_of_one_firing_send_in_turn_and_all_before_on_frame_returns(act) -> None:  # noqa: ANN001
    """Two idle devices: both threads are woken at once, the second sends only once the first's command
    left (`Job.after`), and both datagrams are on the wire when on_frame returns."""
    rxs = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    try:
        for rx in rxs:
            rx.bind(("127.0.0.1", 0))
        acts = [ActuatorConfig(name=n, kind="udp", address=f"127.0.0.1:{rx.getsockname()[1]}")
                for n, rx in zip(("first", "second"), rxs, strict=True)]
        eng = act.engine([{"output": "first", "payload": "a"}, {"output": "second", "payload": "b"}], acts)
        eng.start()
        assert act.wait_for(lambda: eng.workers["first"].ready and eng.workers["second"].ready, 5.0)
        eng.handoff_max_s = 5.0  # generous (a loaded machine): the wait ends when both left
        first = eng.outputs["first"]
        perform = first._perform

        def slow_client(job):  # noqa: ANN001, ANN202 - a client library that takes 30 ms to build its request
            time.sleep(0.03)
            return perform(job)

        first._perform = slow_client
        for f, x in enumerate([0.0] * 30 + [1.5] * 2):
            eng.on_frame(act.result(f, {1: (x, 0.0)}), hostclock.now(), hostclock.now())
            if f == 30:
                r, _, _ = select.select(rxs, [], [], 0)
                assert sorted(s.fileno() for s in r) == sorted(s.fileno() for s in rxs)
        assert act.wait_for(lambda: eng.firings.count == 2)
        eng.close()
        sends = {out: (sent, written) for _, out, sent, written, _ in eng.sends}
        assert sends["second"][0] >= sends["first"][1]  # the second began after the first's send returned
        assert eng.summary()["handoff"]["timeouts"] == 0
    finally:
        for rx in rxs:
            rx.close()


def test_the_thread_that_feeds_the_rules_runs_at_the_device_threads_priority(act) -> None:  # noqa: ANN001
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    seen = []
    try:
        eng = _udp_engine(act, rx)

        def tracking() -> None:
            eng.on_frame(act.result(0, {1: (0.0, 0.0)}), hostclock.now(), hostclock.now())
            seen.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))

        t = threading.Thread(target=tracking)
        t.start()
        t.join(5)
        eng.close()
        allowed = eng.summary()["tracking_priority_raised"]
        assert allowed == (os.geteuid() == 0)  # raising needs root (or CAP_SYS_NICE) here
        if allowed:
            assert seen == [base.WORKER_NICE]
    finally:
        rx.close()


def test_a_main_thread_calling_the_rules_keeps_its_priority(act) -> None:  # noqa: ANN001
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    try:
        before = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        eng = _udp_engine(act, rx)
        eng.on_frame(act.result(0, {1: (0.0, 0.0)}), hostclock.now(), hostclock.now())
        eng.close()
        assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == before
        assert eng.summary()["tracking_priority_raised"] is False
    finally:
        rx.close()
