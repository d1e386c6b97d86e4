"""Benchmark of the closed loop's own part: estimate -> device acknowledgement, and what it costs the
tracking thread, side by side with the plain way (the device call made right on the tracking thread).

For each device (Modbus TCP to a pymodbus server in its own process, CAN on python-can's virtual bus,
UDP on loopback, and the firmware's PULSE in simavr when the AVR tools are here), `n` firings paced at
100 Hz: one frame whose object has just entered the box, through the engine (vectorised rule, queue,
device thread) and, for the same device, the same command called directly where the estimate is made.
Printed: P50/P99 of estimate -> acknowledgement for both, and the tracking thread's time per firing
frame (the engine's `on_frame` vs the blocking call), with their ratio. For Modbus and CAN also the
engine with its hand-off wait against without, the "tracking thread" computing 1 ms after each frame
as it does in a live run (with the bench's thread asleep, a device thread gets the GIL at once either
way). Plus the rule evaluation cost per frame against the number of objects.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.actuation.engine import ActuationEngine
from flytrack_host.actuation.firings import percentiles_ms
from flytrack_host.actuation.peers import CanListener, ModbusPeerProcess
from flytrack_host.actuation.rules import parse_rules
from flytrack_host.rig import ActuatorConfig
from flytrack_host.tracking.types import Estimate, FrameResult
from flytrack_host.util import hostclock

BUSY_S = 0.001  # the tracking thread's work after a frame, in the side-by-side of the hand-off
BOX = {"inside": {"box": {"min": [1, -1, -1], "max": [2, 1, 1]}}}


def _frame(f: int, n_obj: int, inside: bool) -> FrameResult:
    est = []
    for i in range(n_obj):
        x = 1.5 if (inside and i == 0) else 0.0
        est.append(Estimate(i + 1, np.array([x, 0.01 * i, 0, 0, 0, 0], float), np.eye(6), 3))
    return FrameResult(f, 0.0, est)


def _engine(actuator: ActuatorConfig, action: dict, context: dict | None = None) -> ActuationEngine:
    rs = parse_rules({"rules": [{"name": "bench", "when": BOX, "actions": [{"output": actuator.name, **action}]}]})
    return ActuationEngine(rs, [actuator], 100.0, context)


def through_engine(actuator: ActuatorConfig, action: dict, n: int, context: dict | None = None,
                   frame0: int = 0, frame_time: Any = None, frames_out: int = 1, busy_s: float = 0.0,
                   handoff: bool = True) -> dict[str, Any]:
    """`busy_s`: the "tracking thread" goes on computing (Python, holding the GIL but at switch
    intervals) this long after each frame, as the pipeline does (live datagram, recording rows);
    `handoff`: the engine's wait for the device threads' sends on a frame that fired."""
    eng = _engine(actuator, action, context)
    if not handoff:
        eng.handoff_max_s = 0.0
    eng.start()
    on_frame = []
    f = frame0
    for _ in range(n):
        for inside in [False] * frames_out + [True]:
            ft = frame_time(f) if frame_time else hostclock.now()
            time.sleep(max(0.0, ft + 0.001 - hostclock.now()) if frame_time else 0.005)
            t_est = hostclock.now()
            s = time.perf_counter()
            eng.on_frame(_frame(f, 1, inside), ft, t_est)
            if inside:
                on_frame.append(time.perf_counter() - s)
            end = time.perf_counter() + busy_s
            while time.perf_counter() < end:
                pass
            f += 1
    deadline = time.monotonic() + 10
    while eng.firings.count < n and time.monotonic() < deadline:
        time.sleep(0.01)
    eng.close()
    t = eng.firings.table()
    ok = t["error"] == b""
    late = np.char.startswith(t["error"], b"late")
    return {"est_to_ack_ms": percentiles_ms(t["time_ack"][ok] - t["estimate_time"][ok]), "late": int(late.sum()),
            "tracking_thread_us_p50": float(np.median(on_frame) * 1e6),
            "tracking_thread_us_p99": float(np.percentile(on_frame, 99) * 1e6), "failed": int((~ok & ~late).sum())}


def direct(call: Any, n: int, gap_s: float = 0.01) -> dict[str, Any]:
    lat = []
    for _ in range(n):
        time.sleep(gap_s)
        t0 = hostclock.now()
        call()
        lat.append(hostclock.now() - t0)
    a = np.asarray(lat)
    return {"est_to_ack_ms": percentiles_ms(a), "tracking_thread_us_p50": float(np.median(a) * 1e6),
            "tracking_thread_us_p99": float(np.percentile(a, 99) * 1e6), "failed": 0}


def bench_modbus(n: int) -> dict[str, Any]:
    from pymodbus.client import ModbusTcpClient

    peer = ModbusPeerProcess().start()
    try:
        act = ActuatorConfig(name="valve", kind="modbus", address=peer.address)
        eng = through_engine(act, {"coil": 0, "value": 1}, n)
        busy = {h: through_engine(act, {"coil": 0, "value": 1}, n, busy_s=BUSY_S, handoff=h) for h in (True, False)}
        client = ModbusTcpClient(peer.host, port=peer.port, retries=0)
        client.connect()
        d = direct(lambda: client.write_coil(0, True, device_id=1), n)
        client.close()
    finally:
        peer.stop()
    return {"device": "Modbus TCP (pymodbus server process)", "engine": eng, "direct": d,
            "busy_handoff": busy[True], "busy_no_handoff": busy[False]}


def bench_can(n: int) -> dict[str, Any]:
    import can

    ch = f"bench-{time.time_ns()}"
    listener = CanListener("virtual", ch)
    try:
        act = ActuatorConfig(name="stim", kind="can", interface="virtual", address=ch)
        eng = through_engine(act, {"can_id": 0x123, "data": [1, 2]}, n)
        busy = {h: through_engine(act, {"can_id": 0x123, "data": [1, 2]}, n, busy_s=BUSY_S, handoff=h)
                for h in (True, False)}
        bus = can.Bus(interface="virtual", channel=ch)
        msg = can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False)
        d = direct(lambda: bus.send(msg), n)
        bus.shutdown()
    finally:
        listener.close()
    return {"device": "CAN (python-can virtual bus)", "engine": eng, "direct": d,
            "busy_handoff": busy[True], "busy_no_handoff": busy[False]}


def bench_udp(n: int) -> dict[str, Any]:
    import socket

    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    act = ActuatorConfig(name="pc", kind="udp", address=f"127.0.0.1:{rx.getsockname()[1]}")
    eng = through_engine(act, {"payload": "go"}, n)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    d = direct(lambda: tx.sendto(b"go", rx.getsockname()), n)
    rx.close()
    tx.close()
    return {"device": "UDP datagram (loopback)", "engine": eng, "direct": d}


def bench_pulse(n: int) -> dict[str, Any] | None:
    from flytrack_host.trigger import simulator
    from flytrack_host.trigger.common import TriggerError
    from flytrack_host.trigger.device import TriggerDevice

    if not simulator.tools_available():
        return None
    harness, elf = simulator.build()
    with simulator.SimulatedTrigger(elf=elf, harness=harness, realtime=True) as sim:
        dev = TriggerDevice(sim.pty, reset_wait_s=0)
        dev.set_rate(100.0)
        dev.start()
        try:
            for _ in range(8):
                dev.query_clock()
            dev.start_clock_thread(0.1)  # as a live run keeps its clock model fed (the PULSEs share the link)
            model = dev.model
            f0 = int(dev.query_clock().frame_count) + 3
            act = ActuatorConfig(name="hscam", kind="trigger_pulse")
            eng = through_engine(act, {"width_ms": 0.5}, n, {"trigger": dev, "clock": model}, frame0=f0,
                                 frame_time=model.frame_to_host_time, frames_out=4)

            def one() -> None:  # the frame after next, from the clock model; too late: at once (as the engine)
                try:
                    dev.pulse_timed(0, int(model.host_time_to_frame(hostclock.now())) + 2, 0.0005)
                except TriggerError:
                    dev.pulse_timed(0, None, 0.0005)

            d = direct(one, n, gap_s=0.04)  # the pulse is done before the next (one may wait at a time)
        finally:
            dev.stop_clock_thread()
            dev.stop()
            dev.close()
    return {"device": "firmware PULSE (simavr, 1 Mbaud)", "engine": eng, "direct": d}


def bench_eval(objs: list[int], frames: int = 2000) -> list[dict[str, float]]:
    rs = parse_rules({"rules": [{"name": f"r{i}", "dry_run": True, "when": w} for i, w in enumerate([
        BOX, {"speed_m_s": [0.5, 3]}, {"distance_m": {"post": [0, 0], "max": 0.1}, "hold_ms": 50},
        {"inside": {"cylinder": {"center": [0, 0], "radius": 0.1, "z": [0, 0.3]}}, "after_false_ms": 500}])]})
    out = []
    for n in objs:
        eng = ActuationEngine(rs, [], 100.0)
        res = [_frame(f, n, f % 10 >= 5) for f in range(frames)]
        t0 = time.perf_counter()
        for f, r in enumerate(res):
            eng.on_frame(r, f * 0.01, f * 0.01 + 0.001)
        dt = (time.perf_counter() - t0) / frames
        out.append({"objects": n, "rules": len(rs.rules), "us_per_frame": dt * 1e6})
    return out


def _row(name: str, d: dict[str, Any]) -> str:
    e = d["est_to_ack_ms"]
    nan = float("nan")
    return (f"    {name:7s} estimate->ack P50 {e.get('p50', nan):6.3f} ms  P99 {e.get('p99', nan):6.3f} ms"
            f"   tracking thread P50 {d['tracking_thread_us_p50']:7.1f} us  P99 {d['tracking_thread_us_p99']:7.1f} us"
            + (f"  ({d['failed']} failed)" if d["failed"] else "") + (f"  ({d['late']} late)" if d.get("late") else ""))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", type=Path)
    ap.add_argument("-n", type=int, default=100, help="firings per device")
    a = ap.parse_args()
    rows = [bench_modbus(a.n), bench_can(a.n), bench_udp(a.n)]
    p = bench_pulse(min(a.n, 50))
    if p is not None:
        rows.append(p)
    print("closed loop: estimate -> device acknowledgement, engine (queue + device thread) vs the call made "
          "on the tracking thread")
    for r in rows:
        print(f"  {r['device']}:")
        print(_row("engine", r["engine"]))
        print(_row("direct", r["direct"]))
        ratio = r["direct"]["tracking_thread_us_p50"] / r["engine"]["tracking_thread_us_p50"]
        r["tracking_thread_ratio"] = ratio
        print(f"    the tracking thread is held {ratio:.1f}x less with the engine (P50)")
        if "busy_handoff" in r:
            print(f"    tracking thread busy {BUSY_S * 1e3:g} ms after each frame (as in a live run):")
            print(_row("handoff", r["busy_handoff"]))
            print(_row("none", r["busy_no_handoff"]))
            b = r["busy_no_handoff"]["est_to_ack_ms"].get("p50", float("nan")) / \
                r["busy_handoff"]["est_to_ack_ms"].get("p50", float("nan"))
            r["busy_handoff_ratio"] = b
            print(f"    estimate -> ack {b:.1f}x sooner with the hand-off wait (P50)")
    ev = bench_eval([1, 10, 100])
    print("rule evaluation (4 rules, engine on_frame without devices):")
    for e in ev:
        print(f"  {e['objects']:3d} objects: {e['us_per_frame']:7.1f} us per frame")
    if a.json:
        a.json.write_text(json.dumps({"actuation_devices": rows, "actuation_eval": ev}, indent=1))


if __name__ == "__main__":
    main()
