"""The batch's results table (one row per recording and parameter set) as CSV and Parquet, and a plot
that compares parameter sets across recordings."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd

COMPARED = (("coverage", "frames with an estimate / frames with 2D data"),
            ("objects", "objects (track ids)"),
            ("track_len_mean", "mean track length (frames)"),
            ("reproj_px_mean", "mean reprojection error (px)"))


def results_frame(rows: list[dict[str, Any]]) -> pd.DataFrame:
    df = pd.DataFrame(rows)
    if not df.empty:
        df = df.sort_values(["name", "params"] if "params" in df else ["name"], kind="stable").reset_index(drop=True)
    return df


def write_results(df: pd.DataFrame, out_dir: Path, stem: str = "results") -> list[Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    csv, pq = out_dir / f"{stem}.csv", out_dir / f"{stem}.parquet"
    df.to_csv(csv, index=False)
    df.to_parquet(pq, index=False)
    return [csv, pq]


def plot_param_sets(df: pd.DataFrame, path: Path) -> Path:
    """One panel per figure: each recording a line across the parameter sets, the mean in black."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = list(dict.fromkeys(df["params"]))
    fig, axes = plt.subplots(1, len(COMPARED), figsize=(4.2 * len(COMPARED), 3.8), squeeze=False)
    x = range(len(sets))
    for ax, (col, title) in zip(axes[0], COMPARED, strict=True):
        wide = df.pivot_table(index="name", columns="params", values=col, aggfunc="first").reindex(columns=sets)
        for _, r in wide.iterrows():
            ax.plot(x, r.to_numpy(dtype=float), "o-", color="0.7", lw=1, ms=3)
        ax.plot(x, wide.mean().to_numpy(dtype=float), "s-", color="k", lw=2, label="mean over recordings")
        ax.set_title(title, fontsize=9)
        ax.set_xticks(list(x), sets, rotation=30, ha="right", fontsize=7)
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"{df['name'].nunique()} recordings x {len(sets)} parameter sets")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
