"""Synthetic tracking scenarios: known 3D flight paths seen as 2D points by a calibrated rig.

Used by the tracker's tests and benchmarks. A scenario is a rig of cameras around seed 000's
0.3 x 0.3 x 1.5 m flight arena (x along the 1.5 m axis), smooth random flight paths (targets may enter
and leave), and for every trigger frame a `FrameBundle` of protocol point arrays: the true positions
projected with lens distortion, Gaussian pixel noise, missed detections, blobs of nearby targets
merging into one point, false positives, optional NaN/inf points and camera outages.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from flytrack_host.geometry.camera import Camera
from flytrack_host.geometry.refraction import FlatInterface
from flytrack_host.protocol import POINT_DTYPE
from flytrack_host.tracking.types import FrameBundle

F64 = NDArray[np.float64]
ARENA_LO = np.array([0.0, -0.15, 0.0])
ARENA_HI = np.array([1.5, 0.15, 0.3])


def arena_cameras(
    n_cameras: int, width: int = 640, height: int = 480, distortion: bool = True, seed: int = 0,
    interface: FlatInterface | None = None,
) -> dict[int, Camera]:
    """`n_cameras` cameras on a ring around the arena (plus one overhead from 5 cameras on), each
    with the focal length that just fits the whole arena in its image, and mild lens distortion."""
    if n_cameras < 1:
        raise ValueError("need at least one camera")
    rng = np.random.default_rng(seed)
    centre = (ARENA_LO + ARENA_HI) / 2.0
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    corners = ARENA_LO + corners * (ARENA_HI - ARENA_LO)
    n_ring = n_cameras - 1 if n_cameras >= 5 else n_cameras
    cams: dict[int, Camera] = {}
    for i in range(n_cameras):
        if i < n_ring:
            phi = 2.0 * np.pi * i / n_ring + 0.3
            pos = centre + np.array([1.3 * np.cos(phi), 0.9 * np.sin(phi), 0.35 + 0.25 * (i % 3)])
        else:
            pos = centre + np.array([0.05, 0.02, 1.4])
        dist = (
            (rng.uniform(-0.12, -0.05), rng.uniform(0.0, 0.03), rng.uniform(-1e-3, 1e-3),
             rng.uniform(-1e-3, 1e-3), 0.0)
            if distortion
            else (0.0,) * 5
        )
        probe = Camera.look_at(f"cam{i}", pos, centre, width, height, 1.0)
        Xc = probe.to_camera(corners)
        xn = np.abs(Xc[:, :2] / Xc[:, 2:3])
        margin = 20.0
        f = min((width / 2 - margin) / xn[:, 0].max(), (height / 2 - margin) / xn[:, 1].max())
        cams[i] = Camera.look_at(f"cam{i}", pos, centre, width, height, f, dist=dist, interface=interface)
    return cams


@dataclass
class Scenario:
    cameras: dict[int, Camera]
    frame_period_s: float
    bundles: list[FrameBundle]
    truth: list[dict[int, F64]]  # per frame: ground-truth id -> true position (3,)
    truth_axis: list[dict[int, F64]]  # per frame: ground-truth id -> unit body axis (3,)
    n_points: int = 0
    n_false_positives: int = 0
    n_merged_blobs: int = 0
    n_corrupted: int = 0
    closest_approach_m: float = float("inf")
    notes: list[str] = field(default_factory=list)


def _smooth_path(rng: np.random.Generator, t: F64, margin: float = 0.03) -> F64:
    """A smooth random path (len(t), 3) inside the arena: a few sinusoids per axis."""
    out = np.empty((t.size, 3))
    for ax in range(3):
        lo, hi = ARENA_LO[ax] + margin, ARENA_HI[ax] - margin
        n = 3
        amp = rng.uniform(0.3, 1.0, n)
        freq = rng.uniform(0.08, 0.35, n) * (1.0 if ax == 0 else 1.6)
        phase = rng.uniform(0, 2 * np.pi, n)
        s = (amp[None, :] * np.sin(2 * np.pi * freq[None, :] * t[:, None] + phase[None, :])).sum(axis=1)
        s /= amp.sum()
        out[:, ax] = (lo + hi) / 2 + s * (hi - lo) / 2
    return out


def make_scenario(
    n_cameras: int = 5,
    n_targets: int = 3,
    duration_s: float = 10.0,
    fps: float = 100.0,
    noise_px: float = 0.5,
    p_miss: float = 0.05,
    false_positives_per_camera: float = 0.3,
    close_pass_m: float | None = 0.006,
    merge_px: float = 3.0,
    corrupt_fraction: float = 0.0,
    camera_outages: tuple[tuple[int, int, int], ...] = (),
    enter_exit: bool = True,
    width: int = 640,
    height: int = 480,
    seed: int = 1,
    interface: FlatInterface | None = None,
    cameras: dict[int, Camera] | None = None,
) -> Scenario:
    """Build a scenario. With `close_pass_m`, targets 0 and 1 fly head-on past each other at that
    distance mid-way through. `camera_outages`: (camera, first_frame, last_frame) spans where that
    camera sends nothing. `corrupt_fraction`: share of points whose x_dist or area is set to NaN/inf.
    `interface`: every camera sees the arena through it (e.g. FlatInterface.water_surface(z=0.3), the
    arena's top). `cameras`: a rig to use instead of arena_cameras (n_cameras, width, height and
    interface are then ignored)."""
    rng = np.random.default_rng(seed)
    cams = cameras if cameras is not None else arena_cameras(n_cameras, width, height, seed=seed, interface=interface)
    n_frames = int(round(duration_s * fps))
    t = np.arange(n_frames) / fps
    # Positions (targets, frames, 3); NaN where a target is absent.
    pos = np.full((n_targets, n_frames, 3), np.nan)
    for k in range(n_targets):
        path = _smooth_path(rng, t)
        if k == 1 and close_pass_m is not None and n_targets >= 2:
            continue  # set below from target 0
        pos[k] = path
    sc_notes: list[str] = []
    if close_pass_m is not None and n_targets >= 2:
        tc_i = n_frames // 2
        # Target 1 retraces target 0's path backwards in time around tc: a head-on pass.
        mirror = np.clip(2 * tc_i - np.arange(n_frames), 0, n_frames - 1)
        vel = pos[0, min(tc_i + 1, n_frames - 1)] - pos[0, tc_i - 1]
        side = np.cross(vel, [0.0, 0.0, 1.0])
        side /= np.linalg.norm(side) + 1e-12
        pos[1] = pos[0, mirror] + close_pass_m * side
        span = int(1.5 * fps)
        pos[1, : max(tc_i - span, 0)] = np.nan
        pos[1, tc_i + span :] = np.nan
        sc_notes.append(f"targets 0 and 1 pass head-on {close_pass_m * 1e3:.1f} mm apart at frame {tc_i}")
    if enter_exit:
        for k in range(2, n_targets):
            a = int(rng.uniform(0.0, 0.3) * n_frames)
            b = int(rng.uniform(0.7, 1.0) * n_frames)
            pos[k, :a] = np.nan
            pos[k, b:] = np.nan
    vel = np.gradient(pos, axis=1) * fps
    speed = np.linalg.norm(vel, axis=2, keepdims=True)
    axis = vel / np.where(speed > 1e-9, speed, 1.0)
    alive = np.isfinite(pos).all(axis=2)  # (K, F)
    d_min = np.inf
    for a in range(n_targets):
        for b in range(a + 1, n_targets):
            both = alive[a] & alive[b]
            if both.any():
                d_min = min(d_min, float(np.linalg.norm(pos[a, both] - pos[b, both], axis=1).min()))

    outage = {ci: np.zeros(n_frames, dtype=bool) for ci in cams}
    for ci, f0, f1 in camera_outages:
        outage[ci][f0 : f1 + 1] = True

    # Per camera: rows of (frame, u, v, area, theta, ecc) for all frames at once.
    counts = {"points": 0, "fp": 0, "merged": 0, "corrupt": 0}
    frame_rows: dict[int, list[tuple[int, np.ndarray]]] = {}
    for ci, cam in cams.items():
        P = np.nan_to_num(pos.reshape(-1, 3))
        uv = cam.project(P).reshape(n_targets, n_frames, 2)
        vis = alive & cam.in_view(P, margin=1.0).reshape(n_targets, n_frames)
        vis &= rng.random(vis.shape) >= p_miss
        depth = cam.to_camera(P)[:, 2].reshape(n_targets, n_frames)
        area = 40.0 * (0.8 / np.maximum(depth, 0.1)) ** 2 * rng.lognormal(0.0, 0.1, vis.shape)
        tip = cam.project(P + 0.002 * np.nan_to_num(axis.reshape(-1, 3))).reshape(n_targets, n_frames, 2)
        d = tip - uv
        theta = np.arctan(d[..., 1] / np.where(np.abs(d[..., 0]) > 1e-12, d[..., 0], 1e-12))
        theta += rng.normal(0.0, 0.03, theta.shape)
        plen = np.linalg.norm(d, axis=2) / (0.002 * cam.K[0, 0] / np.maximum(depth, 0.1))
        ecc = 1.0 + 2.0 * np.clip(plen, 0.0, 1.0)
        obs = uv + rng.normal(0.0, noise_px, uv.shape)
        rows_f: list[np.ndarray] = []
        for f in range(n_frames):
            if outage[ci][f]:
                continue
            ks = np.flatnonzero(vis[:, f])
            pts = np.column_stack([obs[ks, f], area[ks, f], theta[ks, f], ecc[ks, f]]) if ks.size else np.empty((0, 5))
            if ks.size > 1:
                pts, merged = _merge_blobs(pts, uv[ks, f], merge_px)
                counts["merged"] += merged
            n_fp = rng.poisson(false_positives_per_camera)
            if n_fp:
                fp = np.column_stack([
                    rng.uniform(0, width - 1, n_fp), rng.uniform(0, height - 1, n_fp),
                    rng.uniform(5.0, 80.0, n_fp), rng.uniform(-np.pi / 2, np.pi / 2, n_fp),
                    rng.uniform(1.0, 3.0, n_fp),
                ])
                pts = np.concatenate([pts, fp])
                counts["fp"] += n_fp
            pts = pts[rng.permutation(pts.shape[0])]
            rows_f.append(np.column_stack([np.full(pts.shape[0], f), pts]))
        allrows = np.concatenate(rows_f) if rows_f else np.empty((0, 6))
        ideal = cam.undistort(allrows[:, 1:3]) if allrows.size else np.empty((0, 2))
        arr = np.zeros(allrows.shape[0], POINT_DTYPE)
        arr["x_dist"], arr["y_dist"] = allrows[:, 1], allrows[:, 2]
        arr["x_undist"], arr["y_undist"] = ideal[:, 0], ideal[:, 1]
        arr["area"] = allrows[:, 3]
        arr["orientation"] = allrows[:, 4]
        arr["eccentricity"] = allrows[:, 5]
        arr["peak_diff"] = 60.0
        arr["cur_val"] = 30
        arr["mean_val"] = 200.0
        arr["sumsq_val"] = 200.0**2 + 25.0
        if corrupt_fraction > 0 and arr.size:
            bad = rng.random(arr.size) < corrupt_fraction
            which = rng.integers(0, 4, arr.size)
            arr["x_dist"][bad & (which == 0)] = np.nan
            arr["y_undist"][bad & (which == 1)] = np.inf
            arr["area"][bad & (which == 2)] = np.nan
            arr["x_undist"][bad & (which == 3)] = -np.inf
            counts["corrupt"] += int(bad.sum())
        counts["points"] += arr.size
        frames_of = allrows[:, 0].astype(np.int64)
        bounds = np.searchsorted(frames_of, np.arange(n_frames + 1))
        for f in range(n_frames):
            frame_rows.setdefault(f, []).append((ci, arr[bounds[f] : bounds[f + 1]]))

    bundles: list[FrameBundle] = []
    truth: list[dict[int, F64]] = []
    truth_axis: list[dict[int, F64]] = []
    for f in range(n_frames):
        dets = {ci: a for ci, a in frame_rows.get(f, []) if not outage[ci][f]}
        missing = tuple(ci for ci in cams if outage[ci][f])
        bundles.append(FrameBundle(trigger_frame=f, timestamp=t[f], detections=dets, missing_cameras=missing))
        truth.append({k: pos[k, f].copy() for k in range(n_targets) if alive[k, f]})
        truth_axis.append({k: axis[k, f].copy() for k in range(n_targets) if alive[k, f]})
    return Scenario(
        cameras=cams, frame_period_s=1.0 / fps, bundles=bundles, truth=truth, truth_axis=truth_axis,
        n_points=counts["points"], n_false_positives=counts["fp"], n_merged_blobs=counts["merged"],
        n_corrupted=counts["corrupt"], closest_approach_m=d_min, notes=sc_notes,
    )


def _merge_blobs(pts: F64, uv_true: F64, merge_px: float) -> tuple[F64, int]:
    """Targets whose true images are closer than merge_px make one blob: one area-weighted point."""
    n = pts.shape[0]
    d = np.linalg.norm(uv_true[:, None] - uv_true[None], axis=2)
    close = (d < merge_px) & ~np.eye(n, dtype=bool)
    if not close.any():
        return pts, 0
    keep = np.ones(n, dtype=bool)
    merged = 0
    for a in range(n):
        if not keep[a]:
            continue
        group = [a] + [b for b in range(a + 1, n) if keep[b] and close[a, b]]
        if len(group) > 1:
            w = pts[group, 2]
            pts[a, 0:2] = (pts[group, 0:2] * w[:, None]).sum(axis=0) / w.sum()
            pts[a, 2] = w.sum()
            keep[group[1:]] = False
            merged += 1
    return pts[keep], merged


def point_array(
    cam: Camera, uv: F64, area: float = 30.0, theta: float = np.nan, ecc: float = np.nan
) -> np.ndarray:
    """A protocol point array for distorted pixels uv (N, 2) seen by `cam` (x_undist from the model)."""
    uv = np.atleast_2d(np.asarray(uv, dtype=np.float64)).reshape(-1, 2)
    arr = np.zeros(uv.shape[0], POINT_DTYPE)
    if uv.shape[0] == 0:
        return arr
    ideal = cam.undistort(uv)
    arr["x_dist"], arr["y_dist"] = uv[:, 0], uv[:, 1]
    arr["x_undist"], arr["y_undist"] = ideal[:, 0], ideal[:, 1]
    arr["area"] = area
    arr["orientation"] = theta
    arr["eccentricity"] = ecc
    return arr
