"""Single-point observations for self-calibration, and the points file that stores them.

A points file lists, for each frame, where the LED appeared in each camera that saw it:

CSV (text, one observation per line)::

    # flytrack calibration points v1
    # camera cam1 1280 1024        <- one line per camera: name, image width, image height
    # camera cam2 1280 1024
    frame,camera,u,v
    0,cam1,640.25,512.5
    0,cam2,100.0,733.125
    1,cam1,...

`u, v` are distorted pixel coordinates as the extractor reports them (pixel (0, 0) is the centre of the
top-left pixel). A camera that did not see the LED in a frame has no line for it.

NPZ (numpy): arrays `frame` (int64, N), `camera` (int32 index, N), `uv` (float64, N x 2), `camera_names`
(str, C), `sizes` (int, C x 2: width, height).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

__all__ = ["Observations", "PointsFileError", "load_points", "save_points"]

HEADER = "# flytrack calibration points v1"


class PointsFileError(ValueError):
    """A points file that cannot be used; the message says what is wrong and what to do."""


@dataclass
class Observations:
    frame: NDArray[np.int64]  # (N,) frame number of each observation
    cam: NDArray[np.int32]  # (N,) camera index into camera_names
    uv: NDArray[np.float64]  # (N, 2) distorted pixel coordinates
    camera_names: list[str]
    sizes: list[tuple[int, int]]  # (width, height) per camera

    def __post_init__(self) -> None:
        self.frame = np.asarray(self.frame, dtype=np.int64).ravel()
        self.cam = np.asarray(self.cam, dtype=np.int32).ravel()
        self.uv = np.asarray(self.uv, dtype=np.float64).reshape(-1, 2)
        if not (len(self.frame) == len(self.cam) == len(self.uv)):
            raise PointsFileError("frame, camera and uv arrays differ in length")
        if len(self.sizes) != len(self.camera_names):
            raise PointsFileError("one (width, height) is needed per camera")
        if len(self.cam) and (self.cam.min() < 0 or self.cam.max() >= len(self.camera_names)):
            raise PointsFileError("a camera index is outside the camera list")

    @property
    def n_cameras(self) -> int:
        return len(self.camera_names)

    def counts(self) -> NDArray[np.int64]:
        return np.bincount(self.cam, minlength=self.n_cameras).astype(np.int64)

    def subset(self, keep: NDArray[np.bool_]) -> Observations:
        return Observations(self.frame[keep], self.cam[keep], self.uv[keep], list(self.camera_names),
                            list(self.sizes))

    def point_index(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """(unique frames, index of each observation's frame in them)."""
        frames, inv = np.unique(self.frame, return_inverse=True)
        return frames, inv.astype(np.int64)


def save_points(obs: Observations, path: str | Path) -> None:
    p = Path(path)
    if p.suffix.lower() == ".npz":
        np.savez_compressed(p, frame=obs.frame, camera=obs.cam, uv=obs.uv,
                            camera_names=np.asarray(obs.camera_names), sizes=np.asarray(obs.sizes, dtype=np.int64))
        return
    with p.open("w", newline="") as fh:
        fh.write(HEADER + "\n")
        for name, (w, h) in zip(obs.camera_names, obs.sizes, strict=True):
            fh.write(f"# camera {name} {int(w)} {int(h)}\n")
        wr = csv.writer(fh)
        wr.writerow(["frame", "camera", "u", "v"])
        for f, c, (u, v) in zip(obs.frame, obs.cam, obs.uv, strict=True):
            wr.writerow([int(f), obs.camera_names[c], repr(float(u)), repr(float(v))])


def _fail(path: Path, what: str, fix: str) -> PointsFileError:
    return PointsFileError(f"{path}: {what}. {fix}")


def load_points(path: str | Path) -> Observations:
    p = Path(path)
    if not p.exists():
        raise _fail(p, "no such file", "Check the path (record one with `flytrack calibrate collect`).")
    if p.suffix.lower() == ".npz":
        try:
            with np.load(p, allow_pickle=False) as z:
                missing = [k for k in ("frame", "camera", "uv", "camera_names", "sizes") if k not in z]
                if missing:
                    raise _fail(p, f"lacks array(s) {', '.join(missing)}",
                                "A points NPZ needs frame, camera, uv, camera_names, sizes.")
                obs = Observations(z["frame"], z["camera"], z["uv"], [str(s) for s in z["camera_names"]],
                                   [(int(w), int(h)) for w, h in np.asarray(z["sizes"]).reshape(-1, 2)])
        except (OSError, ValueError) as exc:
            if isinstance(exc, PointsFileError):
                raise
            raise _fail(p, f"is not a valid points NPZ ({exc})", "Regenerate it.") from None
    else:
        obs = _load_csv(p)
    if not np.all(np.isfinite(obs.uv)):
        raise _fail(p, "contains NaN or infinite pixel coordinates", "Remove those lines.")
    return obs


def _load_csv(p: Path) -> Observations:
    names: list[str] = []
    sizes: list[tuple[int, int]] = []
    frames: list[int] = []
    cams: list[int] = []
    uvs: list[tuple[float, float]] = []
    index: dict[str, int] = {}
    header_seen = False
    try:
        text = p.read_text()
    except UnicodeDecodeError:
        raise _fail(p, "is not a text CSV file", "Give a points CSV or NPZ file.") from None
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            parts = s[1:].split()
            if parts[:1] == ["camera"]:
                if len(parts) != 4:
                    raise _fail(p, f"line {lineno}: camera line must be '# camera NAME WIDTH HEIGHT'", "Fix it.")
                try:
                    w, h = int(parts[2]), int(parts[3])
                except ValueError:
                    raise _fail(p, f"line {lineno}: width and height must be integers", "Fix it.") from None
                if w <= 0 or h <= 0:
                    raise _fail(p, f"line {lineno}: image size {w}x{h} is not positive", "Fix it.")
                if parts[1] in index:
                    raise _fail(p, f"line {lineno}: camera {parts[1]!r} declared twice", "Declare it once.")
                index[parts[1]] = len(names)
                names.append(parts[1])
                sizes.append((w, h))
            continue
        row = next(csv.reader([s]))
        if not header_seen:
            if [c.strip() for c in row] != ["frame", "camera", "u", "v"]:
                raise _fail(p, f"line {lineno}: expected the header 'frame,camera,u,v'",
                            "See `flytrack calibrate selfcal --help` for the points file format.")
            header_seen = True
            continue
        if len(row) != 4:
            raise _fail(p, f"line {lineno}: expected 4 fields (frame,camera,u,v), got {len(row)}", "Fix the line.")
        cam = row[1].strip()
        if cam not in index:
            raise _fail(p, f"line {lineno}: camera {cam!r} is not declared",
                        f"Add a line '# camera {cam} WIDTH HEIGHT' before the data.")
        try:
            frames.append(int(row[0]))
            uvs.append((float(row[2]), float(row[3])))
        except ValueError:
            raise _fail(p, f"line {lineno}: frame must be an integer and u, v numbers", "Fix the line.") from None
        cams.append(index[cam])
    if not names:
        raise _fail(p, "declares no camera", "Add '# camera NAME WIDTH HEIGHT' lines before the data.")
    return Observations(np.asarray(frames, dtype=np.int64), np.asarray(cams, dtype=np.int32),
                        np.asarray(uvs, dtype=np.float64).reshape(-1, 2), names, sizes)
