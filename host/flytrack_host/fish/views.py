"""The camera seam of the fish tracker: what the shape fit needs from a camera is where a world point lands
in the image (`project`) and which 3D line a pixel sees (`lines`, origin + unit direction).

`CameraView` wraps FlyTrack's camera model (pinhole + OpenCV distortion, `flytrack_host.geometry.camera.Camera`),
including its refraction at a flat interface (`Camera.interface`, `flytrack_host.geometry.refraction`: Braid's
`<water>` surface or a tank wall): `project` then goes through the interface and `lines` are the refracted,
underwater continuations of the camera's rays, which is what the fit's Plucker lines must be.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from flytrack_host.geometry.camera import Camera

F64 = NDArray[np.float64]


@runtime_checkable
class View(Protocol):
    name: str
    width: int
    height: int

    def project(self, Xw: ArrayLike) -> F64: ...

    def lines(self, uv: ArrayLike) -> tuple[F64, F64]: ...


class CameraView:
    """A FlyTrack camera, in air or looking through a refractive interface."""

    def __init__(self, camera: Camera) -> None:
        self.camera = camera
        self.name = camera.name
        self.width = camera.width
        self.height = camera.height

    def project(self, Xw: ArrayLike) -> F64:
        X = np.asarray(Xw, dtype=float)
        shape = X.shape[:-1]
        return self.camera.project(X.reshape(-1, 3)).reshape(*shape, 2)

    def lines(self, uv: ArrayLike) -> tuple[F64, F64]:
        """Distorted pixels (N,2) -> line origins (N,3) and unit directions (N,3) in the world."""
        return self.camera.refracted_rays(np.asarray(uv, dtype=float).reshape(-1, 2))

    @property
    def center(self) -> F64:
        return self.camera.center


AirView = CameraView  # the name used where the cameras are known to be in air


def as_view(cam: object) -> View:
    if isinstance(cam, Camera):
        return CameraView(cam)
    if isinstance(cam, View):
        return cam
    raise TypeError(f"not a camera: {cam!r}")


def views_from_calibration(cams: Mapping[str, object], names: list[str]) -> list[View]:
    """The views named (in order) from a loaded calibration; a missing name is one clear error."""
    missing = [n for n in names if n not in cams]
    if missing:
        raise KeyError(
            f"calibration has no camera {', '.join(missing)} (it has {', '.join(sorted(cams)) or 'none'}); "
            "name the cameras with --cameras in the order of the videos"
        )
    return [as_view(cams[n]) for n in names]


def tank_rig(top_size: tuple[int, int] = (1280, 1024), side_size: tuple[int, int] = (512, 384),
             distortion: float = -0.04, top_zoom: float = 1.0, water: float | None = None) -> dict[str, Camera]:
    """The synthetic rig of seed 004 §5.1 in air: a 0.61 x 0.30 x 0.40 m tank (x, y, z; floor at z = 0),
    a top camera above it, a side camera facing the long wall (tracking) and one facing the short wall
    (validation only), each with a little barrel distortion. `top_zoom` > 1 narrows the top view on the
    tank's centre (small test images at the full demo's pixels per mm). `water` (a refractive index, e.g.
    1.333) fills the tank: the top camera looks through the surface at z = 0.40 m, the side cameras through
    the walls at y = 0 and x = 0 (thin glass neglected), with the shared refraction model."""
    cx, cy = 0.305, 0.15
    top = Camera.look_at("top", (cx, cy, 1.25), (cx, cy, 0.2), *top_size, focal_px=top_zoom * top_size[0] * 1.05 / 0.66,
                         up=(0.0, 1.0, 0.0), dist=(distortion, 0, 0, 0, 0))
    side = Camera.look_at("side", (cx, -0.95, 0.2), (cx, cy, 0.2), *side_size, focal_px=side_size[0] * 1.1 / 0.68,
                          dist=(distortion, 0, 0, 0, 0))
    val = Camera.look_at("end", (-0.75, cy, 0.2), (cx, cy, 0.2), *side_size, focal_px=side_size[0] * 1.05 / 0.40,
                         dist=(distortion, 0, 0, 0, 0))
    cams = {"top": top, "side": side, "end": val}
    if water is not None:
        import dataclasses

        from flytrack_host.geometry.refraction import FlatInterface

        walls = {"top": ((0.0, 0.0, 0.40), (0.0, 0.0, 1.0)), "side": ((0.0, 0.0, 0.0), (0.0, -1.0, 0.0)),
                 "end": ((0.0, 0.0, 0.0), (-1.0, 0.0, 0.0))}
        cams = {k: dataclasses.replace(c, interface=FlatInterface(walls[k][0], walls[k][1], float(water)))
                for k, c in cams.items()}
    return cams


def refracts(view: View) -> bool:
    cam = getattr(view, "camera", None)
    return getattr(cam, "interface", None) is not None


class GridProjection:
    """A view's projection tabulated on a small 3D grid around a fish and interpolated (trilinear), for the
    many projections of one frame's fit through a refracting camera, whose exact projection solves for the
    refraction point of every point. Points off the grid are projected exactly. With the default 9 mm
    spacing the interpolation error is at most 0.003 px over a fish-sized box in the tank rig (tested)."""

    def __init__(self, view: View, centre: F64, half: float = 0.045, n: int = 11) -> None:
        self.view = view
        self.name, self.width, self.height = view.name, view.width, view.height
        ax = np.linspace(-half, half, n)
        G = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), axis=-1).reshape(-1, 3) + np.asarray(centre)
        self.table = view.project(G).reshape(n, n, n, 2)
        self.lo = np.asarray(centre, float) - half
        self.step = 2 * half / (n - 1)
        self.n = n

    def lines(self, uv: ArrayLike) -> tuple[F64, F64]:
        return self.view.lines(uv)

    def project(self, Xw: ArrayLike) -> F64:
        X = np.asarray(Xw, dtype=float)
        shape = X.shape[:-1]
        X = X.reshape(-1, 3)
        q = (X - self.lo) / self.step
        i = np.floor(q).astype(int)
        inside = np.all((i >= 0) & (i < self.n - 1), axis=1) & np.all(np.isfinite(q), axis=1)
        out = np.empty((len(X), 2))
        if np.any(~inside):
            out[~inside] = self.view.project(X[~inside])
        ii, t = i[inside], q[inside] - i[inside]
        acc = np.zeros((len(ii), 2))
        for dx in (0, 1):
            wx = t[:, 0] if dx else 1 - t[:, 0]
            for dy in (0, 1):
                wy = t[:, 1] if dy else 1 - t[:, 1]
                for dz in (0, 1):
                    wz = t[:, 2] if dz else 1 - t[:, 2]
                    acc += (wx * wy * wz)[:, None] * self.table[ii[:, 0] + dx, ii[:, 1] + dy, ii[:, 2] + dz]
        out[inside] = acc
        return out.reshape(*shape, 2)
