"""The seed's figures from a track: Figure 5 (position, orientation and total curvature against time, per-frame
fit dashed, smoothed solid), Figure 9 (multi-exposure image with the estimated midlines on the top and side
views), Figure 11 (curvature along the body against time)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from flytrack_host.fish.curvature import S_GRID, curvature, total_curvature  # noqa: E402
from flytrack_host.fish.pipeline import TrackResult, midlines  # noqa: E402
from flytrack_host.fish.shape import angles_from_heading  # noqa: E402
from flytrack_host.fish.views import View  # noqa: E402


def _busiest_fish(res: TrackResult) -> int:
    kt = np.nan_to_num(total_curvature(res.smoothed[:, :, 6:11]))
    return int(np.argmax(kt.max(axis=0)))


def figure5(res: TrackResult, fish: int, path: Path) -> None:
    t = (res.first_frame + np.arange(res.smoothed.shape[0])) / res.fps * 1000
    fig, ax = plt.subplots(3, 1, figsize=(7, 7), sharex=True)
    for X, style in ((res.raw[:, fish], "--"), (res.smoothed[:, fish], "-")):
        for i, (c, lab) in enumerate(zip("bgr", ("$r_1$", "$r_2$", "$r_3$"), strict=True)):
            ax[0].plot(t, X[:, i] * 1000, style, color=c, label=lab if style == "-" else None, lw=1)
        yaw, pitch = angles_from_heading(X[:, 3:6])
        ax[1].plot(t, np.degrees(np.unwrap(yaw)), style, color="r", label="yaw" if style == "-" else None, lw=1)
        ax[1].plot(t, np.degrees(pitch), style, color="g", label="pitch" if style == "-" else None, lw=1)
        ax[1].plot(t, np.zeros_like(t), style, color="b", label="roll (0 by assumption 3.2)" if style == "-" else None,
                   lw=1)
        ax[2].plot(t, total_curvature(X[:, 6:11]), style, color="k", lw=1)
    ax[0].set_ylabel("position (mm)")
    ax[1].set_ylabel("orientation (deg)")
    ax[2].set_ylabel(r"$\kappa_{total}$ (1/m)")
    ax[2].set_xlabel("time (ms)")
    ax[0].legend(fontsize=7, ncol=3)
    ax[1].legend(fontsize=7, ncol=3)
    ax[0].set_title(f"fish {fish}: per-frame fit (dashed) and smoothed (solid)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure9(res: TrackResult, views: Sequence[View], path: Path) -> None:
    """Multi-exposure: the darkest value over every 10th frame (TrackResult.exposure), with the estimated
    midlines of those frames."""
    every = getattr(res, "exposure_every", 10)
    n = len(views)
    fig, ax = plt.subplots(1, n, figsize=(6 * n, 4.5))
    ax = np.atleast_1d(ax)
    T = res.smoothed.shape[0]
    frames = list(range(0, T, every))
    colours = plt.cm.tab10(np.arange(res.n_fish) % 10)
    for c, view in enumerate(views):
        if c < len(getattr(res, "exposure", [])):
            ax[c].imshow(res.exposure[c], cmap="gray", vmin=0, vmax=255)
        lo = np.array([np.inf, np.inf])
        hi = -lo
        for f in range(res.n_fish):
            m = midlines(res.smoothed[frames, f], res.models[f])
            uv = view.project(m)
            for k in range(len(frames)):
                ax[c].plot(uv[k, :, 0], uv[k, :, 1], "-", color=colours[f], lw=1)
                ax[c].plot(uv[k, 0, 0], uv[k, 0, 1], ".", color=colours[f], ms=3)
            ok = np.isfinite(uv).all(axis=-1)
            if np.any(ok):
                lo = np.minimum(lo, uv[ok].min(axis=0))
                hi = np.maximum(hi, uv[ok].max(axis=0))
        if np.all(np.isfinite(lo)):
            pad = 30
            ax[c].set_xlim(max(lo[0] - pad, 0), min(hi[0] + pad, view.width))
            ax[c].set_ylim(min(hi[1] + pad, view.height), max(lo[1] - pad, 0))
        ax[c].set_title(f"{view.name} view: midlines every {every} frames (dot: nose)")
        ax[c].set_xticks([])
        ax[c].set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure11(res: TrackResult, path: Path) -> None:
    """Curvature along the body (x) against time (y) for the calmest and the busiest fish."""
    kt = np.nan_to_num(total_curvature(res.smoothed[:, :, 6:11]))
    order = np.argsort(kt.max(axis=0))
    pick = [int(order[0]), int(order[-1])] if res.n_fish > 1 else [0]
    fig, ax = plt.subplots(1, len(pick), figsize=(4.5 * len(pick), 4.5), squeeze=False)
    t = (res.first_frame + np.arange(res.smoothed.shape[0])) / res.fps * 1000
    vmax = np.nanpercentile(curvature(res.smoothed[:, pick, 6:11]), 99)
    for a, f in zip(ax[0], pick, strict=True):
        k = curvature(res.smoothed[:, f, 6:11])
        im = a.imshow(k, aspect="auto", origin="lower", cmap="gray_r", vmin=0, vmax=vmax,
                      extent=(S_GRID[0], S_GRID[-1], t[0], t[-1]))
        a.set_xlabel("body length (s)")
        a.set_ylabel("time (ms)")
        a.set_title(f"fish {f}: curvature $\\kappa(s)$")
        fig.colorbar(im, ax=a, label="1/m")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_plots(out: Path, res: TrackResult, views: Sequence[View], images: object = None) -> list[Path]:
    """Figures 5, 9 and 11 as PNG files in `out`. (`images` is not used: Figure 9's multi-exposure image
    is gathered while tracking, TrackResult.exposure.)"""
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "fish_fig5_state.png", out / "fish_fig9_midlines.png", out / "fish_fig11_curvature.png"]
    figure5(res, _busiest_fish(res), paths[0])
    figure9(res, views, paths[1])
    figure11(res, paths[2])
    return paths
