"""With and without the event cameras, side by side: the same frame bundles tracked twice.

A live run gives the tracker each trigger frame's bundle once, event cameras' points included. To say
what those points are worth, the host keeps the bundles (HostPipeline.dvs_bundles, bounded, off unless
asked) and this module tracks them again with fresh trackers: once as they were (the event cameras'
points with their covariances) and once without the event cameras. Both runs see exactly the same
frame cameras' points, every bundle of the run (also those a busy host recorded without tracking),
so the difference is the event cameras' alone.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from flytrack_host.geometry.camera import Camera
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.tracker import Tracker
from flytrack_host.tracking.types import FrameBundle


@dataclass
class TrackedRun:
    """One re-run: per bundle (trigger frame, object ids, positions), and the tracker's counters."""

    frames: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)
    stats: dict[str, int] = field(default_factory=dict)


def without_cameras(b: FrameBundle, drop: set[int]) -> FrameBundle:
    return FrameBundle(b.trigger_frame, b.timestamp, {c: a for c, a in b.detections.items() if c not in drop},
                       b.missing_cameras, {c: v for c, v in b.point_cov.items() if c not in drop})


def track(bundles: Iterable[FrameBundle], cameras: Mapping[int, Camera], params: TrackingParams,
          frame_period_s: float) -> TrackedRun:
    tr = Tracker(cameras, params, frame_period_s)
    run = TrackedRun()
    for b in bundles:
        res = tr.process(b)
        ids = np.array([e.obj_id for e in res.estimates], dtype=np.int64)
        pos = np.array([e.state[:3] for e in res.estimates], dtype=np.float64).reshape(-1, 3)
        run.frames.append((int(b.trigger_frame), ids, pos))
    run.stats = dict(tr.stats)
    return run


def with_and_without(bundles: list[FrameBundle], cameras: Mapping[int, Camera], params: TrackingParams,
                     frame_period_s: float, dvs_cameras: Iterable[int]) -> dict[str, TrackedRun]:
    """{"with_dvs": ..., "without_dvs": ...} over the same bundles, in trigger-frame order."""
    drop = {int(c) for c in dvs_cameras}
    ordered = sorted(bundles, key=lambda b: b.trigger_frame)
    return {
        "with_dvs": track(ordered, cameras, params, frame_period_s),
        "without_dvs": track((without_cameras(b, drop) for b in ordered), cameras, params, frame_period_s),
    }
