"""Tracking accuracy against ground truth: 3D RMSE, MOTA, IDF1 (py-motmetrics), ID switches, merges."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import motmetrics as mm
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass
class TrackingScore:
    frames: int
    rmse_m: float  # over matched (truth, estimate) pairs
    mota: float
    idf1: float
    id_switches: int
    false_positives: int
    misses: int
    merges: int  # pairs of estimates that stayed within merge_dist_m of each other for merge_frames
    matches: int

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)

    def line(self) -> str:
        return (
            f"RMSE {self.rmse_m * 1e3:.2f} mm, MOTA {self.mota:.4f}, IDF1 {self.idf1:.4f}, "
            f"ID switches {self.id_switches}, FP {self.false_positives}, misses {self.misses}, "
            f"merges {self.merges} ({self.frames} frames, {self.matches} matches)"
        )


def score(
    truth: Sequence[dict[int, F64]],
    estimates: Sequence[dict[int, F64]],
    max_dist_m: float = 0.01,
    merge_dist_m: float = 0.002,
    merge_frames: int = 3,
) -> TrackingScore:
    """truth and estimates: per frame, id -> position (3,). An estimate further than max_dist_m from
    a true target cannot be matched to it."""
    if len(truth) != len(estimates):
        raise ValueError("truth and estimates must cover the same frames")
    acc = mm.MOTAccumulator(auto_id=True)
    close_run: dict[tuple[int, int], int] = {}
    merged_pairs: set[tuple[int, int]] = set()
    for gt, est in zip(truth, estimates, strict=True):
        g_ids = list(gt)
        h_ids = list(est)
        g = np.array([gt[i] for i in g_ids]).reshape(-1, 3)
        h = np.array([est[i] for i in h_ids]).reshape(-1, 3)
        dist = mm.distances.norm2squared_matrix(g, h, max_d2=max_dist_m**2)
        acc.update(g_ids, h_ids, dist)
        seen: set[tuple[int, int]] = set()
        if len(h_ids) > 1:
            d = np.linalg.norm(h[:, None] - h[None], axis=2)
            for a, b in zip(*np.nonzero(np.triu(d < merge_dist_m, 1)), strict=True):
                key = (h_ids[a], h_ids[b])
                seen.add(key)
                close_run[key] = close_run.get(key, 0) + 1
                if close_run[key] >= merge_frames:
                    merged_pairs.add(key)
        for key in list(close_run):
            if key not in seen:
                del close_run[key]
    mh = mm.metrics.create()
    s = mh.compute(acc, metrics=["mota", "idf1", "num_switches", "num_false_positives", "num_misses"], name="t")
    ev = acc.mot_events
    d2 = ev.loc[ev["Type"] == "MATCH", "D"].to_numpy(dtype=float)
    return TrackingScore(
        frames=len(truth),
        rmse_m=float(np.sqrt(d2.mean())) if d2.size else float("nan"),
        mota=float(s["mota"].iloc[0]),
        idf1=float(s["idf1"].iloc[0]),
        id_switches=int(s["num_switches"].iloc[0]),
        false_positives=int(s["num_false_positives"].iloc[0]),
        misses=int(s["num_misses"].iloc[0]),
        merges=len(merged_pairs),
        matches=int(d2.size),
    )
