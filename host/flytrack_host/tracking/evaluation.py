"""Tracking quality against ground truth: 3D RMSE, MOTA, IDF1, ID switches, merges.

The one scorer of the project: the tracking tests and `flytrack bench tracker` (per-frame dicts from
tracking.synthetic, `score_frames`) and the simulated rig (`score_tracks`) use it. MOTA, IDF1 and ID
switches come from py-motmetrics (the CLEAR-MOT and ID measures as the MOT benchmarks compute them);
this module prepares the per-frame distance matrices, handles ground-truth objects that are not to be
scored, and adds what motmetrics does not count: the position RMSE of matched estimates, merges (one
track standing for two animals: an animal without a track while a track within reach belongs to
another), duplicates (the other way round: a second track on an animal that has its own, which
motmetrics counts as a false positive), and whether each ID switch happened during a close encounter
or in free flight.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
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
    duplicates: int  # episodes where a track was on an animal that had its own track (a false positive)
    duplicate_frames: int
    recall: float
    precision: float
    match_threshold_m: float

    def as_dict(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        return (f"RMSE {self.rmse_mm:.2f} mm, MOTA {self.mota:.4f}, IDF1 {self.idf1:.4f}, ID switches "
                f"{self.id_switches} ({self.id_switches_free_flight} in free flight), FP {self.false_positives}, "
                f"misses {self.misses}, merges {self.merges} ({self.merge_frames} animal-frames), "
                f"duplicates {self.duplicates} ({self.duplicate_frames} frames) "
                f"({self.frames} frames, {self.gt_detections} animal-frames scored)")


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
    duplicate_frames = duplicates = 0
    in_dup: set[int] = set()
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
        # Duplicates: a track owning no animal, within reach of one that has its own track.
        dup_now: set[int] = set()
        for j, h in enumerate(hid):
            if int(h) not in owned and dm.size and np.any(np.isfinite(dm[:, j])):
                dup_now.add(int(h))
        duplicate_frames += len(dup_now)
        duplicates += len(dup_now - in_dup)
        in_dup = dup_now
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
        duplicates=duplicates,
        duplicate_frames=duplicate_frames,
        recall=fin(s["recall"]),
        precision=fin(s["precision"]),
        match_threshold_m=thr,
    )


def score_frames(
    truth: Sequence[Mapping[int, NDArray[np.float64]]],
    estimates: Sequence[Mapping[int, NDArray[np.float64]]],
    match_threshold_m: float = 0.01,
    close_distance_m: float = 0.02,
    close_window: int = 10,
) -> TrackingScores:
    """`score_tracks` for per-frame dicts id -> position (3,) (tracking.synthetic's ground truth, the
    tracker's estimates). An animal absent from a frame is not scored in it; "close" (for the ID switch
    split) is another present animal within close_distance_m."""
    if len(truth) != len(estimates):
        raise ValueError(f"truth and estimates must cover the same frames ({len(truth)} vs {len(estimates)})")
    ids = sorted({int(i) for frame in truth for i in frame})
    col = {i: c for c, i in enumerate(ids)}
    F, n = len(truth), len(ids)
    gt_pos = np.full((F, n, 3), np.nan)
    for k, frame in enumerate(truth):
        for i, x in frame.items():
            gt_pos[k, col[int(i)]] = x
    present = np.all(np.isfinite(gt_pos), axis=2)
    close = np.zeros((F, n), bool)
    if n > 1:
        d = np.linalg.norm(gt_pos[:, :, None, :] - gt_pos[:, None, :, :], axis=-1)
        d[:, np.arange(n), np.arange(n)] = np.inf
        close = np.nan_to_num(d, nan=np.inf).min(axis=2) < close_distance_m
    hyps = [FrameTracks(k, np.array(list(e), np.int64), np.array([e[i] for i in e], np.float64).reshape(-1, 3))
            for k, e in enumerate(estimates)]
    # Absent animals stay NaN: no estimate is near them, so none is excused as near an unscored animal.
    return score_tracks(gt_pos, hyps, scored=present, close=close,
                        match_threshold_m=match_threshold_m, close_window=close_window)
