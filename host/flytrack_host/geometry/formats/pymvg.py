"""pymvg JSON: `{"__pymvg_file_version__": "1.0", "camera_system": [{name, width, height, P, K, D, R,
Q, translation}]}` where Q (the rotation; "rotation" is read too) and translation are world -> camera,
K and D the distortion model, R the rectification (identity for us) and P the rectified projection.

pymvg's projection (its CameraModel.project_3d_to_pixel, ROS's pinhole model): the undistorted pixel is
P [R | t] X, skew P[0, 1] included; it is brought back to the plane the distortion acts on with P's
focal lengths and centre only (no skew), distorted by D, and put on the image with K's focal lengths and
centre (K's skew unused). That is FlyTrack's camera with K = P[:, :3] and K_dist = K without skew, exactly,
when P's focal lengths and centre are K's (as pymvg writes them for a camera without rectification)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from flytrack_host.geometry.camera import Camera

from .common import check_unique, fail, make_camera, matrix, resolution


def load_pymvg_json(path: str | Path, warnings: list[str] | None = None) -> dict[str, Camera]:
    warns = warnings if warnings is not None else []
    try:
        doc = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise fail(path, f"is not valid JSON ({exc.msg} at line {exc.lineno})", "Fix the file.") from None
    system = doc.get("camera_system") if isinstance(doc, dict) else None
    if not isinstance(system, list):
        raise fail(path, "has no 'camera_system' list", "This is not a pymvg camera-system file.")
    cams: list[Camera] = []
    for i, d in enumerate(system):
        if not isinstance(d, dict):
            raise fail(path, f"camera_system[{i}] is not an object", "Fix the file.")
        name = str(d.get("name", f"cam{i}"))
        missing = [k for k in ("width", "height", "K") if k not in d]
        rot_key = "rotation" if "rotation" in d else ("Q" if "Q" in d else None)
        if rot_key is None:
            missing.append("rotation")
        if "translation" not in d:
            missing.append("translation")
        if missing:
            raise fail(path, f"camera {name!r} lacks {', '.join(missing)}", "pymvg cameras need all of them.")
        w, h = resolution(d["width"], d["height"], path, f"camera {name!r}")
        K = matrix(d["K"], (3, 3), path, f"camera {name!r} K")
        R = matrix(d[rot_key], (3, 3), path, f"camera {name!r} rotation")
        t = matrix(d["translation"], (1, 3), path, f"camera {name!r} translation").ravel()
        D = np.asarray(d.get("D", [0, 0, 0, 0, 0]), dtype=np.float64).ravel()
        if D.size > 5:
            raise fail(path, f"camera {name!r}: D has {D.size} coefficients", "FlyTrack handles k1 k2 p1 p2 k3.")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise fail(path, f"camera {name!r}: rotation is not a proper rotation matrix", "Fix the file.")
        rect = d.get("R")
        if rect is not None and not np.allclose(np.asarray(rect, dtype=float), np.eye(3), atol=1e-12):
            warns.append(f"camera {name!r}: non-identity rectification R ignored (only K, D, rotation, "
                         "translation define the distorted projection)")
        K_ideal, K_dist = K, None
        if "P" in d:
            P = matrix(d["P"], (3, 4), path, f"camera {name!r} P")
            if not abs(P[2, 2] - 1.0) <= 1e-8 or np.any(P[:, 3] != 0):
                raise fail(path, f"camera {name!r}: P must have P[2, 2] = 1 and a zero last column (pymvg's rule)",
                           "Fix or regenerate the file.")
            K_ideal = P[:, :3]
        # The distortion acts about K's focal lengths and centre, without skew (see the module docstring).
        plain = np.array([[K[0, 0], 0.0, K[0, 2]], [0.0, K[1, 1], K[1, 2]], [0.0, 0.0, 1.0]])
        if not np.allclose(np.delete(K_ideal.ravel(), 1), np.delete(plain.ravel(), 1), rtol=1e-12, atol=1e-12):
            warns.append(f"camera {name!r}: P's focal lengths or centre differ from K's; FlyTrack takes P's for "
                         "the pinhole and K's for the distortion, which pymvg does not do exactly")
        if K_ideal[0, 1] != 0.0 or not np.allclose(K_ideal, plain, rtol=1e-12, atol=1e-12):
            K_dist = plain
        cams.append(make_camera(path, name=name, width=w, height=h, K=K_ideal, R=R, t=t, dist=D, K_dist=K_dist))
    check_unique([c.name for c in cams], path)
    return {c.name: c for c in cams}


def save_pymvg_json(cameras: Mapping[str, Camera], path: str | Path) -> None:
    system = []
    for name, cam in cameras.items():
        P = np.zeros((3, 4))
        P[:, :3] = cam.K
        # pymvg distorts about K's focal lengths and centre: the camera's own K_dist when it has one.
        K = cam.K if cam.K_dist is None else cam.K_dist
        system.append({
            "name": name,
            "width": int(cam.width),
            "height": int(cam.height),
            "P": P.tolist(),
            "K": np.asarray(K).tolist(),
            "D": [float(v) for v in cam.dist],
            "R": np.eye(3).tolist(),
            "Q": cam.R.tolist(),  # pymvg's key for the rotation (it reads no other)
            "translation": [float(v) for v in cam.t],
        })
    doc = {"__pymvg_file_version__": "1.0", "camera_system": system}
    Path(path).write_text(json.dumps(doc, indent=2) + "\n")
