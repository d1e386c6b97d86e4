"""Event (DVS) cameras as observation sources for the 3D tracker, beside frame cameras.

An event camera's edge sends DVS_CLUSTERS per time slice of its own clock (protocol/SPEC.md 1.6), not
per trigger frame. For each trigger frame the tracker takes, this module picks, per DVS camera, the
clusters of the latest slice ending at or before that frame's time on the sensor's clock, moves them
to the frame's time with their velocities, and hands them to the tracker as that camera's 2D points
(a CameraFrame flagged `dvs`, so the recording's data2d rows say where they came from).

Sensor clock to trigger frames: the edge's DVS_CLUSTERS carry device times only (the sync events
stay in the edge), so the tie is made through the host's trigger clock model: a slice received at
host time r holds events no later than the frame the clock model gives r, so
t0 = t_end_us - frame(r) * period_us is a lower bound of the sensor time of trigger frame 0, and the
largest seen (the freshest slice) is the estimate. Its error is the edge-to-host delay of the freshest
slice (about a millisecond on loopback), well under a period at 100 fps.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from flytrack_host.camera import Camera
from flytrack_host.protocol.udp import POINT_DTYPE
from flytrack_host.receiver import DvsSlice
from flytrack_host.sync import CameraFrame

SLICES_KEPT = 256  # per camera: a few frames of 1 ms slices


@dataclass
class DvsCameraStats:
    slices: int = 0
    clusters: int = 0
    frames_given: int = 0  # trigger frames this camera gave the tracker points for
    points_given: int = 0
    no_slice: int = 0  # trigger frames without a recent slice (sensor silent, or behind)
    t0_us: float | None = None  # sensor time of trigger frame 0, as estimated


@dataclass
class _Cam:
    camera: Camera | None
    slices: deque = field(default_factory=lambda: deque(maxlen=SLICES_KEPT))
    stats: DvsCameraStats = field(default_factory=DvsCameraStats)


class DvsObservations:
    """Turns DVS slices into per-trigger-frame 2D observations.

    frame_of_host_time: the trigger clock model, host time (s) -> trigger frame (float)."""

    def __init__(self, cameras: dict[int, Camera | None], fps: float, max_age_frames: float = 2.0,
                 min_mass: float = 0.0) -> None:
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be positive, got {fps}")
        self.period_us = 1e6 / fps
        self.max_age_us = max_age_frames * self.period_us
        self.min_mass = float(min_mass)
        self.cams = {int(i): _Cam(c) for i, c in cameras.items()}

    @property
    def indices(self) -> Iterable[int]:
        return self.cams.keys()

    def add(self, sl: DvsSlice, frame_of_host_time: Callable[[float], float] | None) -> None:
        c = self.cams.get(sl.camera_index)
        if c is None:
            return
        m = sl.msg
        c.stats.slices += 1
        c.stats.clusters += len(m.clusters)
        if frame_of_host_time is not None:
            f = frame_of_host_time(sl.recv_time)
            if math.isfinite(f):
                cand = float(m.t_end_us) - f * self.period_us
                if c.stats.t0_us is None or cand > c.stats.t0_us:
                    c.stats.t0_us = cand
        c.slices.append((int(m.t_end_us), m.clusters, sl.recv_time, int(m.edge_done_ns)))

    def frame(self, cam_index: int, trigger_frame: int) -> CameraFrame | None:
        """The camera's observations for a trigger frame (None when it has nothing recent)."""
        c = self.cams.get(cam_index)
        if c is None or c.stats.t0_us is None:
            return None
        t_f = c.stats.t0_us + trigger_frame * self.period_us
        best = None
        for s in reversed(c.slices):
            if s[0] <= t_f + 0.25 * self.period_us:
                best = s
                break
        if best is None or t_f - best[0] > self.max_age_us:
            c.stats.no_slice += 1
            return None
        t_end, cl, recv, done_ns = best
        cl = cl[np.isfinite(cl["x"]) & np.isfinite(cl["y"]) & (cl["mass"] >= self.min_mass)]
        dt = (t_f - t_end) / 1e6
        x = cl["x"].astype(np.float64) + cl["vx"] * dt
        y = cl["y"].astype(np.float64) + cl["vy"] * dt
        pts = np.zeros(len(cl), dtype=POINT_DTYPE)
        pts["x_dist"], pts["y_dist"] = x, y
        if c.camera is not None and c.camera.has_distortion and len(cl):
            u = c.camera.undistort(np.column_stack([x, y]))
            pts["x_undist"], pts["y_undist"] = u[:, 0], u[:, 1]
        else:
            pts["x_undist"], pts["y_undist"] = x, y
        pts["area"] = np.pi * cl["size"].astype(np.float64) ** 2
        pts["orientation"] = np.nan
        pts["eccentricity"] = np.nan
        pts["peak_diff"] = cl["mass"]
        c.stats.frames_given += 1
        c.stats.points_given += len(pts)
        return CameraFrame(cam_index, trigger_frame, trigger_frame, pts, recv, edge_done_ns=done_ns,
                           total_points=len(pts), dvs=True)

    def stats(self) -> dict[int, dict[str, float | int | None]]:
        from dataclasses import asdict

        return {i: asdict(c.stats) for i, c in self.cams.items()}
