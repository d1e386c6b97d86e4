"""Calibration report: per-camera figures, warnings that say what to do, and a PNG plot."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flytrack_host.calibration.observations import Observations
from flytrack_host.geometry.camera import Camera

__all__ = ["CameraStats", "Report", "make_report", "plot_report", "set_equal_3d"]


@dataclass
class CameraStats:
    name: str
    points: int  # observations used
    rejected: int
    mean_px: float
    p95_px: float
    coverage: float  # fraction of a 4x4 grid of image cells that hold points


@dataclass
class Report:
    cameras: list[CameraStats]
    mean_px: float
    warnings: list[str] = field(default_factory=list)

    def lines(self) -> list[str]:
        out = [f"{'camera':<12} {'points':>7} {'rejected':>8} {'mean px':>8} {'p95 px':>8} {'coverage':>8}"]
        for s in self.cameras:
            out.append(f"{s.name:<12} {s.points:>7d} {s.rejected:>8d} {s.mean_px:>8.3f} {s.p95_px:>8.3f} "
                       f"{100 * s.coverage:>7.0f}%")
        out.append(f"overall mean reprojection error {self.mean_px:.3f} px")
        out += [f"warning: {w}" for w in self.warnings]
        return out


def make_report(cameras: dict[str, Camera], obs: Observations, residuals: np.ndarray, inlier: np.ndarray,
                min_points: int = 100) -> Report:
    stats: list[CameraStats] = []
    warns: list[str] = []
    rn = np.linalg.norm(residuals, axis=1)
    for c, name in enumerate(obs.camera_names):
        sel = inlier & (obs.cam == c) & np.isfinite(rn)
        e = rn[sel]
        w, h = obs.sizes[c]
        uv = obs.uv[sel]
        cells = set(zip(np.clip((uv[:, 0] / w * 4).astype(int), 0, 3), np.clip((uv[:, 1] / h * 4).astype(int), 0, 3),
                        strict=True))
        s = CameraStats(name, int(sel.sum()), int(np.sum((obs.cam == c) & ~inlier)),
                        float(np.mean(e)) if len(e) else float("nan"),
                        float(np.percentile(e, 95)) if len(e) else float("nan"), len(cells) / 16.0)
        stats.append(s)
        if s.points < min_points:
            warns.append(f"camera {name}: only {s.points} points used; wave the LED longer where it sees it "
                         f"(aim for {min_points} or more).")
        if s.coverage < 0.5:
            warns.append(f"camera {name}: points cover only {100 * s.coverage:.0f}% of the image; its lens "
                         "distortion is poorly known near the edges. Wave the LED through the corners of its view.")
    means = np.array([s.mean_px for s in stats])
    ok = np.isfinite(means)
    overall = float(np.mean(rn[inlier & np.isfinite(rn)])) if np.any(inlier) else float("nan")
    if ok.sum() >= 3:
        med = float(np.median(means[ok]))
        for s in stats:
            if np.isfinite(s.mean_px) and s.mean_px > max(2.0 * med, med + 0.5):
                warns.append(f"camera {s.name}: reprojection error {s.mean_px:.2f} px, much above the others "
                             f"({med:.2f} px). It may have been moved or bumped, or sees a reflection: check it "
                             "and record again.")
    for s in stats:
        total = s.points + s.rejected
        if total and s.rejected > 0.2 * total:
            warns.append(f"camera {s.name}: {s.rejected} of {total} detections rejected as outliers; look for a "
                         "second bright spot or reflection in its view.")
    return Report(stats, overall, warns)


def set_equal_3d(ax: object, pts: np.ndarray) -> tuple[float, float, float]:
    """Give a 3D axes the same scale on x, y and z (a cube around pts), so the rig is not distorted.

    Returns the (equal) half-widths that were set."""
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    lo, hi = (pts.min(axis=0), pts.max(axis=0)) if len(pts) else (np.zeros(3), np.ones(3))
    mid = (lo + hi) / 2
    half = max(float(np.max(hi - lo)) / 2, 1e-9) * 1.05
    ax.set_xlim(mid[0] - half, mid[0] + half)  # type: ignore[attr-defined]
    ax.set_ylim(mid[1] - half, mid[1] + half)  # type: ignore[attr-defined]
    ax.set_zlim(mid[2] - half, mid[2] + half)  # type: ignore[attr-defined]
    ax.set_box_aspect((1, 1, 1))  # type: ignore[attr-defined]
    return half, half, half


def plot_report(cameras: dict[str, Camera], points: np.ndarray, obs: Observations, residuals: np.ndarray,
                inlier: np.ndarray, path: str | Path) -> None:
    """Cameras and LED points in 3D, and reprojection error per camera, as one PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(13, 6))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    P = points[np.all(np.isfinite(points), axis=1)]
    if len(P) > 4000:
        P = P[:: len(P) // 4000 + 1]
    ax.scatter(P[:, 0], P[:, 1], P[:, 2], s=1, c="0.5", alpha=0.5)
    span = float(np.ptp(P, axis=0).max()) if len(P) else 1.0
    for name, cam in cameras.items():
        c = cam.center
        axis = cam.R[2] * 0.15 * span
        ax.scatter(*c, color="C3", s=30)
        ax.plot([c[0], c[0] + axis[0]], [c[1], c[1] + axis[1]], [c[2], c[2] + axis[2]], color="C3")
        ax.text(c[0], c[1], c[2], f" {name}", fontsize=8)
    set_equal_3d(ax, np.vstack([P.reshape(-1, 3)] + [c.center[None] for c in cameras.values()]))
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    ax.set_title("cameras and LED points")
    ax2 = fig.add_subplot(1, 2, 2)
    rn = np.linalg.norm(residuals, axis=1)
    data = [rn[inlier & (obs.cam == c) & np.isfinite(rn)] for c in range(obs.n_cameras)]
    ax2.boxplot([d if len(d) else np.array([np.nan]) for d in data], showfliers=False)
    ax2.set_xticks(range(1, obs.n_cameras + 1), obs.camera_names, rotation=45)
    ax2.set_ylabel("reprojection error (px)")
    ax2.set_title("reprojection error per camera (inliers)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
