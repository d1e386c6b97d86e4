"""flydra calibrations: the `multi_camera_reconstructor` XML (read and written) and the calibration group
of a flydra .h5 (read).

Per camera a `calibration_matrix` P (3x4, for undistorted pixels, rows separated by ';'), `resolution` (width
height) and optional `non_linear_parameters` (Bouguet's model: fc1 fc2 cc1 cc2 k1 k2 p1 p2 alpha_c, optionally
k3 and the rectified intrinsics fc1p fc2p cc1p cc2p). An optional `<water>n</water>` in the root (Braid) puts
every camera above a water surface at z = 0 of refractive index n (Camera.interface =
refraction.FlatInterface.water_surface(n)); we write it back. A per-camera `scale_factor` multiplies the last
column of P (old files in mm -> m). We write P = K[R|t] with 17 significant digits and fc1p.. equal to fc1..,
so a file we write reads back exactly.
"""

from __future__ import annotations

import dataclasses
import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from flytrack_host.geometry.camera import Camera, distort_normalized, face_the_scene, mirrored_world_note
from flytrack_host.geometry.refraction import FlatInterface

from .common import CalibrationFormatError, check_unique, fail, fmt, matrix, resolution

# Below this many pixels a flydra camera whose distortion and projection intrinsics differ is still
# represented exactly enough by one K; above it the reader says how far off it is.
_FLYDRA_APPROX_WARN_PX = 1e-3


def _xml_float(elem: ET.Element, tag: str, path: Path | str, cam: str, default: float | None = None) -> float:
    child = elem.find(tag)
    if child is None or child.text is None or not child.text.strip():
        if default is not None:
            return default
        raise fail(path, f"camera {cam!r}: <non_linear_parameters> lacks <{tag}>",
                    "flydra needs fc1 fc2 cc1 cc2 k1 k2 p1 p2 (alpha_c optional).")
    try:
        v = float(child.text)
    except ValueError:
        raise fail(path, f"camera {cam!r}: <{tag}> is {child.text.strip()!r}, not a number", "Fix the file.") from None
    if not math.isfinite(v):
        raise fail(path, f"camera {cam!r}: <{tag}> is not finite", "Fix the file.")
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
        raise fail(path, "a <single_camera_calibration> has no <cam_id>", "Give every camera a cam_id.")
    name = (cam_el.text or "").strip()
    pm_el = elem.find("calibration_matrix")
    if pm_el is None or not (pm_el.text or "").strip():
        raise fail(path, f"camera {name!r} has no <calibration_matrix>", "It must hold the 3x4 matrix P.")
    try:
        rows = [[float(v) for v in row.replace(",", " ").split()] for row in (pm_el.text or "").strip().split(";")]
    except ValueError:
        raise fail(path, f"camera {name!r}: <calibration_matrix> is not numeric",
                    "Write P as 3 rows of 4 numbers separated by ';'.") from None
    rows = [r for r in rows if r]
    if len(rows) != 3 or any(len(r) != 4 for r in rows):
        raise fail(path, f"camera {name!r}: <calibration_matrix> is not 3x4",
                    "Write P as 3 rows of 4 numbers separated by ';'.")
    P = matrix(rows, (3, 4), path, f"camera {name!r} calibration_matrix")
    res_el = elem.find("resolution")
    if res_el is None or not (res_el.text or "").split():
        raise fail(path, f"camera {name!r} has no <resolution>", "Add <resolution>width height</resolution>.")
    parts = (res_el.text or "").split()
    if len(parts) != 2:
        raise fail(path, f"camera {name!r}: <resolution> must be 'width height'", "Fix the file.")
    w, h = resolution(parts[0], parts[1], path, f"camera {name!r}")
    sf_el = elem.find("scale_factor")
    if sf_el is not None and (sf_el.text or "").strip():
        try:
            sf = float(sf_el.text or "")
        except ValueError:
            raise fail(path, f"camera {name!r}: <scale_factor> is not a number", "Fix the file.") from None
        P = P.copy()
        P[:, 3] *= sf  # flydra's convention: world units become (old units x scale_factor)
    try:
        base = Camera.from_P(name, P, w, h)
    except ValueError as exc:
        raise fail(path, str(exc), "The calibration matrix must be a valid camera (rank 3).") from None
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
        raise fail(path, f"is not well-formed XML ({exc})", "Fix the file or regenerate it.") from None
    except OSError as exc:
        raise fail(path, f"cannot be read ({exc.strerror})", "Check the path.") from None
    mcr = root if root.tag == "multi_camera_reconstructor" else root.find(".//multi_camera_reconstructor")
    if mcr is None:
        raise fail(path, "has no <multi_camera_reconstructor> element", "This is not a flydra calibration file.")
    cams = [_flydra_camera(e, path, warns, fid) for e in mcr.findall("single_camera_calibration")]
    if not cams:
        raise fail(path, "has no <single_camera_calibration> element", "Give at least one camera.")
    check_unique([c.name for c in cams], path)
    cams, turned = face_the_scene(cams)
    if turned:
        warns.append(mirrored_world_note(turned))
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
        raise fail(path, f"<water> is {text!r}, not a refractive index", "Write e.g. <water>1.333</water>.") from None
    if not (math.isfinite(n) and n >= 1.0):
        raise fail(path, f"<water> is {n!r}; a refractive index is finite and >= 1", "Fix the file.")
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
        ET.SubElement(sc, "calibration_matrix").text = "; ".join(" ".join(fmt(v) for v in row) for row in P)
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
            ET.SubElement(nl, tag).text = fmt(v)
    ET.SubElement(root, "minimum_eccentricity").text = fmt(minimum_eccentricity)
    if water is not None:
        ET.SubElement(root, "water").text = fmt(water.n_far)
    ET.indent(root)
    Path(path).write_text(ET.tostring(root, encoding="unicode") + "\n")


def load_flydra_h5_calibration(path: str | Path, warnings: list[str] | None = None) -> dict[str, Camera]:
    """The `calibration` group of a flydra .h5 (flydra_h5.read_flydra_calibration)."""
    import h5py

    from .flydra_h5 import FlydraH5Error, read_flydra_calibration

    try:
        with h5py.File(path, "r") as h5:
            cams = read_flydra_calibration(h5, warnings)
    except OSError as exc:
        raise fail(path, f"is not a readable HDF5 file ({exc})", "Check the file.") from None
    except FlydraH5Error as exc:
        raise fail(path, str(exc), "Check the file.") from None
    if not cams:
        raise fail(path, "has no calibration group (calibration/pmat/<cam_id>)",
                    "Give the calibration separately (an XML file), or a flydra .h5 that holds one.")
    return cams
