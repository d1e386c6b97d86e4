"""Calibration files in and out: flydra XML, pymvg JSON, OpenCV YAML, anipose TOML.

Every reader returns `dict[str, Camera]` (camera name -> the one camera model of `flytrack_host.camera`),
so the tracker, the simulator and the calibration never see a file format.

flydra XML (`multi_camera_reconstructor`): per camera a `calibration_matrix` P (3x4, for undistorted pixels,
rows separated by ';'), `resolution` (width height) and optional `non_linear_parameters` (Bouguet's
model: fc1 fc2 cc1 cc2 k1 k2 p1 p2 alpha_c, optionally k3 and the rectified intrinsics fc1p fc2p cc1p cc2p).
An optional `<water>n</water>` in the root (Braid) puts every camera above a water surface at z = 0 of
refractive index n (Camera.interface = refraction.FlatInterface.water_surface(n)); we write it back.
A per-camera `scale_factor` multiplies the last column of P (old files in mm -> m). We write P = K[R|t]
with 17 significant digits and fc1p.. equal to fc1.., so a file we write reads back exactly.

pymvg JSON: `{"__pymvg_file_version__": "1.0", "camera_system": [{name, width, height, P, K, D, R,
rotation, translation}]}` where rotation/translation are world -> camera, K and D the distortion model,
R the rectification (identity for us) and P the rectified projection.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from flytrack_host.camera import Camera, distort_normalized
from flytrack_host.refraction import FlatInterface

__all__ = [
    "CalibrationFormatError",
    "detect_format",
    "load_calibration",
    "load_flydra_xml",
    "load_pymvg_json",
    "load_opencv_yaml",
    "load_anipose_toml",
    "save_calibration",
    "save_flydra_xml",
    "save_pymvg_json",
    "save_anipose_toml",
    "FORMATS",
]

FORMATS = ("flydra-xml", "pymvg-json", "opencv-yaml", "anipose-toml", "flydra-h5")
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"

# Below this many pixels a flydra camera whose distortion and projection intrinsics differ is still
# represented exactly enough by one K; above it the reader says how far off it is.
_FLYDRA_APPROX_WARN_PX = 1e-3


class CalibrationFormatError(ValueError):
    """A calibration file that cannot be read; the message says what is wrong and what to do."""


def _fail(path: Path | str, what: str, fix: str) -> CalibrationFormatError:
    return CalibrationFormatError(f"{path}: {what}. {fix}")


# ---------------------------------------------------------------------------------------------
# detection
# ---------------------------------------------------------------------------------------------
def detect_format(path: str | Path) -> str:
    """Guess the format from the content (not the file name)."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except FileNotFoundError:
        raise _fail(p, "no such file", "Check the path.") from None
    except OSError as exc:
        raise _fail(p, f"cannot be read ({exc.strerror})", "Check the path and its permissions.") from None
    if raw.startswith(_HDF5_MAGIC):
        return "flydra-h5"  # flydra's .h5 with a calibration group (read by io.flydra_h5)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise _fail(p, "is not a text file",
                    "Give a flydra XML or .h5, pymvg JSON, OpenCV YAML or anipose TOML file.") from None
    head = text.lstrip()
    if not head:
        raise _fail(p, "is empty", "Give a calibration file with at least one camera.")
    if head.startswith("<"):
        return "flydra-xml"
    if head.startswith("{"):
        return "pymvg-json"
    if head.startswith("%YAML") or head.startswith("---"):
        return "opencv-yaml"
    if head.startswith("[") or "=" in head.splitlines()[0]:
        return "anipose-toml"
    raise _fail(p, "is not a calibration format FlyTrack knows",
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
        raise _fail(path, "contains no cameras", "Give a calibration file with at least one camera.")
    if warnings is not None:
        warnings.extend(warns)
    else:
        for w in warns:
            logging.getLogger(__name__).warning("%s: %s", path, w)
    return cams


def load_flydra_h5_calibration(path: str | Path, warnings: list[str] | None = None) -> dict[str, Camera]:
    """The `calibration` group of a flydra .h5 (io.flydra_h5.read_flydra_calibration)."""
    import h5py

    from flytrack_host.io.flydra_h5 import FlydraH5Error, read_flydra_calibration

    try:
        with h5py.File(path, "r") as h5:
            cams = read_flydra_calibration(h5, warnings)
    except OSError as exc:
        raise _fail(path, f"is not a readable HDF5 file ({exc})", "Check the file.") from None
    except FlydraH5Error as exc:
        raise _fail(path, str(exc), "Check the file.") from None
    if not cams:
        raise _fail(path, "has no calibration group (calibration/pmat/<cam_id>)",
                    "Give the calibration separately (an XML file), or a flydra .h5 that holds one.")
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
    if fmt != "flydra-xml" and any(c.K_dist is not None for c in cameras.values()):
        raise CalibrationFormatError(
            f"{path}: {fmt} has one K per camera, but these cameras' distortion is about another K than their "
            "projection's (flydra's model); write flydra XML (.xml), which keeps it exactly, or convert with "
            "`flytrack calibrate convert`, which approximates it and measures how well.")
    writers[fmt](cameras, path)


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------
def _matrix(values: object, shape: tuple[int, int], path: Path | str, where: str) -> np.ndarray:
    try:
        a = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise _fail(path, f"{where} is not a numeric matrix", f"It must be {shape[0]}x{shape[1]} numbers.") from None
    if a.size != shape[0] * shape[1]:
        raise _fail(path, f"{where} has {a.size} numbers, expected {shape[0]}x{shape[1]}",
                    "Fix or regenerate the file.")
    a = a.reshape(shape)
    if not np.all(np.isfinite(a)):
        raise _fail(path, f"{where} contains NaN or infinity", "Re-run the calibration that produced it.")
    return a


def _resolution(w: object, h: object, path: Path | str, where: str) -> tuple[int, int]:
    try:
        wi, hi = int(float(w)), int(float(h))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise _fail(path, f"{where}: resolution is not two integers", "Write it as 'width height'.") from None
    if wi <= 0 or hi <= 0:
        raise _fail(path, f"{where}: resolution {wi}x{hi} is not positive", "Write the image width and height.")
    return wi, hi


def _make_camera(path: Path | str, **kw: object) -> Camera:
    try:
        return Camera(**kw)  # type: ignore[arg-type]
    except ValueError as exc:
        raise _fail(path, str(exc), "Fix or regenerate the file.") from None


def _check_unique(names: list[str], path: Path | str) -> None:
    seen: set[str] = set()
    for n in names:
        if n in seen:
            raise _fail(path, f"camera {n!r} appears twice", "Each camera name must be unique.")
        seen.add(n)


def _fmt(x: float) -> str:
    return repr(float(x))


def _rodrigues_to_matrix(rvec: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(rvec))
    if theta < 1e-300:
        return np.eye(3)
    k = rvec / theta
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * Kx + (1 - math.cos(theta)) * (Kx @ Kx)


def _matrix_to_rodrigues(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


# ---------------------------------------------------------------------------------------------
# flydra XML
# ---------------------------------------------------------------------------------------------
def _xml_float(elem: ET.Element, tag: str, path: Path | str, cam: str, default: float | None = None) -> float:
    child = elem.find(tag)
    if child is None or child.text is None or not child.text.strip():
        if default is not None:
            return default
        raise _fail(path, f"camera {cam!r}: <non_linear_parameters> lacks <{tag}>",
                    "flydra needs fc1 fc2 cc1 cc2 k1 k2 p1 p2 (alpha_c optional).")
    try:
        v = float(child.text)
    except ValueError:
        raise _fail(path, f"camera {cam!r}: <{tag}> is {child.text.strip()!r}, not a number", "Fix the file.") from None
    if not math.isfinite(v):
        raise _fail(path, f"camera {cam!r}: <{tag}> is not finite", "Fix the file.")
    return v


def _flydra_project(P: np.ndarray, Kh: np.ndarray, Kp: np.ndarray, dist: np.ndarray, X: np.ndarray) -> np.ndarray:
    """flydra's own projection: undistorted pixel P X, normalised by Kp, distorted, then Kh (Bouguet)."""
    x = np.hstack([X, np.ones((len(X), 1))]) @ P.T
    x = x[:, :2] / x[:, 2:3]
    yn = (x[:, 1] - Kp[1, 2]) / Kp[1, 1]
    xn = (x[:, 0] - Kp[0, 2] - Kp[0, 1] * yn) / Kp[0, 0]
    xd, yd = distort_normalized(xn, yn, dist)
    return np.stack([Kh[0, 0] * xd + Kh[0, 1] * yd + Kh[0, 2], Kh[1, 1] * yd + Kh[1, 2]], axis=1)


def _flydra_camera(elem: ET.Element, path: Path | str, warnings: list[str], fidelity: dict[str, float]) -> Camera:
    cam_el = elem.find("cam_id")
    if cam_el is None or not (cam_el.text or "").strip():
        raise _fail(path, "a <single_camera_calibration> has no <cam_id>", "Give every camera a cam_id.")
    name = (cam_el.text or "").strip()
    pm_el = elem.find("calibration_matrix")
    if pm_el is None or not (pm_el.text or "").strip():
        raise _fail(path, f"camera {name!r} has no <calibration_matrix>", "It must hold the 3x4 matrix P.")
    try:
        rows = [[float(v) for v in row.replace(",", " ").split()] for row in (pm_el.text or "").strip().split(";")]
    except ValueError:
        raise _fail(path, f"camera {name!r}: <calibration_matrix> is not numeric",
                    "Write P as 3 rows of 4 numbers separated by ';'.") from None
    rows = [r for r in rows if r]
    if len(rows) != 3 or any(len(r) != 4 for r in rows):
        raise _fail(path, f"camera {name!r}: <calibration_matrix> is not 3x4",
                    "Write P as 3 rows of 4 numbers separated by ';'.")
    P = _matrix(rows, (3, 4), path, f"camera {name!r} calibration_matrix")
    res_el = elem.find("resolution")
    if res_el is None or not (res_el.text or "").split():
        raise _fail(path, f"camera {name!r} has no <resolution>", "Add <resolution>width height</resolution>.")
    parts = (res_el.text or "").split()
    if len(parts) != 2:
        raise _fail(path, f"camera {name!r}: <resolution> must be 'width height'", "Fix the file.")
    w, h = _resolution(parts[0], parts[1], path, f"camera {name!r}")
    sf_el = elem.find("scale_factor")
    if sf_el is not None and (sf_el.text or "").strip():
        try:
            sf = float(sf_el.text or "")
        except ValueError:
            raise _fail(path, f"camera {name!r}: <scale_factor> is not a number", "Fix the file.") from None
        P = P.copy()
        P[:, 3] *= sf  # flydra's convention: world units become (old units x scale_factor)
    try:
        base = Camera.from_P(name, P, w, h)
    except ValueError as exc:
        raise _fail(path, str(exc), "The calibration matrix must be a valid camera (rank 3).") from None
    nl = elem.find("non_linear_parameters")
    if nl is None:
        return base
    fc1 = _xml_float(nl, "fc1", path, name)
    fc2 = _xml_float(nl, "fc2", path, name)
    cc1 = _xml_float(nl, "cc1", path, name)
    cc2 = _xml_float(nl, "cc2", path, name)
    k1 = _xml_float(nl, "k1", path, name)
    k2 = _xml_float(nl, "k2", path, name)
    p1 = _xml_float(nl, "p1", path, name)
    p2 = _xml_float(nl, "p2", path, name)
    k3 = _xml_float(nl, "k3", path, name, default=0.0)
    alpha = _xml_float(nl, "alpha_c", path, name, default=0.0)
    fc1p = _xml_float(nl, "fc1p", path, name, default=fc1)
    fc2p = _xml_float(nl, "fc2p", path, name, default=fc2)
    cc1p = _xml_float(nl, "cc1p", path, name, default=cc1)
    cc2p = _xml_float(nl, "cc2p", path, name, default=cc2)
    dist = np.array([k1, k2, p1, p2, k3])
    # flydra's helper: undistort normalises distorted pixels by Kh (fc, cc, alpha_c), removes the lens
    # distortion, and maps back with Kp (fc1p.., same skew); distort is its inverse. P gives the ideal
    # pixels. When Kh == Kp ("simple", what flydra writes) that is exactly Camera(K from P, K_dist=Kh).
    Kh = np.array([[fc1, alpha * fc1, cc1], [0.0, fc2, cc2], [0.0, 0.0, 1.0]])
    Kp = np.array([[fc1p, alpha * fc1p, cc1p], [0.0, fc2p, cc2p], [0.0, 0.0, 1.0]])
    simple = (fc1, fc2, cc1, cc2) == (fc1p, fc2p, cc1p, cc2p)
    if not np.any(dist != 0.0):
        if not simple:
            warnings.append(f"camera {name!r}: zero distortion but rectified intrinsics differ; used P only")
        return base  # the distortion is the identity: P alone
    cam = Camera(name=name, width=w, height=h, K=base.K, R=base.R, t=base.t, dist=dist, K_dist=Kh)
    if not simple:
        # Distortion about Kp on the way in and Kh on the way out: one K_dist cannot hold both. Measure
        # how far the model is from flydra's over the image and say so.
        gu, gv = np.meshgrid(np.linspace(0, w - 1, 9), np.linspace(0, h - 1, 9))
        uv = np.stack([gu.ravel(), gv.ravel()], axis=1)
        centre, rays = cam.rays(uv)
        err = float(np.nanmax(np.linalg.norm(_flydra_project(P, Kh, Kp, dist, centre + rays) - uv, axis=1)))
        fidelity[name] = err
        if err > _FLYDRA_APPROX_WARN_PX:
            warnings.append(
                f"camera {name!r}: its rectified intrinsics (fc1p.., cc1p..) differ from fc1.., cc1..; FlyTrack's "
                f"model reproduces flydra's projection to within {err:.3g} px. Re-run the calibration "
                "(flytrack calibrate selfcal) for an exact model.")
    return cam


def flydra_projection(P: np.ndarray, cam_xml_nl: dict[str, float], X: np.ndarray) -> np.ndarray:
    """flydra's distorted projection of world points X (N, 3) for a 3x4 P and the XML's non-linear
    parameters (fc1 fc2 cc1 cc2 k1 k2 p1 p2 [alpha_c k3 fc1p fc2p cc1p cc2p]); the reference tests and
    conversions check FlyTrack's cameras against."""
    g = cam_xml_nl.get
    a = g("alpha_c", 0.0)
    Kh = np.array([[g("fc1"), a * g("fc1"), g("cc1")], [0.0, g("fc2"), g("cc2")], [0.0, 0.0, 1.0]])
    fc1p, fc2p = g("fc1p", g("fc1")), g("fc2p", g("fc2"))
    Kp = np.array([[fc1p, a * fc1p, g("cc1p", g("cc1"))], [0.0, fc2p, g("cc2p", g("cc2"))], [0.0, 0.0, 1.0]])
    dist = np.array([g("k1"), g("k2"), g("p1"), g("p2"), g("k3", 0.0)])
    return _flydra_project(P, Kh, Kp, dist, X)


def load_flydra_xml(
    path: str | Path, warnings: list[str] | None = None, fidelity: dict[str, float] | None = None
) -> dict[str, Camera]:
    warns = warnings if warnings is not None else []
    fid = fidelity if fidelity is not None else {}
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise _fail(path, f"is not well-formed XML ({exc})", "Fix the file or regenerate it.") from None
    except OSError as exc:
        raise _fail(path, f"cannot be read ({exc.strerror})", "Check the path.") from None
    mcr = root if root.tag == "multi_camera_reconstructor" else root.find(".//multi_camera_reconstructor")
    if mcr is None:
        raise _fail(path, "has no <multi_camera_reconstructor> element", "This is not a flydra calibration file.")
    cams = [_flydra_camera(e, path, warns, fid) for e in mcr.findall("single_camera_calibration")]
    if not cams:
        raise _fail(path, "has no <single_camera_calibration> element", "Give at least one camera.")
    _check_unique([c.name for c in cams], path)
    water = _flydra_water(mcr, path)
    if water is not None:
        cams = [dataclasses.replace(c, interface=water) for c in cams]
    return {c.name: c for c in cams}


def _flydra_water(mcr: ET.Element, path: Path | str) -> FlatInterface | None:
    el = mcr.find("water")
    if el is None:
        return None
    text = (el.text or "").strip()
    try:
        n = float(text)
    except ValueError:
        raise _fail(path, f"<water> is {text!r}, not a refractive index", "Write e.g. <water>1.333</water>.") from None
    if not (math.isfinite(n) and n >= 1.0):
        raise _fail(path, f"<water> is {n!r}; a refractive index is finite and >= 1", "Fix the file.")
    return FlatInterface.water_surface(n)


def _common_water(cameras: Mapping[str, Camera], path: Path | str) -> FlatInterface | None:
    """The one water surface all cameras share (what <water> can hold), or None; anything else is an error."""
    ifcs = {c.interface for c in cameras.values()}
    if ifcs == {None}:
        return None
    (ifc,) = ifcs if len(ifcs) == 1 else (None,)
    if ifc is None or not ifc.is_braid_water:
        raise CalibrationFormatError(
            f"{path}: flydra XML can only hold one water surface at z = 0 shared by every camera (<water>); "
            "these cameras have other refractive interfaces, which no format FlyTrack writes can hold.")
    return ifc


def save_flydra_xml(cameras: Mapping[str, Camera], path: str | Path, minimum_eccentricity: float = 1.4) -> None:
    """Write flydra's `multi_camera_reconstructor` XML (world units: metres, scale_factor absent)."""
    water = _common_water(cameras, path)
    root = ET.Element("multi_camera_reconstructor")
    for name, cam in cameras.items():
        sc = ET.SubElement(root, "single_camera_calibration")
        ET.SubElement(sc, "cam_id").text = name
        P = cam.P
        ET.SubElement(sc, "calibration_matrix").text = "; ".join(" ".join(_fmt(v) for v in row) for row in P)
        ET.SubElement(sc, "resolution").text = f"{int(cam.width)} {int(cam.height)}"
        nl = ET.SubElement(sc, "non_linear_parameters")
        K = cam.Kd  # the distortion's K (flydra's fc, cc, alpha_c); P holds the pinhole's
        k1, k2, p1, p2, k3 = cam.dist
        vals = {
            "fc1": K[0, 0], "fc2": K[1, 1], "cc1": K[0, 2], "cc2": K[1, 2],
            "k1": k1, "k2": k2, "p1": p1, "p2": p2, "alpha_c": K[0, 1] / K[0, 0],
            "fc1p": K[0, 0], "fc2p": K[1, 1], "cc1p": K[0, 2], "cc2p": K[1, 2],
        }
        if k3 != 0.0:
            vals["k3"] = k3  # flydra itself writes no k3; readers that know it (FlyTrack, Braid) use it
        for tag, v in vals.items():
            ET.SubElement(nl, tag).text = _fmt(v)
    ET.SubElement(root, "minimum_eccentricity").text = _fmt(minimum_eccentricity)
    if water is not None:
        ET.SubElement(root, "water").text = _fmt(water.n_far)
    ET.indent(root)
    Path(path).write_text(ET.tostring(root, encoding="unicode") + "\n")


# ---------------------------------------------------------------------------------------------
# pymvg JSON
# ---------------------------------------------------------------------------------------------
def load_pymvg_json(path: str | Path, warnings: list[str] | None = None) -> dict[str, Camera]:
    warns = warnings if warnings is not None else []
    try:
        doc = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise _fail(path, f"is not valid JSON ({exc.msg} at line {exc.lineno})", "Fix the file.") from None
    system = doc.get("camera_system") if isinstance(doc, dict) else None
    if not isinstance(system, list):
        raise _fail(path, "has no 'camera_system' list", "This is not a pymvg camera-system file.")
    cams: list[Camera] = []
    for i, d in enumerate(system):
        if not isinstance(d, dict):
            raise _fail(path, f"camera_system[{i}] is not an object", "Fix the file.")
        name = str(d.get("name", f"cam{i}"))
        missing = [k for k in ("width", "height", "K") if k not in d]
        rot_key = "rotation" if "rotation" in d else ("Q" if "Q" in d else None)
        if rot_key is None:
            missing.append("rotation")
        if "translation" not in d:
            missing.append("translation")
        if missing:
            raise _fail(path, f"camera {name!r} lacks {', '.join(missing)}", "pymvg cameras need all of them.")
        w, h = _resolution(d["width"], d["height"], path, f"camera {name!r}")
        K = _matrix(d["K"], (3, 3), path, f"camera {name!r} K")
        R = _matrix(d[rot_key], (3, 3), path, f"camera {name!r} rotation")
        t = _matrix(d["translation"], (1, 3), path, f"camera {name!r} translation").ravel()
        D = np.asarray(d.get("D", [0, 0, 0, 0, 0]), dtype=np.float64).ravel()
        if D.size > 5:
            raise _fail(path, f"camera {name!r}: D has {D.size} coefficients", "FlyTrack handles k1 k2 p1 p2 k3.")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise _fail(path, f"camera {name!r}: rotation is not a proper rotation matrix", "Fix the file.")
        rect = d.get("R")
        if rect is not None and not np.allclose(np.asarray(rect, dtype=float), np.eye(3), atol=1e-12):
            warns.append(f"camera {name!r}: non-identity rectification R ignored (only K, D, rotation, "
                         "translation define the distorted projection)")
        cams.append(_make_camera(path, name=name, width=w, height=h, K=K, R=R, t=t, dist=D))
    _check_unique([c.name for c in cams], path)
    return {c.name: c for c in cams}


def save_pymvg_json(cameras: Mapping[str, Camera], path: str | Path) -> None:
    system = []
    for name, cam in cameras.items():
        P = np.zeros((3, 4))
        P[:, :3] = cam.K
        system.append({
            "name": name,
            "width": int(cam.width),
            "height": int(cam.height),
            "P": P.tolist(),
            "K": cam.K.tolist(),
            "D": [float(v) for v in cam.dist],
            "R": np.eye(3).tolist(),
            "rotation": cam.R.tolist(),
            "translation": [float(v) for v in cam.t],
        })
    doc = {"__pymvg_file_version__": "1.0", "camera_system": system}
    Path(path).write_text(json.dumps(doc, indent=2) + "\n")


# ---------------------------------------------------------------------------------------------
# OpenCV YAML (cv2.FileStorage)
# ---------------------------------------------------------------------------------------------
_K_KEYS = ("camera_matrix", "cameraMatrix", "K", "intrinsic_matrix", "M")
_D_KEYS = ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D", "dist")
_R_KEYS = ("R", "rotation_matrix")
_RVEC_KEYS = ("rvec", "rvecs", "rotation")
_T_KEYS = ("T", "t", "tvec", "tvecs", "translation")
_W_KEYS = ("image_width", "width", "imageWidth")
_H_KEYS = ("image_height", "height", "imageHeight")


def _fs_get(node: object, keys: tuple[str, ...]) -> object | None:
    for k in keys:
        n = node.getNode(k)  # type: ignore[attr-defined]
        if not n.empty():
            return n
    return None


def _fs_value(n: object) -> np.ndarray | float | None:
    if n is None:
        return None
    if n.isSeq():  # type: ignore[attr-defined]
        return np.asarray([_fs_value(n.at(i)) for i in range(n.size())], dtype=float)  # type: ignore[attr-defined]
    if n.isReal() or n.isInt():  # type: ignore[attr-defined]
        return float(n.real())  # type: ignore[attr-defined]
    m = n.mat()  # type: ignore[attr-defined]
    return None if m is None else np.asarray(m, dtype=float)


def _yaml_camera(node: object, name: str, path: Path | str) -> Camera:
    K = _fs_value(_fs_get(node, _K_KEYS))
    if K is None:
        raise _fail(path, f"camera {name!r} has no camera matrix ({'/'.join(_K_KEYS)})", "Add the 3x3 matrix.")
    K = _matrix(K, (3, 3), path, f"camera {name!r} camera matrix")
    D = _fs_value(_fs_get(node, _D_KEYS))
    D = np.zeros(5) if D is None else np.asarray(D, dtype=float).ravel()
    if D.size > 5:
        if np.any(D[5:] != 0):
            raise _fail(path, f"camera {name!r} uses {D.size} distortion coefficients",
                        "FlyTrack's model has k1 k2 p1 p2 k3: recalibrate without the rational/thin-prism terms.")
        D = D[:5]
    Rn = _fs_value(_fs_get(node, _R_KEYS))
    rv = _fs_value(_fs_get(node, _RVEC_KEYS))
    if Rn is not None and np.asarray(Rn).size == 9:
        R = _matrix(Rn, (3, 3), path, f"camera {name!r} R")
    elif rv is not None or (Rn is not None and np.asarray(Rn).size == 3):
        vec = np.asarray(rv if rv is not None else Rn, dtype=float).ravel()
        if vec.size != 3:
            raise _fail(path, f"camera {name!r}: rotation vector must have 3 numbers", "Fix the file.")
        R = _rodrigues_to_matrix(vec)
    else:
        R = np.eye(3)
    T = _fs_value(_fs_get(node, _T_KEYS))
    t = np.zeros(3) if T is None else _matrix(T, (1, 3), path, f"camera {name!r} translation").ravel()
    wn, hn = _fs_value(_fs_get(node, _W_KEYS)), _fs_value(_fs_get(node, _H_KEYS))
    if wn is None or hn is None:
        size = _fs_value(_fs_get(node, ("image_size", "imageSize", "size")))
        if size is None or np.asarray(size).size != 2:
            raise _fail(path, f"camera {name!r} has no image size",
                        "Add image_width and image_height (or image_size: [w, h]).")
        wn, hn = np.asarray(size).ravel()
    w, h = _resolution(wn, hn, path, f"camera {name!r}")
    return _make_camera(path, name=name, width=w, height=h, K=K, R=R, t=t, dist=D)


def load_opencv_yaml(path: str | Path) -> dict[str, Camera]:
    """One camera at the top level (named after the file), or one map per camera at the top level."""
    import cv2

    p = Path(path)
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_FORMAT_YAML)
    except cv2.error as exc:
        msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else "parse error"
        raise _fail(p, f"is not a valid OpenCV YAML file ({msg})", "Fix the file or regenerate it.") from None
    try:
        if not fs.isOpened():
            raise _fail(p, "cannot be opened as OpenCV YAML", "Check the path and the '%YAML:1.0' header.")
        root = fs.root()
        if _fs_get(root, _K_KEYS) is not None:
            return {p.stem: _yaml_camera(root, p.stem, p)}
        cams: dict[str, Camera] = {}
        for key in root.keys():
            node = root.getNode(key)
            if node.isMap() and _fs_get(node, _K_KEYS) is not None:
                cams[key] = _yaml_camera(node, key, p)
        if not cams:
            raise _fail(p, "holds no camera (no camera_matrix at the top level or in any top-level map)",
                        "Write camera_matrix, distortion_coefficients, image_width, image_height per camera.")
        return cams
    finally:
        fs.release()


# ---------------------------------------------------------------------------------------------
# anipose TOML
# ---------------------------------------------------------------------------------------------
def load_anipose_toml(path: str | Path) -> dict[str, Camera]:
    try:
        doc = tomllib.loads(Path(path).read_text())
    except tomllib.TOMLDecodeError as exc:
        raise _fail(path, f"is not valid TOML ({exc})", "Fix the file.") from None
    cams: list[Camera] = []
    for key, d in doc.items():
        if key == "metadata" or not isinstance(d, dict):
            continue
        name = str(d.get("name", key))
        missing = [k for k in ("size", "matrix", "rotation", "translation") if k not in d]
        if missing:
            raise _fail(path, f"[{key}] lacks {', '.join(missing)}", "anipose cameras need size, matrix, "
                        "distortions, rotation (Rodrigues vector) and translation.")
        size = np.asarray(d["size"]).ravel()
        if size.size != 2:
            raise _fail(path, f"[{key}] size must be [width, height]", "Fix the file.")
        w, h = _resolution(size[0], size[1], path, f"camera {name!r}")
        K = _matrix(d["matrix"], (3, 3), path, f"camera {name!r} matrix")
        D = np.asarray(d.get("distortions", [0, 0, 0, 0, 0]), dtype=float).ravel()
        if D.size > 5:
            raise _fail(path, f"camera {name!r}: {D.size} distortions", "FlyTrack handles k1 k2 p1 p2 k3.")
        rvec = _matrix(d["rotation"], (1, 3), path, f"camera {name!r} rotation").ravel()
        t = _matrix(d["translation"], (1, 3), path, f"camera {name!r} translation").ravel()
        cams.append(_make_camera(path, name=name, width=w, height=h, K=K, R=_rodrigues_to_matrix(rvec), t=t,
                                 dist=D))
    if not cams:
        raise _fail(path, "holds no [cam_*] table", "This is not an anipose calibration file.")
    _check_unique([c.name for c in cams], path)
    return {c.name: c for c in cams}


def save_anipose_toml(cameras: Mapping[str, Camera], path: str | Path) -> None:
    def arr(a: np.ndarray) -> str:
        if a.ndim == 1:
            return "[ " + ", ".join(_fmt(v) for v in a) + ",]"
        return "[ " + ", ".join(arr(r) for r in a) + ",]"

    lines: list[str] = []
    for i, (name, cam) in enumerate(cameras.items()):
        lines += [f"[cam_{i}]", f"name = {json.dumps(name)}", f"size = [ {int(cam.width)}, {int(cam.height)},]",
                  f"matrix = {arr(cam.K)}", f"distortions = {arr(cam.dist)}",
                  f"rotation = {arr(_matrix_to_rodrigues(cam.R))}", f"translation = {arr(cam.t)}", ""]
    lines += ["[metadata]", 'adjusted = true', 'error = 0.0', ""]
    Path(path).write_text("\n".join(lines))


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
