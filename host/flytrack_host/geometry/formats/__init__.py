"""Calibration files in and out: flydra XML (and a flydra .h5's calibration), pymvg JSON, OpenCV YAML,
anipose TOML, one module per format.

Every reader returns `dict[str, Camera]` (camera name -> the one camera model of `flytrack_host.geometry.camera`),
so the tracker, the simulator and the calibration never see a file format. `load_calibration` detects the
format from the content; `save_calibration` writes one, refusing what the format cannot hold.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from flytrack_host.geometry.camera import Camera

from .anipose import load_anipose_toml, save_anipose_toml
from .common import CalibrationFormatError, fail
from .flydra import flydra_projection, load_flydra_h5_calibration, load_flydra_xml, save_flydra_xml
from .opencv_yaml import load_opencv_yaml
from .pymvg import load_pymvg_json, save_pymvg_json

__all__ = [
    "CalibrationFormatError",
    "detect_format",
    "load_calibration",
    "load_flydra_xml",
    "load_flydra_h5_calibration",
    "load_pymvg_json",
    "load_opencv_yaml",
    "load_anipose_toml",
    "save_calibration",
    "save_flydra_xml",
    "save_pymvg_json",
    "save_anipose_toml",
    "flydra_projection",
    "single_k_approximation",
    "compare_projections",
    "FORMATS",
]

FORMATS = ("flydra-xml", "pymvg-json", "opencv-yaml", "anipose-toml", "flydra-h5")
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


def detect_format(path: str | Path) -> str:
    """Guess the format from the content (not the file name)."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except FileNotFoundError:
        raise fail(p, "no such file", "Check the path.") from None
    except OSError as exc:
        raise fail(p, f"cannot be read ({exc.strerror})", "Check the path and its permissions.") from None
    if raw.startswith(_HDF5_MAGIC):
        return "flydra-h5"  # flydra's .h5 with a calibration group (read by io.flydra_h5)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise fail(p, "is not a text file",
                    "Give a flydra XML or .h5, pymvg JSON, OpenCV YAML or anipose TOML file.") from None
    head = text.lstrip()
    if not head:
        raise fail(p, "is empty", "Give a calibration file with at least one camera.")
    if head.startswith("<"):
        return "flydra-xml"
    if head.startswith("{"):
        return "pymvg-json"
    if head.startswith("%YAML") or head.startswith("---"):
        return "opencv-yaml"
    if head.startswith("[") or "=" in head.splitlines()[0]:
        return "anipose-toml"
    raise fail(p, "is not a calibration format FlyTrack knows",
                "Give a flydra XML, pymvg JSON, OpenCV YAML (%YAML:1.0) or anipose TOML file.")


def load_calibration(
    path: str | Path, warnings: list[str] | None = None, fidelity: dict[str, float] | None = None
) -> dict[str, Camera]:
    """Read any supported calibration file (format detected from its content). The readers' warnings
    (e.g. a flydra model FlyTrack reproduces only approximately) go to `warnings` when given, else to
    this module's logger at WARNING level, so they always reach the user. `fidelity` gets, per camera
    whose file model FlyTrack can only approximate, the largest pixel difference measured over its image."""
    import logging

    fmt = detect_format(path)
    warns: list[str] = []
    if fmt == "flydra-xml":
        cams = load_flydra_xml(path, warns, fidelity)
    elif fmt == "pymvg-json":
        cams = load_pymvg_json(path, warns)
    elif fmt == "flydra-h5":
        cams = load_flydra_h5_calibration(path, warns)
    elif fmt == "opencv-yaml":
        cams = load_opencv_yaml(path)
    else:
        cams = load_anipose_toml(path)
    if not cams:
        raise fail(path, "contains no cameras", "Give a calibration file with at least one camera.")
    if warnings is not None:
        warnings.extend(warns)
    else:
        for w in warns:
            logging.getLogger(__name__).warning("%s: %s", path, w)
    return cams


