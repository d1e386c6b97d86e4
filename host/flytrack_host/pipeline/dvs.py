"""Event cameras (DVS) in the host pipeline: their time slices are kept and their clusters join the
bundles of the frame cameras (flytrack_host.dvs.clusters). A mixin of `HostPipeline`."""

from __future__ import annotations

import math

from flytrack_host.intake.receiver import DvsSlice
from flytrack_host.intake.sync import (
    SyncedBundle,
)


class DvsIntake:
    """`HostPipeline`'s event-camera part (uses its `dvs_obs`, `dvs_slices` and `sync`)."""

    def _dvs_slice(self, item: DvsSlice) -> None:
        """An event camera's time slice: kept, to give its clusters to the tracker at the trigger
        frames it covers (flytrack_host.dvs.clusters)."""
        self.dvs_slices[item.camera_index] = self.dvs_slices.get(item.camera_index, 0) + 1
        if self.dvs_obs is not None:
            self.dvs_obs.add(item, self._frame_of_host_time)

    def _frame_of_host_time(self, t: float) -> float:
        """The trigger clock model inverted: host time -> trigger frame (NaN before it is known)."""
        clock = self.sync.clock if self.sync is not None else None
        if clock is None:
            return math.nan
        t0, t1 = float(clock.frame_to_host_time(0)), float(clock.frame_to_host_time(1000))
        if not (math.isfinite(t0) and math.isfinite(t1)) or t1 <= t0:
            return math.nan
        return (t - t0) / ((t1 - t0) / 1000.0)

    def _add_dvs(self, sb: SyncedBundle, count: bool = True) -> None:
        """Event cameras' observations join the bundle of frame cameras (a rig may mix them)."""
        if self.dvs_obs is None:
            return
        tf = sb.bundle.trigger_frame
        for ci in self.dvs_obs.indices:
            got = self.dvs_obs.frame(ci, tf)
            if got is not None:
                fr, cov = got
                if count:
                    self.dvs_obs.count(ci, len(fr.points))
                sb.frames[ci] = fr
                sb.bundle.detections[ci] = fr.points
                # their own covariance is their measurement noise, and they never start a track
                sb.bundle.point_cov[ci] = cov
