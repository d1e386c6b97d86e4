"""What every calibration reader and writer shares: the error type, checked matrices and sizes, and
Rodrigues vectors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from flytrack_host.geometry.camera import Camera


class CalibrationFormatError(ValueError):
    """A calibration file that cannot be read; the message says what is wrong and what to do."""


def fail(path: Path | str, what: str, fix: str) -> CalibrationFormatError:
    return CalibrationFormatError(f"{path}: {what}. {fix}")


def matrix(values: object, shape: tuple[int, int], path: Path | str, where: str) -> np.ndarray:
    try:
        a = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise fail(path, f"{where} is not a numeric matrix", f"It must be {shape[0]}x{shape[1]} numbers.") from None
    if a.size != shape[0] * shape[1]:
        raise fail(path, f"{where} has {a.size} numbers, expected {shape[0]}x{shape[1]}",
                    "Fix or regenerate the file.")
    a = a.reshape(shape)
    if not np.all(np.isfinite(a)):
        raise fail(path, f"{where} contains NaN or infinity", "Re-run the calibration that produced it.")
    return a


def resolution(w: object, h: object, path: Path | str, where: str) -> tuple[int, int]:
    try:
        wi, hi = int(float(w)), int(float(h))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise fail(path, f"{where}: resolution is not two integers", "Write it as 'width height'.") from None
    if wi <= 0 or hi <= 0:
        raise fail(path, f"{where}: resolution {wi}x{hi} is not positive", "Write the image width and height.")
    return wi, hi


def make_camera(path: Path | str, **kw: object) -> Camera:
    try:
        return Camera(**kw)  # type: ignore[arg-type]
    except ValueError as exc:
        raise fail(path, str(exc), "Fix or regenerate the file.") from None


def check_unique(names: list[str], path: Path | str) -> None:
    seen: set[str] = set()
    for n in names:
        if n in seen:
            raise fail(path, f"camera {n!r} appears twice", "Each camera name must be unique.")
        seen.add(n)


def fmt(x: float) -> str:
    return repr(float(x))


def rodrigues_to_matrix(rvec: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(rvec))
    if theta < 1e-300:
        return np.eye(3)
    k = rvec / theta
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * Kx + (1 - math.cos(theta)) * (Kx @ Kx)


def matrix_to_rodrigues(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()
