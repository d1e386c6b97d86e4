"""The demo's figure: top and side views of the tracks, coloured by track id, ground truth faint behind
(the layout of flydra's figures 1b and 5), and each coordinate against time (figure 6)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from flytrack_host.sim.flight import GroundTruth  # noqa: E402
from flytrack_host.tracking.evaluation import FrameTracks  # noqa: E402


def _tracks_by_id(hyps: Sequence[FrameTracks]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    frames: dict[int, list[int]] = {}
    pts: dict[int, list[np.ndarray]] = {}
    for h in hyps:
        for i, p in zip(h.ids.tolist(), np.asarray(h.pos).reshape(-1, 3), strict=True):
            frames.setdefault(int(i), []).append(h.frame)
            pts.setdefault(int(i), []).append(p)
    return {i: (np.asarray(frames[i]), np.asarray(pts[i])) for i in frames}


def _broken(frames: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """Insert NaN where frames jump, so a track with gaps is not drawn across them."""
    out = xs.astype(float).copy()
    if frames.size > 1:
        gap = np.nonzero(np.diff(frames) > 1)[0]
        out = np.insert(out, gap + 1, np.nan, axis=0)
    return out


def plot_tracks(gt: GroundTruth, hyps: Sequence[FrameTracks], path: Path, title: str = "",
                latencies_ms: Sequence[float] | None = None) -> Path:
    tracks = _tracks_by_id(hyps)
    fig = plt.figure(figsize=(12, 8.5), constrained_layout=True)
    gs = fig.add_gridspec(3, 2, width_ratios=[1.6, 1.0])
    ax_top = fig.add_subplot(gs[0, 0])
    ax_side = fig.add_subplot(gs[1, 0], sharex=ax_top)
    ax_t = [fig.add_subplot(gs[i, 1]) for i in range(3)]
    sub = gs[2, 0].subgridspec(1, 2, width_ratios=[1.0, 1.2])
    ax_info = fig.add_subplot(sub[0, 0])
    ax_info.axis("off")
    ax_lat = fig.add_subplot(sub[0, 1])
    lo, hi = gt.arena.lo, gt.arena.hi
    t = gt.t
    for a in range(gt.n_animals):
        p = gt.pos[:, a]
        ax_top.plot(p[:, 0], p[:, 1], color="0.75", lw=3.0, zorder=1)
        ax_side.plot(p[:, 0], p[:, 2], color="0.75", lw=3.0, zorder=1)
        for k in range(3):
            ax_t[k].plot(t, p[:, k], color="0.8", lw=3.0, zorder=1)
    cmap = plt.get_cmap("tab10")
    for n_i, (tid, (fr, pts)) in enumerate(sorted(tracks.items())):
        col = cmap(n_i % 10)
        xs = _broken(fr, pts)
        tt = _broken(fr, fr / gt.fps)
        ax_top.plot(xs[:, 0], xs[:, 1], color=col, lw=1.0, zorder=2, label=f"track {tid}")
        ax_side.plot(xs[:, 0], xs[:, 2], color=col, lw=1.0, zorder=2)
        for k in range(3):
            ax_t[k].plot(tt, xs[:, k], color=col, lw=1.0, zorder=2)
    for ax, (i, j), name in ((ax_top, (0, 1), "top view"), (ax_side, (0, 2), "side view")):
        ax.add_patch(plt.Rectangle((lo[i], lo[j]), hi[i] - lo[i], hi[j] - lo[j], fill=False, color="k", lw=0.8))
        ax.set_aspect("equal")
        ax.set_xlim(lo[0] - 0.02, hi[0] + 0.02)
        ax.set_ylim(lo[j] - 0.02, hi[j] + 0.02)
        ax.set_ylabel(f"{'xyz'[j]} (m)")
        ax.set_title(name, fontsize=10)
    ax_side.set_xlabel("x (m)")
    for k in range(3):
        ax_t[k].set_ylabel(f"{'xyz'[k]} (m)")
        ax_t[k].set_xlim(0, t[-1] if t.size else 1)
    ax_t[2].set_xlabel("time (s)")
    ax_t[0].set_title("coordinates against time", fontsize=10)
    if len(tracks) <= 12:
        ax_top.legend(loc="upper right", fontsize=7, ncols=min(4, max(1, len(tracks))))
    ax_info.text(0.0, 1.0, title, va="top", ha="left", family="monospace", fontsize=8)
    lat = np.asarray(latencies_ms if latencies_ms is not None else [], dtype=float)
    lat = lat[np.isfinite(lat)]
    if lat.size:
        hi_ms = max(1.0, float(np.percentile(lat, 95)) * 2.0)
        over = int(np.sum(lat > hi_ms))
        ax_lat.hist(lat[lat <= hi_ms], bins=60, range=(0, hi_ms), color="0.35")
        p50 = float(np.median(lat))
        ax_lat.axvline(p50, color="C3", lw=1)
        more = f"; {over} frames > {hi_ms:.0f} ms, max {lat.max():.0f} ms" if over else ""
        ax_lat.set_title(f"latency, frames to 3D estimate (P50 {p50:.2f} ms{more})", fontsize=8)
        ax_lat.set_xlabel("ms")
        ax_lat.set_ylabel("frames")
    else:
        ax_lat.axis("off")
    fig.suptitle("FlyTrack simulated rig: tracks (colour) over ground truth (grey)")
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
