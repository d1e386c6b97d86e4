"""OpenCV YAML (cv2.FileStorage): one camera at the top level, or one map per camera, with the key names
OpenCV's samples and the common calibration tools write."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flytrack_host.geometry.camera import Camera

from .common import fail, make_camera, matrix, resolution, rodrigues_to_matrix

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
        raise fail(path, f"camera {name!r} has no camera matrix ({'/'.join(_K_KEYS)})", "Add the 3x3 matrix.")
    K = matrix(K, (3, 3), path, f"camera {name!r} camera matrix")
    D = _fs_value(_fs_get(node, _D_KEYS))
    D = np.zeros(5) if D is None else np.asarray(D, dtype=float).ravel()
    if D.size > 5:
        if np.any(D[5:] != 0):
            raise fail(path, f"camera {name!r} uses {D.size} distortion coefficients",
                        "FlyTrack's model has k1 k2 p1 p2 k3: recalibrate without the rational/thin-prism terms.")
        D = D[:5]
    Rn = _fs_value(_fs_get(node, _R_KEYS))
    rv = _fs_value(_fs_get(node, _RVEC_KEYS))
    if Rn is not None and np.asarray(Rn).size == 9:
        R = matrix(Rn, (3, 3), path, f"camera {name!r} R")
    elif rv is not None or (Rn is not None and np.asarray(Rn).size == 3):
        vec = np.asarray(rv if rv is not None else Rn, dtype=float).ravel()
        if vec.size != 3:
            raise fail(path, f"camera {name!r}: rotation vector must have 3 numbers", "Fix the file.")
        R = rodrigues_to_matrix(vec)
    else:
        R = np.eye(3)
    T = _fs_value(_fs_get(node, _T_KEYS))
    t = np.zeros(3) if T is None else matrix(T, (1, 3), path, f"camera {name!r} translation").ravel()
    wn, hn = _fs_value(_fs_get(node, _W_KEYS)), _fs_value(_fs_get(node, _H_KEYS))
    if wn is None or hn is None:
        size = _fs_value(_fs_get(node, ("image_size", "imageSize", "size")))
        if size is None or np.asarray(size).size != 2:
            raise fail(path, f"camera {name!r} has no image size",
                        "Add image_width and image_height (or image_size: [w, h]).")
        wn, hn = np.asarray(size).ravel()
    w, h = resolution(wn, hn, path, f"camera {name!r}")
    return make_camera(path, name=name, width=w, height=h, K=K, R=R, t=t, dist=D)


def load_opencv_yaml(path: str | Path) -> dict[str, Camera]:
    """One camera at the top level (named after the file), or one map per camera at the top level."""
    import cv2

    p = Path(path)
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_FORMAT_YAML)
    except cv2.error as exc:
        msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else "parse error"
        raise fail(p, f"is not a valid OpenCV YAML file ({msg})", "Fix the file or regenerate it.") from None
    try:
        if not fs.isOpened():
            raise fail(p, "cannot be opened as OpenCV YAML", "Check the path and the '%YAML:1.0' header.")
        root = fs.root()
        if _fs_get(root, _K_KEYS) is not None:
            return {p.stem: _yaml_camera(root, p.stem, p)}
        cams: dict[str, Camera] = {}
        for key in root.keys():
            node = root.getNode(key)
            if node.isMap() and _fs_get(node, _K_KEYS) is not None:
                cams[key] = _yaml_camera(node, key, p)
        if not cams:
            raise fail(p, "holds no camera (no camera_matrix at the top level or in any top-level map)",
                        "Write camera_matrix, distortion_coefficients, image_width, image_height per camera.")
        return cams
    finally:
        fs.release()
