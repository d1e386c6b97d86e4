"""A live run whose points arrive but which reports no estimate says why, with numbers, in its summary and
text log (the real Tracker over real UDP, with a calibration in millimetres that says it is in metres); a
camera missing from the calibration is said at start, in the text log too."""

from __future__ import annotations

import socket
import time

import numpy as np

from flytrack_host.geometry.camera import Camera
from flytrack_host.pipeline import HostPipeline
from flytrack_host.protocol import POINT_DTYPE
from flytrack_host.protocol.udp import FeatureFrame, encode_features
from flytrack_host.recording import load_recording
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.tracker import Tracker


def test_live_run_in_millimetres_says_why_nothing_tracked(helpers, tmp_path):
    # Three cameras 1000 "units" (mm, though the tracker takes them for metres) from a target at the origin.
    cams = {i: Camera.look_at(f"cam{i}", (1000 * np.cos(a), 1000 * np.sin(a), 500.0), (0, 0, 0), 640, 480, 600.0)
            for i, a in enumerate((0.0, 2.1, 4.2))}
    uv = {i: c.project(np.zeros((1, 3)))[0] for i, c in cams.items()}

    def points(cam: int, frame: int) -> np.ndarray:
        p = np.zeros(1, POINT_DTYPE)
        p["x_dist"], p["y_dist"] = uv[cam]
        p["x_undist"], p["y_undist"] = uv[cam]
        p["area"], p["orientation"], p["eccentricity"] = 30.0, np.nan, np.nan
        return p

    rig = helpers.make_rig(4, fps=100.0)  # camera 3 has no calibration: said at start
    pipe = HostPipeline(rig, cameras=cams, tracker_factory=lambda c, p, dt: Tracker(c, p, dt),
                        params=TrackingParams(kernel="numpy"), recording_path=tmp_path / "r", bind="127.0.0.1:0")
    pipe.start()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    seq = dict.fromkeys(cams, 0)
    try:
        for k in range(40):
            for i in cams:
                ff = FeatureFrame(camera_index=i, seq=seq[i], camera_frame=k, trigger_frame=-1, total_points=1,
                                  points=points(i, k), edge_recv_ns=1, edge_done_ns=2)
                for d in encode_features(ff):
                    sock.sendto(d, pipe.address)
                    seq[i] += 1
            time.sleep(0.01)
        time.sleep(0.2)
    finally:
        sock.close()
        summary = pipe.stop()
    assert summary["estimates"] == 0 and summary["frames_tracked"] > 20
    why = " ".join(summary["why_nothing"])
    print("\n" + why)
    assert "died before confirmation" in why and "is the calibration in metres?" in why
    log = " ".join(r["message"] for r in load_recording(summary["recording"]).textlog)
    assert "no estimates: every new target died" in log and "tracker: NumPy path" in log
    assert "camera(s) 3 " in log and "are not in the calibration" in log
