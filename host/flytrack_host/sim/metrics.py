"""Tracking quality against ground truth: 3D RMSE, MOTA, IDF1, ID switches, merges.

MOTA, IDF1 and ID switches come from py-motmetrics (the CLEAR-MOT and ID measures as the MOT
benchmarks compute them); this module prepares the per-frame distance matrices, handles ground-truth
objects that are not to be scored, and adds what motmetrics does not count: the position RMSE of
matched estimates, merges (one track standing for two animals), and whether each ID switch happened
during a close encounter or in free flight.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass

import motmetrics as mm
import numpy as np
from numpy.typing import NDArray


@dataclass
class FrameTracks:
    """The tracker's estimates at one ground-truth frame."""

    frame: int  # ground-truth frame index
    ids: NDArray[np.int64]  # (m,)
    pos: NDArray[np.float64]  # (m, 3) m


@dataclass
class TrackingScores:
    frames: int
    gt_objects: int  # distinct animals scored
    gt_detections: int  # animal-frames scored
    tracks_found: int  # distinct track ids that matched an animal at least once
    tracks_total: int  # distinct track ids reported
    rmse_mm: float  # over matched animal-frames
    mota: float
    idf1: float
    id_switches: int
    id_switches_free_flight: int  # not within a close encounter
    misses: int
    false_positives: int
    merges: int  # episodes where a track stood for an animal that had none of its own
    merge_frames: int
    recall: float
    precision: float
    match_threshold_m: float

    def as_dict(self) -> dict:
        return asdict(self)


def score_tracks(
    gt_pos: NDArray[np.float64],
    hyps: Iterable[FrameTracks],
    scored: NDArray[np.bool_] | None = None,
    close: NDArray[np.bool_] | None = None,
    match_threshold_m: float = 0.02,
    close_window: int = 10,
) -> TrackingScores:
    """Score tracks against ground truth.

    gt_pos: (F, n, 3) true positions. hyps: the estimates per frame (frames not given have none).
    scored: (F, n) which animal-frames count (e.g. seen by >= 2 cameras); an estimate near an
    unscored animal is neither a hit nor a false positive. close: (F, n) animal near another one;
    an ID switch within `close_window` frames of that is a contact switch, else a free-flight one.
    """
    gt_pos = np.asarray(gt_pos, dtype=np.float64)
    if gt_pos.ndim != 3 or gt_pos.shape[2] != 3:
        raise ValueError(f"ground truth must be (frames, animals, 3), got {gt_pos.shape}")
    F, n, _ = gt_pos.shape
    scored = np.ones((F, n), bool) if scored is None else np.asarray(scored, bool)
    close = np.zeros((F, n), bool) if close is None else np.asarray(close, bool)
    if scored.shape != (F, n) or close.shape != (F, n):
        raise ValueError("scored and close masks must be (frames, animals) like the ground truth")
    by_frame: dict[int, FrameTracks] = {}
    for h in hyps:
        if not 0 <= h.frame < F:
            continue
        by_frame[h.frame] = h
    thr = float(match_threshold_m)
    acc = mm.MOTAccumulator(auto_id=False)
    all_ids: set[int] = set()
    per_frame: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    empty_ids = np.zeros(0, np.int64)
    empty_pos = np.zeros((0, 3))
    for k in range(F):
        h = by_frame.get(k)
        hid = np.asarray(h.ids, np.int64) if h is not None else empty_ids
        hpos = np.asarray(h.pos, np.float64).reshape(-1, 3) if h is not None else empty_pos
        all_ids.update(int(x) for x in hid)
        d = np.linalg.norm(gt_pos[k][:, None, :] - hpos[None, :, :], axis=-1)  # (n, m)
        # Estimates near an unscored animal (and near no scored one) are "don't care".
        sc = scored[k]
        if np.any(~sc) and hid.size:
            near_unscored = np.any(d[~sc] < thr, axis=0)
            near_scored = np.any(d[sc] < thr, axis=0) if np.any(sc) else np.zeros(hid.size, bool)
            keep = ~(near_unscored & ~near_scored)
            hid, hpos, d = hid[keep], hpos[keep], d[:, keep]
        oids = np.nonzero(sc)[0]
        dm = d[sc]
        dm = np.where(dm < thr, dm, np.nan)
        acc.update(oids.tolist(), hid.tolist(), dm, frameid=k)
        per_frame.append((oids, hid, dm))
    ev = acc.mot_events
    hits = ev[ev.Type.isin(["MATCH", "SWITCH"])]
    sq_err = (hits.D.to_numpy(dtype=float) ** 2).tolist()
    matched_ids = {int(x) for x in hits.HId.to_numpy()}
    owner: dict[int, dict[int, int]] = {}
    for (frame, _), row in hits.iterrows():
        owner.setdefault(int(frame), {})[int(row.OId)] = int(row.HId)
    # Merges: an animal without a track while a track within reach belongs to another animal.
    merge_frames = merges = 0
    in_merge = np.zeros(n, bool)
    for k, (oids, hid, dm) in enumerate(per_frame):
        matched_h = owner.get(k, {})
        owned = set(matched_h.values())
        now = np.zeros(n, bool)
        for o_i, o in enumerate(oids):
            if int(o) in matched_h or not hid.size:
                continue
            near = hid[np.nan_to_num(dm[o_i], nan=np.inf) < thr]
            now[o] = any(int(x) in owned for x in near)
        merge_frames += int(now.sum())
        merges += int(np.sum(now & ~in_merge))
        in_merge = now
    switches = ev[ev.Type == "SWITCH"]
    free = 0
    for (frame, _), row in switches.iterrows():
        o = int(row.OId)
        lo, hi = max(0, frame - close_window), min(F, frame + close_window + 1)
        if not np.any(close[lo:hi, o]):
            free += 1
    mh = mm.metrics.create()
    s = mh.compute(
        acc,
        metrics=["mota", "idf1", "num_switches", "num_misses", "num_false_positives", "recall", "precision"],
        name="sim",
    ).iloc[0]
    n_det = int(scored.sum())

    def fin(x: float) -> float:
        x = float(x)
        return x if np.isfinite(x) else 0.0

    return TrackingScores(
        frames=F,
        gt_objects=int(np.any(scored, axis=0).sum()),
        gt_detections=n_det,
        tracks_found=len(matched_ids),
        tracks_total=len(all_ids),
        rmse_mm=float(np.sqrt(np.mean(sq_err)) * 1000.0) if sq_err else float("nan"),
        mota=fin(s["mota"]),
        idf1=fin(s["idf1"]),
        id_switches=int(s["num_switches"]),
        id_switches_free_flight=free,
        misses=int(s["num_misses"]),
        false_positives=int(s["num_false_positives"]),
        merges=merges,
        merge_frames=merge_frames,
        recall=fin(s["recall"]),
        precision=fin(s["precision"]),
        match_threshold_m=thr,
    )


def latency_summary(latencies_s: Sequence[float] | NDArray[np.float64]) -> dict[str, float]:
    """P50, P99, max and mean of latencies, in milliseconds (NaN when there are none)."""
    a = np.asarray(latencies_s, dtype=np.float64)
    a = a[np.isfinite(a)]
    if a.size == 0:
        nan = float("nan")
        return {"p50_ms": nan, "p99_ms": nan, "max_ms": nan, "mean_ms": nan, "n": 0}
    return {
        "p50_ms": float(np.percentile(a, 50) * 1e3),
        "p99_ms": float(np.percentile(a, 99) * 1e3),
        "max_ms": float(a.max() * 1e3),
        "mean_ms": float(a.mean() * 1e3),
        "n": int(a.size),
    }
