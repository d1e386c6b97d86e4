"""Helpers for the host data-path tests: a stand-in tracker and a UDP edge simulator.

The stand-in tracker isolates the data path (receive, synchronise, record, serve live) from tracking
quality: it reports one object per frame at the mean of the first points of each camera, so a test
can predict every estimate and needs no calibration. The real `Tracker` runs end to end over UDP in
test_braidz_schema.py (and the tracker itself is tested in host/tests/tracking/).
"""

from __future__ import annotations

import socket
from collections.abc import Mapping

import numpy as np
import pytest

from flytrack_host.protocol.udp import POINT_DTYPE, FeatureFrame, encode_features
from flytrack_host.rig import parse_rig
from flytrack_host.tracking.types import Association, Estimate, FrameBundle, FrameResult


class StandInTracker:
    def __init__(self, cameras: Mapping, params, frame_period_s: float):
        self.period = frame_period_s
        self.frames = 0

    def process(self, bundle: FrameBundle) -> FrameResult:
        self.frames += 1
        res = FrameResult(bundle.trigger_frame, bundle.timestamp)
        used = {c: p for c, p in bundle.detections.items() if len(p)}
        if len(used) >= 2:
            xs = np.array([p["x_dist"][0] for p in used.values()], dtype=float)
            state = np.array([xs.mean() / 1000.0, 0.0, 0.1, 0.0, 0.0, 0.0])
            res.estimates.append(Estimate(1, state, np.eye(6) * 1e-4, len(used)))
            res.associations.extend(Association(1, c, 0) for c in used)
        return res


def stand_in_factory(cameras, params, period):
    return StandInTracker(cameras, params, period)


def points_for(cam: int, frame: int, n: int = 2) -> np.ndarray:
    """Deterministic points, so a test can recompute what was sent."""
    p = np.zeros(n, POINT_DTYPE)
    k = np.arange(n, dtype=np.float32)
    p["x_dist"] = 100.0 + cam * 10 + k + (frame % 1000) * 0.25
    p["y_dist"] = 200.0 + k
    p["x_undist"] = p["x_dist"]
    p["y_undist"] = p["y_dist"]
    p["area"] = 5.0 + k
    p["peak_diff"] = 40.0
    p["orientation"] = np.nan
    p["eccentricity"] = np.nan
    p["cur_val"] = 200
    p["mean_val"] = 10.0
    p["sumsq_val"] = 120.0
    return p


class EdgeSim:
    """One simulated edge: sends FEATURES datagrams for a camera over real UDP."""

    def __init__(self, cam: int, dest: tuple[str, int], src_ip: str = "127.0.0.1", frame0: int = 0,
                 edge_trigger: bool = False):
        self.cam = cam
        self.edge_trigger = edge_trigger  # the edge fills trigger_frame itself
        self.dest = dest
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((src_ip, 0))
        self.seq = 0
        self.frame0 = frame0

    def datagrams(self, frame: int, n_points: int = 2, trigger_frame: int | None = None) -> list[bytes]:
        if trigger_frame is None:
            trigger_frame = frame if self.edge_trigger else -1
        pts = points_for(self.cam, frame, n_points)
        ff = FeatureFrame(camera_index=self.cam, seq=self.seq, camera_frame=self.frame0 + frame,
                          trigger_frame=trigger_frame, total_points=n_points, points=pts,
                          edge_recv_ns=1, edge_done_ns=2)
        out = encode_features(ff)
        self.seq += len(out)
        return out

    def send(self, frame: int, **kw) -> None:
        for d in self.datagrams(frame, **kw):
            self.sock.sendto(d, self.dest)

    def raw(self, data: bytes) -> None:
        self.sock.sendto(data, self.dest)

    def close(self) -> None:
        self.sock.close()


def make_rig(n_cams: int = 3, fps: float = 200.0, subscribers: list[str] | None = None, folder: str = "rec",
             flush_interval_s: float = 1.0):
    return parse_rig({
        "name": "testrig",
        "trigger": {"kind": "software", "fps": fps},
        "host": {"listen": "127.0.0.1:7000", "live_subscribers": subscribers or [], "sync_deadline_fraction": 0.5},
        "recording": {"folder": folder, "flush_interval_s": flush_interval_s},
        "cameras": [{"name": f"cam{i}", "index": i, "edge": "127.0.0.1"} for i in range(n_cams)],
    })


@pytest.fixture
def helpers():
    class H:
        pass

    h = H()
    h.EdgeSim = EdgeSim
    h.make_rig = make_rig
    h.points_for = points_for
    h.factory = stand_in_factory
    h.StandInTracker = StandInTracker
    return h
