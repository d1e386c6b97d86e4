"""Event (DVS) cameras as observation sources for the 3D tracker, beside frame cameras.

An event camera's edge sends DVS_CLUSTERS per time slice of its own clock (protocol/SPEC.md 1.6), not
per trigger frame. For each trigger frame the tracker takes, this module picks, per DVS camera, the
clusters of the latest slice stated at or before that frame, moves them to the frame's time with their
velocities, and hands them to the tracker as that camera's 2D points (a CameraFrame flagged `dvs`, so
the recording's data2d rows say where they came from) with their position covariances (the edge's
Kalman filters', grown by the move), which the tracker uses as each point's measurement noise.

Sensor clock to trigger frames: the edge stamps each slice with the trigger frame at its end, from the
sync events the sensor records at every trigger pulse (flag SYNCED), and cuts a slice at each sync, so
that most slices are stated exactly at a trigger frame. Without the stamp (an edge that sees no sync
events) the tie is made through the host's trigger clock model: a slice received at host time r holds
events no later than the frame the clock model gives r, so t0 = t_end_us - frame(r) * period_us is a
lower bound of the sensor time of trigger frame 0, and the largest seen is the estimate (early by the
edge-to-host delay of the freshest slice).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from flytrack_host.geometry.camera import Camera
from flytrack_host.intake.receiver import DvsSlice
from flytrack_host.intake.sync import CameraFrame
from flytrack_host.protocol.udp import POINT_DTYPE

SLICES_KEPT = 256  # per camera: a few frames of 1 ms slices


@dataclass
class DvsCameraStats:
    slices: int = 0
    clusters: int = 0
    frames_given: int = 0  # trigger frames this camera gave the tracker points for
    points_given: int = 0  # given to the tracker (which gates them on their covariance)
    points_used: int = 0  # associated with a target by the 3D tracker
    no_slice: int = 0  # trigger frames without a recent slice (sensor silent, or behind)
    synced_slices: int = 0  # slices the edge stamped with their trigger frame (sync events)
    t0_us: float | None = None  # sensor time of trigger frame 0, as estimated (unsynced slices)


@dataclass
class _Cam:
    camera: Camera | None
    slices: deque = field(default_factory=lambda: deque(maxlen=SLICES_KEPT))
    stats: DvsCameraStats = field(default_factory=DvsCameraStats)


class DvsObservations:
    """Turns DVS slices into per-trigger-frame 2D observations.

    frame_of_host_time: the trigger clock model, host time (s) -> trigger frame (float)."""

    def __init__(self, cameras: dict[int, Camera | None], fps: float, max_age_frames: float = 2.0,
                 min_mass: float = 0.0, blob_radius_px: float = 3.0, velocity_std_px_s: float = 50.0) -> None:
        """blob_radius_px: the animal's apparent radius on the event sensor, for the points' area. A
        cluster's `size` is the tracker's a priori search radius (10% of the sensor), not the animal's;
        as area it would fail the 3D tracker's area gate and drag each target's smoothed area away
        from what the frame cameras see. velocity_std_px_s: the uncertainty of a cluster's velocity
        (the record carries the position covariance only), which grows the covariance of a point
        moved by dt by (velocity_std_px_s dt)^2 per axis."""
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be positive, got {fps}")
        self.period_us = 1e6 / fps
        self.max_age_us = max_age_frames * self.period_us
        self.min_mass = float(min_mass)
        self.area_px = math.pi * float(blob_radius_px) ** 2
        self.vel_var = float(velocity_std_px_s) ** 2
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
        frame_end = None
        if m.synced and math.isfinite(m.trigger_frame) and m.frame_period_us > 0:
            c.stats.synced_slices += 1
            frame_end = float(m.trigger_frame)
        elif frame_of_host_time is not None:
            f = frame_of_host_time(sl.recv_time)
            if math.isfinite(f):
                cand = float(m.t_end_us) - f * self.period_us
                if c.stats.t0_us is None or cand > c.stats.t0_us:
                    c.stats.t0_us = cand
        c.slices.append((frame_end, int(m.t_end_us), m.clusters, sl.recv_time, int(m.edge_done_ns)))

    def _slice_for(self, c: _Cam, trigger_frame: int) -> tuple[tuple, float] | None:
        """The latest slice stated at or before the frame (a quarter period of slack), and the time
        (s) from its end to the frame."""
        for s in reversed(c.slices):
            if s[0] is not None:  # stamped by the edge
                lag = trigger_frame - s[0]
            elif c.stats.t0_us is not None:
                lag = (c.stats.t0_us + trigger_frame * self.period_us - s[1]) / self.period_us
            else:
                continue
            if lag >= -0.25:
                return (s, lag * self.period_us / 1e6) if lag * self.period_us <= self.max_age_us else None
        return None

    def frame(self, cam_index: int, trigger_frame: int) -> tuple[CameraFrame, np.ndarray] | None:
        """The camera's observations for a trigger frame and their covariances ((n, 3) var_x, var_y,
        cov_xy in distorted px^2), or None when it has nothing recent."""
        c = self.cams.get(cam_index)
        if c is None:
            return None
        got = self._slice_for(c, trigger_frame)
        if got is None:
            c.stats.no_slice += 1
            return None
        (_f, _t_end, cl, recv, done_ns), dt = got
        cl = cl[np.isfinite(cl["x"]) & np.isfinite(cl["y"]) & (cl["mass"] >= self.min_mass)]
        x = cl["x"].astype(np.float64) + cl["vx"] * dt
        y = cl["y"].astype(np.float64) + cl["vy"] * dt
        grow = self.vel_var * dt * dt
        cov = np.column_stack([cl["var_x"].astype(np.float64) + grow, cl["var_y"].astype(np.float64) + grow,
                               cl["cov_xy"].astype(np.float64)])
        pts = np.zeros(len(cl), dtype=POINT_DTYPE)
        pts["x_dist"], pts["y_dist"] = x, y
        if c.camera is not None and c.camera.has_distortion and len(cl):
            u = c.camera.undistort(np.column_stack([x, y]))
            pts["x_undist"], pts["y_undist"] = u[:, 0], u[:, 1]
        else:
            pts["x_undist"], pts["y_undist"] = x, y
        pts["area"] = self.area_px
        pts["orientation"] = np.nan
        pts["eccentricity"] = np.nan
        pts["peak_diff"] = cl["mass"]
        fr = CameraFrame(cam_index, trigger_frame, trigger_frame, pts, recv, edge_done_ns=done_ns,
                         total_points=len(pts), dvs=True)
        return fr, cov

    def count(self, cam_index: int, given: int, used: int = 0) -> None:
        c = self.cams.get(cam_index)
        if c is not None:
            c.stats.frames_given += 1 if given else 0
            c.stats.points_given += given
            c.stats.points_used += used

    def stats(self) -> dict[int, dict[str, float | int | None]]:
        from dataclasses import asdict

        return {i: asdict(c.stats) for i, c in self.cams.items()}
