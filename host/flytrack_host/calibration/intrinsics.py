"""Intrinsics (K and distortion) of one camera from images of a checkerboard, through OpenCV.

An optional starting point for `selfcal --intrinsics`: the self-calibration refines them anyway.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from flytrack_host.camera import Camera

__all__ = ["IntrinsicsError", "checkerboard_intrinsics"]


class IntrinsicsError(ValueError):
    """Intrinsics cannot be computed; the message says what is wrong and what to do."""


def checkerboard_intrinsics(name: str, images: Sequence[str | Path], inner_corners: tuple[int, int],
                            square_m: float) -> tuple[Camera, float, int]:
    """(camera with K and dist and identity pose, RMS reprojection error in px, images used)."""
    cols, rows = inner_corners
    obj = np.zeros((cols * rows, 3), np.float32)
    obj[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    objpoints, imgpoints = [], []
    size: tuple[int, int] | None = None
    for p in images:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise IntrinsicsError(f"{p}: cannot be read as an image. Give PNG/JPEG/TIFF files.")
        if size is None:
            size = (img.shape[1], img.shape[0])
        elif size != (img.shape[1], img.shape[0]):
            raise IntrinsicsError(f"{p}: size {img.shape[1]}x{img.shape[0]} differs from {size[0]}x{size[1]}: "
                                  "all images must come from the same camera and mode.")
        ok, corners = cv2.findChessboardCorners(img, (cols, rows))
        if not ok:
            continue
        corners = cv2.cornerSubPix(img, corners, (5, 5), (-1, -1),
                                   (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3))
        objpoints.append(obj)
        imgpoints.append(corners)
    if size is None:
        raise IntrinsicsError("no images given.")
    if len(objpoints) < 3:
        raise IntrinsicsError(f"the {cols}x{rows} inner-corner board was found in only {len(objpoints)} of "
                              f"{len(images)} images; at least 3 (better 15, tilted and in every corner) are "
                              "needed. Check --corners (inner corners, not squares) and the lighting.")
    rms, K, dist, _, _ = cv2.calibrateCamera(objpoints, imgpoints, size, None, None)
    cam = Camera(name=name, width=size[0], height=size[1], K=K, R=np.eye(3), t=np.zeros(3),
                 dist=np.asarray(dist).ravel()[:5])
    return cam, float(rms), len(objpoints)
