"""The rule engine as a sink of the real HostPipeline over UDP (issue 10): a Modbus device absent at
start, then up, then killed; every frame is tracked and recorded all along, every firing is in the
recording (failed ones with their error), the status line counts the failures."""

from __future__ import annotations

import threading
import time

import numpy as np

from flytrack_host.actuation.engine import ActuationEngine
from flytrack_host.actuation.peers import ModbusPeer, free_tcp_port
from flytrack_host.actuation.rules import parse_rules
from flytrack_host.pipeline import HostPipeline
from flytrack_host.recording import load_recording
from flytrack_host.recording.schema import FIRING_FAILED
from flytrack_host.rig import ActuatorConfig
from flytrack_host.tracking.types import Estimate, FrameBundle, FrameResult

PERIOD_FRAMES = 40  # the object is out for 20 frames, in for 20


def _wait(cond, timeout_s: float = 10.0) -> bool:  # noqa: ANN001
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.005)
    return False


class InOutTracker:
    """One object that flies into the box (x 1..2) at frames 20, 60, 100, ... and out again."""

    def __init__(self, cameras, params, period) -> None:  # noqa: ANN001
        pass

    def process(self, bundle: FrameBundle) -> FrameResult:
        inside = (bundle.trigger_frame % PERIOD_FRAMES) >= PERIOD_FRAMES // 2
        state = np.array([1.5 if inside else 0.0, 0, 0, 0, 0, 0], float)
        return FrameResult(bundle.trigger_frame, bundle.timestamp, [Estimate(1, state, np.eye(6) * 1e-4, 2)])


def test_dead_then_live_then_killed_modbus_device_never_stops_tracking(helpers, tmp_path) -> None:  # noqa: ANN001
    port = free_tcp_port()
    rig = helpers.make_rig(2, fps=100.0)
    acts = [ActuatorConfig(name="valve", kind="modbus", address=f"127.0.0.1:{port}", timeout_s=0.2)]
    rules = parse_rules({"rules": [{"name": "enter", "when": {"inside": {"box": {"min": [1, -1, -1],
                                                                                 "max": [2, 1, 1]}}},
                                    "actions": [{"output": "valve", "coil": 0, "value": 1}]}]})
    eng = ActuationEngine(rules, acts, 100.0)
    pipe = HostPipeline(rig, cameras={0: None, 1: None}, tracker_factory=lambda c, p, t: InOutTracker(c, p, t),
                        recording_path=tmp_path / "r", bind="127.0.0.1:0", keep_results=True)
    eng.attach(pipe)
    eng.start()
    pipe.start()
    edges = [helpers.EdgeSim(i, pipe.address, frame0=100 * i) for i in range(2)]
    peer = ModbusPeer(port=port)
    status = []

    def device_life() -> None:  # off the sending loop, so the frames keep their pace
        if _wait(lambda: eng.firings.count >= 1):  # the firing at frame 20 found no device
            peer.start()
        if _wait(lambda: eng.firings.count >= 3):  # 60 and 100 reached it
            peer.stop()  # switched off: 140 and 180 fail

    life = threading.Thread(target=device_life, daemon=True)
    life.start()
    try:
        t0 = time.monotonic()
        for k in range(200):  # entries at 20 (device absent), 60, 100 (up), 140, 180 (killed)
            for e in edges:
                e.send(k)
            if k == 199:
                time.sleep(0.05)
                status.append(pipe.status_line())
            time.sleep(max(0.0, t0 + (k + 1) / 100.0 - time.monotonic()))
        time.sleep(0.3)
    finally:
        life.join(10)
        summary = pipe.stop()
        peer.stop()
        for e in edges:
            e.close()
    assert summary["frames_tracked"] == 200 and summary["sink_errors"] == 0
    rec = load_recording(summary["recording"])
    assert len(rec.table("kalman_estimates")) == 200  # tracking and recording went on throughout
    t = rec.table("actuation_firings")
    assert [int(f) for f in t["condition_frame"]] == [20, 60, 100, 140, 180]
    failed = ((t["flags"] & FIRING_FAILED) != 0).tolist()
    assert failed == [True, False, False, True, True]
    assert "no Modbus TCP device" in t["error"][0].decode()
    assert len(peer.coil_writes(0)) == 2
    assert "rules: enter 5" in status[0] and "valve ok 2 ERR 3" in status[0]
    assert any("cannot connect" in r["message"] and r["source"] == "actuation" for r in rec.textlog)
