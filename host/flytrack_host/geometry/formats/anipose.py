"""anipose TOML: one `[cam_N]` table per camera (name, size, matrix, distortions, Rodrigues rotation,
translation) and a `[metadata]` table."""

from __future__ import annotations

import json
import tomllib
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from flytrack_host.geometry.camera import Camera

from .common import check_unique, fail, fmt, make_camera, matrix, matrix_to_rodrigues, resolution, rodrigues_to_matrix


def load_anipose_toml(path: str | Path) -> dict[str, Camera]:
    try:
        doc = tomllib.loads(Path(path).read_text())
    except tomllib.TOMLDecodeError as exc:
        raise fail(path, f"is not valid TOML ({exc})", "Fix the file.") from None
    cams: list[Camera] = []
    for key, d in doc.items():
        if key == "metadata" or not isinstance(d, dict):
            continue
        name = str(d.get("name", key))
        missing = [k for k in ("size", "matrix", "rotation", "translation") if k not in d]
        if missing:
            raise fail(path, f"[{key}] lacks {', '.join(missing)}", "anipose cameras need size, matrix, "
                        "distortions, rotation (Rodrigues vector) and translation.")
        size = np.asarray(d["size"]).ravel()
        if size.size != 2:
            raise fail(path, f"[{key}] size must be [width, height]", "Fix the file.")
        w, h = resolution(size[0], size[1], path, f"camera {name!r}")
        K = matrix(d["matrix"], (3, 3), path, f"camera {name!r} matrix")
        D = np.asarray(d.get("distortions", [0, 0, 0, 0, 0]), dtype=float).ravel()
        if D.size > 5:
            raise fail(path, f"camera {name!r}: {D.size} distortions", "FlyTrack handles k1 k2 p1 p2 k3.")
        rvec = matrix(d["rotation"], (1, 3), path, f"camera {name!r} rotation").ravel()
        t = matrix(d["translation"], (1, 3), path, f"camera {name!r} translation").ravel()
        cams.append(make_camera(path, name=name, width=w, height=h, K=K, R=rodrigues_to_matrix(rvec), t=t,
                                 dist=D))
    if not cams:
        raise fail(path, "holds no [cam_*] table", "This is not an anipose calibration file.")
    check_unique([c.name for c in cams], path)
    return {c.name: c for c in cams}


def save_anipose_toml(cameras: Mapping[str, Camera], path: str | Path) -> None:
    def arr(a: np.ndarray) -> str:
        if a.ndim == 1:
            return "[ " + ", ".join(fmt(v) for v in a) + ",]"
        return "[ " + ", ".join(arr(r) for r in a) + ",]"

    lines: list[str] = []
    for i, (name, cam) in enumerate(cameras.items()):
        lines += [f"[cam_{i}]", f"name = {json.dumps(name)}", f"size = [ {int(cam.width)}, {int(cam.height)},]",
                  f"matrix = {arr(cam.K)}", f"distortions = {arr(cam.dist)}",
                  f"rotation = {arr(matrix_to_rodrigues(cam.R))}", f"translation = {arr(cam.t)}", ""]
    lines += ["[metadata]", 'adjusted = true', 'error = 0.0', ""]
    Path(path).write_text("\n".join(lines))
