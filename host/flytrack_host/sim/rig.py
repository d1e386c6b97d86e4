"""A simulated camera rig around the arena, and the rig file that describes it.

Cameras stand on a ring around the arena at different elevations, each pulled back until the whole
arena fits in its image. Intrinsics and lens distortion are drawn from ranges typical of 640 x 480
machine-vision cameras with 4-6 mm lenses (focal 650-900 px, barrel distortion k1 -0.25..-0.05, a few
pixels of principal-point offset, a little tangential distortion), so the calibration the tracker
gets is as awkward as a real one.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.geometry.camera import Camera
from flytrack_host.rig import CameraConfig, HostConfig, RecordingConfig, RigConfig, TriggerConfig
from flytrack_host.sim.flight import Arena

# Elevations (degrees above the horizontal) cycled over the cameras: mixed views triangulate well.
_ELEVATIONS_DEG = (30.0, 55.0, 20.0, 70.0, 40.0)


def _fits(cam: Camera, pts: np.ndarray, margin_px: float) -> bool:
    return bool(np.all(cam.in_view(pts, margin=margin_px)))


def make_cameras(
    n: int,
    arena: Arena,
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    margin_px: float = 16.0,
    distortion: bool = True,
) -> list[Camera]:
    """N cameras around `arena`, each seeing all of it, with realistic intrinsics and distortion."""
    if not 1 <= n <= 64:
        raise ValueError(f"number of cameras must be 1..64, got {n}")
    if width < 64 or height < 64:
        raise ValueError(f"image size {width}x{height} is too small (at least 64x64)")
    rng = np.random.default_rng(seed + 7919)
    corners = arena.corners()
    center = arena.center
    cams: list[Camera] = []
    az0 = rng.uniform(0, 2 * math.pi)
    for i in range(n):
        az = az0 + 2 * math.pi * i / n + rng.uniform(-0.15, 0.15)
        el = math.radians(_ELEVATIONS_DEG[i % len(_ELEVATIONS_DEG)] + rng.uniform(-5, 5))
        direction = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        f = rng.uniform(650.0, 900.0)
        dist = (
            np.array([rng.uniform(-0.25, -0.05), rng.uniform(0.0, 0.1), rng.normal(0, 4e-4), rng.normal(0, 4e-4), 0.0])
            if distortion
            else np.zeros(5)
        )
        target = center + rng.normal(0, 0.01, 3)
        # Back away along the viewing direction until the whole arena is inside the image.
        r = 0.3
        while True:
            cam = Camera.look_at(f"cam{i + 1}", target + direction * r, target, width, height, f, dist=dist)
            if _fits(cam, corners, margin_px) or r > 50:
                break
            r *= 1.03
        K = cam.K.copy()
        K[0, 2] += rng.normal(0, 4.0)
        K[1, 2] += rng.normal(0, 4.0)
        K[1, 1] *= 1.0 + rng.normal(0, 0.002)  # pixels are almost, not exactly, square
        cams.append(Camera(cam.name, width, height, K, cam.R, cam.t, dist))
    return cams


def rig_config(
    cameras: Sequence[Camera],
    fps: float,
    listen: str,
    trigger_kind: str,
    trigger_port: str,
    calibration: str | None,
    recording_folder: str,
    live_subscribers: Sequence[str] = (),
    name: str = "simulated-rig",
    tracking: dict[str, Any] | None = None,
    dvs_cameras: Sequence[Camera] = (),
) -> RigConfig:
    """The rig file content for a simulated rig (all edges on loopback); event cameras come after the
    frame cameras, with the next indices."""
    n = len(cameras)
    return RigConfig(
        name=name,
        calibration=calibration,
        cameras=[CameraConfig(name=c.name, index=i, edge="127.0.0.1") for i, c in enumerate(cameras)]
        + [CameraConfig(name=c.name, index=n + i, edge="127.0.0.1", kind="dvs") for i, c in enumerate(dvs_cameras)],
        trigger=TriggerConfig(kind=trigger_kind, port=trigger_port, fps=fps),
        host=HostConfig(listen=listen, live_subscribers=list(live_subscribers)),
        recording=RecordingConfig(folder=recording_folder),
        **({"tracking": tracking} if tracking else {}),
    )


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"cannot write {v} into a rig file")
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"no TOML form for {type(v).__name__}")


def to_toml(data: dict[str, Any]) -> str:
    """TOML text for a rig dict: scalars, tables, and arrays of tables (all a rig file uses)."""
    lines: list[str] = ["# Written by the FlyTrack simulator (flytrack demo)."]
    tables: list[tuple[str, dict]] = []
    arrays: list[tuple[str, list[dict]]] = []
    for key, v in data.items():
        if v is None:
            continue
        if isinstance(v, dict):
            tables.append((key, v))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            arrays.append((key, v))
        else:
            lines.append(f"{key} = {_toml_value(v)}")
    for key, table in tables:
        lines += ["", f"[{key}]"]
        lines += [f"{k} = {_toml_value(x)}" for k, x in table.items() if x is not None]
    for key, items in arrays:
        for item in items:
            lines += ["", f"[[{key}]]"]
            lines += [f"{k} = {_toml_value(x)}" for k, x in item.items() if x is not None]
    return "\n".join(lines) + "\n"


def write_rig(rig: RigConfig, path: Path) -> Path:
    """Write `rig` as a TOML rig file that `flytrack_host.rig.load_rig` reads back identically."""
    data = rig.model_dump(mode="json", exclude={"base_dir"})
    path = Path(path)
    path.write_text(to_toml(data), encoding="utf-8")
    return path


def _write_calibration(cams: list[Camera], path: Path, notes: list[str]) -> Path | None:
    try:
        from flytrack_host.geometry.formats import save_flydra_xml
    except ImportError:
        notes.append("calibration writer missing: the host got the cameras directly")
        return None
    save_flydra_xml({c.name: c for c in cams}, path)
    return path


def _host_cameras(rig: Any, cams: list[Camera], calib_path: Path | None) -> dict[int, Camera]:
    """Cameras for the host, read back from the calibration file when there is one (as a user's)."""
    by_name = {c.name: c for c in cams}
    if calib_path is not None:
        from flytrack_host.geometry.formats import load_calibration

        by_name = load_calibration(calib_path)
    return {c.index: by_name[c.calib_name] for c in rig.cameras}
