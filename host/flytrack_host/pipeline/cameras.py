"""The rig's cameras from its calibration file, and what is missing from it for 3D tracking."""

from __future__ import annotations

from collections.abc import Mapping

from flytrack_host.geometry.camera import Camera
from flytrack_host.rig import RigConfig


def calibration_problems(rig: RigConfig, cameras: Mapping[int, Camera]) -> list[str]:
    """What is missing for 3D tracking: no calibration at all, or rig cameras absent from it."""
    if not cameras:
        where = f" ({rig.calibration_path} has none of the rig's cameras)" if rig.calibration_path else ""
        return [f"no calibration{where}: recording 2D data only, NO 3D tracking"]
    missing = [f"{c.index} ({c.calib_name})" for c in rig.cameras if c.index not in cameras]
    if missing:
        return [f"camera(s) {', '.join(missing)} are not in the calibration {rig.calibration_path}: their points "
                "cannot be used for 3D"]
    return []


def load_cameras(rig: RigConfig) -> dict[int, Camera]:
    """Calibration file of the rig -> camera_index -> Camera (empty without a calibration)."""
    path = rig.calibration_path
    if path is None:
        return {}
    from flytrack_host.geometry.formats import load_calibration

    by_name = load_calibration(path)
    cams = {}
    for c in rig.cameras:
        if c.calib_name in by_name:
            cams[c.index] = by_name[c.calib_name]
    return cams