def single_k_approximation(cam: Camera) -> Camera:
    """`cam` with its distortion about P's own K (K_dist dropped), the coefficients refitted by linear least
    squares so the distorted projection stays as close as one K allows over the image (formats with one K
    per camera). The caller measures how close (compare_projections)."""
    if cam.K_dist is None:
        return cam
    gu, gv = np.meshgrid(np.linspace(0, cam.width - 1, 25), np.linspace(0, cam.height - 1, 25))
    uv = np.stack([gu.ravel(), gv.ravel()], axis=1)
    ideal = cam.undistort(uv)
    ok = np.isfinite(ideal).all(axis=1)
    uv, ideal = uv[ok], ideal[ok]
    K = cam.K
    y = (ideal[:, 1] - K[1, 2]) / K[1, 1]
    x = (ideal[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    yd = (uv[:, 1] - K[1, 2]) / K[1, 1]
    xd = (uv[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    r2 = x * x + y * y
    # xd - x = x (k1 r2 + k2 r4 + k3 r6) + 2 p1 x y + p2 (r2 + 2 x^2); yd - y likewise: linear in the 5.
    ax = np.stack([x * r2, x * r2**2, 2 * x * y, r2 + 2 * x * x, x * r2**3], axis=1)
    ay = np.stack([y * r2, y * r2**2, r2 + 2 * y * y, 2 * x * y, y * r2**3], axis=1)
    A = np.concatenate([ax * K[0, 0], ay * K[1, 1]])  # weighted to pixels
    b = np.concatenate([(xd - x) * K[0, 0], (yd - y) * K[1, 1]])
    coef = np.linalg.lstsq(A, b, rcond=None)[0]
    return Camera(name=cam.name, width=cam.width, height=cam.height, K=cam.K, R=cam.R, t=cam.t,
                  dist=coef, interface=cam.interface)


def save_calibration(cameras: Mapping[str, Camera], path: str | Path, fmt: str | None = None) -> None:
    """Write cameras in `fmt` (or guessed from the suffix: .xml, .json, .toml)."""
    if fmt is None:
        suffix = Path(path).suffix.lower()
        fmt = {".xml": "flydra-xml", ".json": "pymvg-json", ".toml": "anipose-toml"}.get(suffix)
        if fmt is None:
            raise CalibrationFormatError(
                f"{path}: cannot tell the output format from the suffix {suffix!r}. "
                "Use .xml (flydra), .json (pymvg) or .toml (anipose), or pass --format flydra-xml, pymvg-json "
                "or anipose-toml.")
    writers = {"flydra-xml": save_flydra_xml, "pymvg-json": save_pymvg_json, "anipose-toml": save_anipose_toml}
    if fmt not in writers:
        raise CalibrationFormatError(f"cannot write format {fmt!r}; FlyTrack writes {sorted(writers)}.")
    if fmt != "flydra-xml" and any(c.interface is not None for c in cameras.values()):
        raise CalibrationFormatError(
            f"{path}: {fmt} has no place for refraction (these cameras look through water); write flydra XML "
            "(.xml), whose <water> element keeps it.")
    mirrored = [n for n, c in cameras.items() if np.linalg.det(c.R) < 0]
    if fmt != "flydra-xml" and mirrored:
        raise CalibrationFormatError(
            f"{path}: {fmt} holds rotations, but the world of camera(s) {', '.join(mirrored)} is mirrored (as "
            "MultiCamSelfCal can give: an improper rotation); write flydra XML (.xml), which keeps it.")
    if fmt != "flydra-xml" and any(c.K_dist is not None and not (fmt == "pymvg-json" and _pymvg_keeps(c))
                                   for c in cameras.values()):
        raise CalibrationFormatError(
            f"{path}: {fmt} has one K per camera, but these cameras' distortion is about another K than their "
            "projection's (flydra's model); write flydra XML (.xml), which keeps it exactly, or convert with "
            "`flytrack calibrate convert`, which approximates it and measures how well.")
    writers[fmt](cameras, path)


def compare_projections(a: Mapping[str, Camera], b: Mapping[str, Camera]) -> dict[str, float]:
    """Per camera of `a` (also in `b`): the largest pixel distance between their distorted projections
    of 3D points on the rays of a 9x9 pixel grid at 3 depths around the rig's scale (a conversion check)."""
    centres = np.stack([c.center for c in a.values()])
    scale = max(float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max()), 1e-3)
    out: dict[str, float] = {}
    for name, ca in a.items():
        cb = b.get(name)
        if cb is None:
            out[name] = float("inf")
            continue
        gu, gv = np.meshgrid(np.linspace(0, ca.width - 1, 9), np.linspace(0, ca.height - 1, 9))
        uv = np.stack([gu.ravel(), gv.ravel()], axis=1)
        o, d = ca.refracted_rays(uv)
        ok = np.isfinite(d).all(axis=1)
        X = np.concatenate([o[ok] + f * scale * d[ok] for f in (0.3, 1.0, 2.0)])
        pa, pb = ca.project(X), cb.project(X)
        good = np.isfinite(pa).all(axis=1)
        diff = np.linalg.norm(pa[good] - pb[good], axis=1)
        out[name] = float(np.nan_to_num(diff, nan=np.inf).max()) if diff.size else 0.0
    return out


def _pymvg_keeps(cam: Camera) -> bool:
    """pymvg distorts about K's focal lengths and centre without skew (formats/pymvg.py): a camera whose
    K_dist is exactly that is a pymvg camera."""
    K, Kd = cam.K, cam.K_dist
    assert Kd is not None
    return bool(Kd[0, 1] == 0.0 and Kd[0, 0] == K[0, 0] and Kd[1, 1] == K[1, 1] and Kd[0, 2] == K[0, 2]
                and Kd[1, 2] == K[1, 2] and Kd[1, 0] == Kd[2, 0] == Kd[2, 1] == 0.0 and Kd[2, 2] == 1.0)
