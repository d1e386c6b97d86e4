"""Figures of a wing-beat analysis, as the seed draws them: the edge track over its measurements
(figs 4-6, 9), and frequency and amplitude per beat over time for each method (fig. 10)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flytrack_host.dvs.wingbeat.analysis import WingbeatResult

WING_NAMES = ("wing 0", "wing 1")


def plot_truth_beats(ax, truth, wing: int, frequency: bool, scale: float) -> None:
    """The truth's beat frequency (frequency=True) or the wing's amplitude times scale, over time in s,
    thinned to about 2000 points, as a dashed black line labelled "truth"."""
    tt = truth.t_us[:: max(1, len(truth.t_us) // 2000)]
    val = truth.freq_at(tt) if frequency else truth.amplitude_at(wing, tt) * scale
    ax.plot(tt * 1e-6, val, "k--", lw=1, label="truth")


def save_figure(fig, path: Path) -> Path:
    """Write fig as a PNG at 100 dpi (making its folder) and free it."""
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_wingbeats(results: list[WingbeatResult], path: Path, window_s: tuple[float, float] | None = None,
                   truth=None) -> Path:
    """One figure: per wing, a 40 ms window of the leading edge's track over its events, then frequency
    and amplitude per beat for every method given (and the truth when known)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 2, figsize=(12, 9), sharex="row")
    colours = {"ekf": "tab:red", "wra": "goldenrod"}
    t_first = min(r.wings[0].z_t_us[0] for r in results if len(r.wings[0].z_t_us)) * 1e-6
    lo, hi = window_s or (t_first + 0.3, t_first + 0.34)
    for w in (0, 1):
        ax = axes[0, w]
        ref = results[0].wings[w]
        sel = (ref.z_t_us * 1e-6 >= lo) & (ref.z_t_us * 1e-6 <= hi)
        ax.plot(ref.z_t_us[sel] * 1e-3, np.degrees(ref.z[sel]), ".", ms=1.5, color="0.6", label="events (angle)")
        for r in results:
            e = r.wings[w].edges["leading"]
            s = (e.t_us * 1e-6 >= lo) & (e.t_us * 1e-6 <= hi)
            ax.plot(e.t_us[s] * 1e-3, np.degrees(e.position[s]), "-", lw=1.2, color=colours.get(r.method, "k"),
                    label=f"{r.method.upper()} leading edge")
        ax.set_title(f"{WING_NAMES[w]}: track over measurements", fontsize=9)
        ax.set_xlabel("time (ms)")
        ax.set_ylabel("angle from heading (deg)")
        ax.legend(fontsize=7, loc="upper right")
        for row, (attr, label, scale) in enumerate((("freq_hz", "frequency (Hz)", 1.0),
                                                    ("amplitude", "amplitude (deg)", 180 / np.pi)), start=1):
            ax = axes[row, w]
            for r in results:
                b = r.wings[w].beats
                ax.plot(b.t_us * 1e-6, getattr(b, attr) * scale, ".-", ms=2, lw=0.6,
                        color=colours.get(r.method, "k"), label=r.method.upper())
            if truth is not None:
                plot_truth_beats(ax, truth, w, attr == "freq_hz", scale)
            ax.set_ylabel(label)
            ax.set_xlabel("time (s)")
            ax.legend(fontsize=7)
    fig.suptitle("Wing beats from events (seed 002, part II)")
    fig.tight_layout()
    return save_figure(fig, path)
