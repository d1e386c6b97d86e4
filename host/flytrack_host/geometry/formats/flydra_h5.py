"""The `calibration` group of a flydra `.h5` file, read as flydra's Reconstructor reads it.

A calibration format like the others here; `io.flydra_h5` reads the rest of such a file (2D data,
tracks, clock samples) and takes the cameras from this module.
"""

from __future__ import annotations

import h5py
import numpy as np

from flytrack_host.geometry.camera import Camera, face_the_scene, mirrored_world_note
from flytrack_host.geometry.refraction import FlatInterface


class FlydraH5Error(Exception):
    """A flydra .h5 file that cannot be read; the message says which part and why."""


def read_flydra_calibration(h5: h5py.File, warnings: list[str] | None = None) -> dict[str, Camera]:
    """cam_id -> Camera from a flydra .h5's `calibration` group ({} when it has none)."""
    warns = warnings if warnings is not None else []
    if "calibration" not in h5 or "pmat" not in h5["calibration"]:
        return {}
    g = h5["calibration"]
    water = None
    if "refractive_interfaces" in g:
        ri = g["refractive_interfaces"][...]
        if len(ri) > 1:
            raise FlydraH5Error(f"calibration/refractive_interfaces has {len(ri)} rows; FlyTrack reads one water "
                                "surface")
        if len(ri) == 1:
            r = ri[0]
            nrm = (float(r["plane_normal_x"]), float(r["plane_normal_y"]), float(r["plane_normal_z"]))
            if nrm != (0.0, 0.0, 1.0) or float(r["plane_dist_from_origin"]) != 0.0:
                raise FlydraH5Error("calibration/refractive_interfaces: only the plane z = 0 (normal +z) is "
                                    "flydra's water surface")
            water = FlatInterface((0.0, 0.0, 0.0), nrm, n_far=float(r["n2"]), n_near=float(r["n1"]))
    cams = {}
    for cam_id, ds in g["pmat"].items():
        P = np.asarray(ds[...], dtype=np.float64)
        if P.shape != (3, 4) or not np.all(np.isfinite(P)):
            raise FlydraH5Error(f"calibration/pmat/{cam_id} is not a finite 3x4 matrix")
        if "scale_factor2meters" in g and cam_id in g["scale_factor2meters"]:
            sf = float(np.asarray(g["scale_factor2meters"][cam_id][...]).ravel()[0])
            if not (np.isfinite(sf) and sf > 0):
                raise FlydraH5Error(f"calibration/scale_factor2meters/{cam_id} is {sf!r}, not a positive number")
            P = P.copy()
            P[:, 3] *= sf  # flydra: X_m = sf X_units, so P X_units = [M | sf p4] X_m
        if "resolution" in g and cam_id in g["resolution"]:
            w, h = (int(v) for v in np.asarray(g["resolution"][cam_id][...]).ravel()[:2])
        else:
            w, h = 640, 480
            warns.append(f"camera {cam_id!r}: no calibration/resolution; assumed 640x480")
        dist = np.zeros(5)
        if "intrinsic_nonlinear" in g and cam_id in g["intrinsic_nonlinear"]:
            nl = np.asarray(g["intrinsic_nonlinear"][cam_id][...], dtype=np.float64).ravel()
            dist[: min(5, nl.size)] = nl[:5]
        K_dist = None
        if "intrinsic_linear" in g and cam_id in g["intrinsic_linear"]:
            K = np.asarray(g["intrinsic_linear"][cam_id][...], dtype=np.float64).reshape(3, 3)
            # flydra's helper is built from fc = K[0,0], K[1,1] and cc = K[0,2], K[1,2] only.
            K_dist = np.array([[K[0, 0], 0.0, K[0, 2]], [0.0, K[1, 1], K[1, 2]], [0.0, 0.0, 1.0]])
        elif np.any(dist != 0):
            warns.append(f"camera {cam_id!r}: no calibration/intrinsic_linear; the distortion is taken about "
                         "P's own K")
        try:
            cams[cam_id] = Camera.from_P(cam_id, P, w, h, dist, interface=water,
                                         K_dist=K_dist if np.any(dist != 0) else None)
        except ValueError as exc:
            raise FlydraH5Error(str(exc)) from None
    turned_cams, turned = face_the_scene(list(cams.values()))
    if turned:
        warns.append(mirrored_world_note(turned))
        cams = {c.name: c for c in turned_cams}
    return cams
