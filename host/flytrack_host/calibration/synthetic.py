"""Synthetic calibration data: cameras around an arena and an LED waved through it.

Used by the tests and the benchmark to check the self-calibration against a known truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from flytrack_host.calibration.observations import Observations
from flytrack_host.geometry.camera import Camera

__all__ = ["SyntheticRig", "make_rig", "led_path", "observe"]


@dataclass
class SyntheticRig:
    cameras: dict[str, Camera]
    arena_size: float  # edge of the cubic arena, metres
    points: NDArray[np.float64]  # (F, 3) true LED positions, one per frame
    obs: Observations
    outlier: NDArray[np.bool_]  # (N,) which observations are gross outliers
    noise_px: float


def make_rig(n_cameras: int, arena: float = 1.0, seed: int = 0, width: int = 1280, height: int = 1024,
             dist_k1: float = -0.12, dist_k2: float = 0.03, principal_offset_px: float = 15.0) -> dict[str, Camera]:
    """Cameras on a ring around (and above or below) a cubic arena, all looking at its centre; principal
    points up to principal_offset_px off the image centre (0: centred)."""
    rng = np.random.default_rng(seed)
    cams: dict[str, Camera] = {}
    centre = np.array([0.0, 0.0, arena / 2])
    for i in range(n_cameras):
        ang = 2 * np.pi * i / n_cameras + rng.uniform(-0.15, 0.15)
        r = arena * rng.uniform(1.2, 1.45)
        z = arena * (0.5 + rng.uniform(0.3, 0.9) * (1 if i % 2 == 0 else -0.7))
        pos = np.array([r * np.cos(ang), r * np.sin(ang), z])
        dist_to_c = np.linalg.norm(pos - centre)
        # Focal length so that the arena fills about 80 % of the smaller image side.
        f = 0.8 * min(width, height) * dist_to_c / (arena * 1.5) * rng.uniform(0.95, 1.05)
        cam = Camera.look_at(f"cam{i + 1}", pos, centre + rng.normal(0, 0.03 * arena, 3), width, height, f,
                             dist=(dist_k1 * rng.uniform(0.7, 1.3), dist_k2 * rng.uniform(0.5, 1.5), 0, 0, 0))
        off = rng.uniform(-1, 1, 2) * principal_offset_px  # drawn either way: the same rig otherwise
        cam.K[0, 2] += off[0]
        cam.K[1, 2] += off[1]
        cams[cam.name] = cam
    return cams


def led_path(n: int, arena: float = 1.0, seed: int = 0) -> NDArray[np.float64]:
    """A smooth wandering path that fills the arena (sum of incommensurate sinusoids per axis)."""
    rng = np.random.default_rng(seed + 1000)
    s = np.linspace(0, 1, n)
    out = np.zeros((n, 3))
    for ax in range(3):
        for k in range(4):
            freq = rng.uniform(2, 9) * (k + 1)
            out[:, ax] += np.sin(2 * np.pi * freq * s + rng.uniform(0, 2 * np.pi)) / (k + 1)
    out -= out.min(axis=0)
    out /= out.max(axis=0)
    return 0.05 * arena + 0.9 * arena * out - np.array([arena / 2, arena / 2, 0.0])


def observe(cameras: dict[str, Camera], points: NDArray[np.float64], noise_px: float = 0.5,
            missing: float = 0.3, outliers: float = 0.02, seed: int = 0) -> tuple[Observations, NDArray[np.bool_]]:
    """Project the LED into every camera: Gaussian noise, random drop-outs, uniformly random gross outliers."""
    rng = np.random.default_rng(seed + 2000)
    names = list(cameras)
    frames, cams, uvs, bad = [], [], [], []
    for ci, name in enumerate(names):
        cam = cameras[name]
        vis = cam.in_view(points, margin=2.0) & (rng.random(len(points)) >= missing)
        idx = np.nonzero(vis)[0]
        uv = cam.project(points[idx]) + rng.normal(0, noise_px, (len(idx), 2))
        out = rng.random(len(idx)) < outliers
        uv[out] = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (int(out.sum()), 2))
        frames.append(idx)
        cams.append(np.full(len(idx), ci))
        uvs.append(uv)
        bad.append(out)
    order = np.argsort(np.concatenate(frames), kind="stable")
    obs = Observations(np.concatenate(frames)[order], np.concatenate(cams)[order], np.concatenate(uvs)[order],
                       names, [(cameras[n].width, cameras[n].height) for n in names])
    return obs, np.concatenate(bad)[order]


def synthetic_rig(n_cameras: int, n_points: int = 3000, arena: float = 1.0, noise_px: float = 0.5,
                  missing: float = 0.3, outliers: float = 0.02, seed: int = 0, dist_k2: float = 0.03,
                  principal_offset_px: float = 15.0) -> SyntheticRig:
    cams = make_rig(n_cameras, arena=arena, seed=seed, dist_k2=dist_k2, principal_offset_px=principal_offset_px)
    pts = led_path(n_points, arena=arena, seed=seed)
    obs, bad = observe(cams, pts, noise_px=noise_px, missing=missing, outliers=outliers, seed=seed)
    return SyntheticRig(cams, arena, pts, obs, bad, noise_px)
