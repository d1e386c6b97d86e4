"""The page's state from a real (not started) HostPipeline of 11 cameras: tiles, points, histogram,
recording and disk, rule firings from the actuation's FiringLog, and NaN-free JSON."""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from flytrack_host.actuation.firings import FiringLog
from flytrack_host.intake.sync import CameraFrame, SyncedBundle
from flytrack_host.live.web.server import LiveServer, to_json
from flytrack_host.pipeline import HostPipeline
from flytrack_host.protocol import POINT_DTYPE
from flytrack_host.recording.schema import FIRINGS
from flytrack_host.sim.flight import Arena
from flytrack_host.sim.rig import make_cameras, rig_config
from flytrack_host.tracking.types import FrameBundle

sys.path.insert(0, str(Path(__file__).parent))
from frames import make_result  # noqa: E402


class _Rules:
    """Holds the actuation's own FiringLog, as its engine does (the page reads `firings`)."""

    def __init__(self) -> None:
        self.firings = FiringLog()

    def on_frame(self, *a) -> None: ...

    def close(self) -> None: ...


def test_state_of_an_11_camera_pipeline(tmp_path):
    cams = make_cameras(11, Arena(), seed=0)
    rig = rig_config(cams, 100.0, "127.0.0.1:7000", "software", "", None, str(tmp_path / "rec"))
    rules = _Rules()
    pipe = HostPipeline(rig, {i: c for i, c in enumerate(cams)}, record=False, sinks=[rules],
                        recording_path=tmp_path / "rec" / "x.flytrack")
    pts = np.zeros(3, dtype=POINT_DTYPE)
    pts["x_dist"], pts["y_dist"] = [10.0, 20.0, np.nan], [30.0, 40.0, 50.0]
    t = time.time()
    frames = {i: CameraFrame(i, 5, 5, pts, t + 0.001 * i) for i in range(11)}
    pipe.last_synced = SyncedBundle(FrameBundle(5, t - 0.002, {}), frames, t, t + 0.01, "complete")
    for ms in [1.0, 1.2, 1.3, 2.5] * 100 + [900.0]:
        pipe.latency.row(5, t, t, t, t + ms / 1e3, 11, 0)
    row = np.zeros(1, dtype=FIRINGS)
    row["rule"], row["output"], row["obj_id"], row["scheduled_frame"] = b"near_post", b"led", 3, 42
    row["frame_time"], row["time_ack"] = 100.0, 100.0035
    rules.firings.rows.append(row)
    rules.firings.count = 1
    server = LiveServer("127.0.0.1", 0)
    server.state.pipe = pipe
    server.add_rule_firing("manual: test")
    server.state.add_frame(make_result(5, 10, born=list(range(1, 11))), t - 0.002, t)
    snap = json.loads(to_json(server.state.snapshot(server.stats())))
    assert len(snap["cameras"]) == 11 and snap["objects"] == 10 and len(snap["tracks"]) == 10
    c0 = snap["cameras"][0]
    assert c0["name"] == cams[0].name and c0["width"] == 640 and c0["height"] == 480
    assert c0["points"] == [[10.0, 30.0], [20.0, 40.0], [None, 50.0]] and c0["n_points"] == 3
    assert math.isclose(c0["latency_ms"], 2.0, abs_tol=0.01)
    assert len(c0["centre"]) == 3 and snap["frames_tracked"] == 0
    lat = snap["latency"]
    assert sum(lat["counts"]) + lat["beyond"] == 401 and lat["beyond"] == 1  # the 900 ms outlier
    assert len(lat["counts"]) < 100  # the page's axis ends near the P99.5, not at 1 s
    assert snap["recording"]["on"] is False and snap["recording"]["disk"]["free_gb"] > 0
    assert snap["rules_fired"][0] == "1 actions fired, 0 failed"
    assert snap["rules_fired"][1] == "near_post obj 3 -> led frame 42 3.5 ms"
    assert snap["rules"][0].endswith("manual: test")
    assert "NaN" not in to_json(snap).decode()
