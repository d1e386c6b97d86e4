"""`flytrack compare A B`: do two track sets over the same 2D data agree?

A track set is 3D estimates (obj_id, frame, x, y, z in metres) plus, where known, which 2D points each
estimate used, the 2D points and the calibration. Sources: a FlyTrack recording, a .braidz, a flydra .h5
(its `kalman_estimates` are flydra's own tracks, the 2D points they used are in `ML_estimates` and
`ML_estimates_2d_idxs`).

Reported: frames each set covers and both cover; per frame, the estimates of A and B paired one-to-one
(scipy's linear_sum_assignment on 3D distance, pairs farther than `match_m` left unpaired) and the
distances of the pairs; coverage (share of each set's estimates that found a partner); objects matched
(an A object and the B object it was paired with most often, over at least half of its paired frames);
and each set's reprojection error: the distance from each estimate's distorted projection to the 2D
points it used (the data association when the source has one, else, labelled so, the nearest 2D point
of each camera within `nearest_px`).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment

from flytrack_host.geometry.camera import Camera
from flytrack_host.io.reprojection import associated_reprojection


class CompareError(Exception):
    pass


@dataclass
class TrackSet:
    name: str
    est: pd.DataFrame  # obj_id, frame, x, y, z
    assoc: pd.DataFrame | None  # obj_id, frame, camn, pt_idx
    rows: np.ndarray | None  # DATA2D rows (camera_index, trigger_frame, frame_pt_idx, x_dist, y_dist)
    cameras: dict[int, Camera] = field(default_factory=dict)


def _columns(df: pd.DataFrame, cols: list[str], path: Path, table: str) -> pd.DataFrame:
    missing = [c for c in cols if c not in df.columns]
    if missing:
        raise CompareError(f"{path}: its {table} table has no column {', '.join(missing)} "
                           f"(it has {', '.join(map(str, df.columns)) or 'none'})")
    return df[cols].copy()


def load_tracks(path: Path | str, calibration: Path | None = None) -> TrackSet:
    from flytrack_host.io.retrack import RetrackError, cameras_for, load_2d

    path = Path(path)
    try:
        data = load_2d(path)
    except Exception as exc:
        raise CompareError(str(exc)) from None
    try:
        cams = cameras_for(data, calibration)
    except RetrackError:
        cams = {}
    assoc = None
    if path.is_file() and zipfile.is_zipfile(path):
        from flytrack_host.io.braidz import _read_table

        with zipfile.ZipFile(path) as z:
            k = _read_table(z, "kalman_estimates")
            a = _read_table(z, "data_association")
        if k is None:
            raise CompareError(f"{path}: no kalman_estimates table")
        est = _columns(k, ["obj_id", "frame", "x", "y", "z"], path, "kalman_estimates")
        if a is not None and len(a.columns):
            assoc = _columns(a.rename(columns={"cam_num": "camn"}), ["obj_id", "frame", "camn", "pt_idx"], path,
                             "data_association")
    else:
        from flytrack_host.recording.finalize import RecordingError
        from flytrack_host.recording.reader import load_recording

        try:
            rec = load_recording(path)
        except RecordingError:
            from flytrack_host.io.flydra_h5 import read_flydra_association, read_flydra_kalman

            k = read_flydra_kalman(path)
            if k is None or not len(k):
                raise CompareError(f"{path}: no kalman_estimates table") from None
            est = _columns(k, ["obj_id", "frame", "x", "y", "z"], path, "kalman_estimates")
            assoc = read_flydra_association(path)
        else:
            k = rec.table("kalman_estimates")
            est = pd.DataFrame({"obj_id": k["obj_id"], "frame": k["trigger_frame"], "x": k["x"], "y": k["y"],
                                "z": k["z"]})
            a = rec.table("data_association")
            assoc = pd.DataFrame({"obj_id": a["obj_id"], "frame": a["trigger_frame"], "camn": a["camera_index"],
                                  "pt_idx": a["pt_idx"]})
    est = est[np.isfinite(est[["x", "y", "z"]].to_numpy()).all(axis=1)]
    return TrackSet(path.name, est.reset_index(drop=True), assoc, data.rows, cams)


@dataclass
class Comparison:
    frames_a: int
    frames_b: int
    frames_both: int
    estimates_a: int
    estimates_b: int
    paired: int
    distances_m: np.ndarray
    objects_a: int
    objects_b: int
    objects_matched: int
    reproj_a: np.ndarray
    reproj_b: np.ndarray
    reproj_how_a: str
    reproj_how_b: str

    @property
    def coverage_a(self) -> float:
        return self.paired / max(self.estimates_a, 1)

    @property
    def coverage_b(self) -> float:
        return self.paired / max(self.estimates_b, 1)

    def agree(self, min_coverage: float = 0.9, max_median_mm: float = 5.0) -> bool:
        return bool(self.coverage_a >= min_coverage and self.coverage_b >= min_coverage and self.paired
                    and float(np.median(self.distances_m)) * 1e3 <= max_median_mm)


def reprojection(ts: TrackSet, nearest_px: float = 10.0) -> tuple[np.ndarray, str]:
    """Per (estimate, camera) pair: distance (px) from the estimate's projection to the 2D point it used."""
    if ts.rows is None or not ts.cameras or not len(ts.est):
        return np.empty(0), "no 2D points or calibration"
    if ts.assoc is not None and len(ts.assoc):
        return associated_reprojection(ts.est, ts.assoc, ts.rows, ts.cameras), "the points of its data association"
    out: list[float] = []
    r = ts.rows[np.isfinite(ts.rows["x_dist"])]
    for camn, cam in ts.cameras.items():
        rc = r[r["camera_index"] == camn]
        if not len(rc):
            continue
        order = np.argsort(rc["trigger_frame"], kind="stable")
        rc = rc[order]
        frames = rc["trigger_frame"]
        uv = cam.project(ts.est[["x", "y", "z"]].to_numpy(dtype=np.float64))
        lo = np.searchsorted(frames, ts.est["frame"].to_numpy(), "left")
        hi = np.searchsorted(frames, ts.est["frame"].to_numpy(), "right")
        for q, a, b in zip(uv, lo, hi, strict=True):
            if b > a and np.isfinite(q).all():
                d = np.hypot(rc["x_dist"][a:b] - q[0], rc["y_dist"][a:b] - q[1]).min()
                if d <= nearest_px:
                    out.append(float(d))
    return np.asarray(out), f"the nearest 2D point of each camera within {nearest_px:g} px (no association)"


def compare(a: TrackSet, b: TrackSet, match_m: float = 0.01, nearest_px: float = 10.0) -> Comparison:
    ea, eb = a.est, b.est
    fa, fb = set(ea["frame"].tolist()), set(eb["frame"].tolist())
    both = sorted(fa & fb)
    ga = {f: g for f, g in ea[ea["frame"].isin(both)].groupby("frame")}
    gb = {f: g for f, g in eb[eb["frame"].isin(both)].groupby("frame")}
    dists: list[float] = []
    pairs: dict[tuple[int, int], int] = {}
    for f in both:
        A, B = ga[f], gb[f]
        XA, XB = A[["x", "y", "z"]].to_numpy(float), B[["x", "y", "z"]].to_numpy(float)
        D = np.linalg.norm(XA[:, None] - XB[None], axis=2)
        ia, ib = linear_sum_assignment(D)
        for i, j in zip(ia, ib, strict=True):
            if D[i, j] <= match_m:
                dists.append(float(D[i, j]))
                key = (int(A["obj_id"].iloc[i]), int(B["obj_id"].iloc[j]))
                pairs[key] = pairs.get(key, 0) + 1
    per_a: dict[int, list[tuple[int, int]]] = {}
    for (oa, ob), n in pairs.items():
        per_a.setdefault(oa, []).append((n, ob))
    matched = 0
    for lst in per_a.values():
        total = sum(n for n, _ in lst)
        if max(lst)[0] >= 0.5 * total:
            matched += 1
    ra, how_a = reprojection(a, nearest_px)
    rb, how_b = reprojection(b, nearest_px)
    return Comparison(len(fa), len(fb), len(both), len(ea), len(eb), len(dists), np.asarray(dists),
                      int(ea["obj_id"].nunique()), int(eb["obj_id"].nunique()), matched, ra, rb, how_a, how_b)


def report_lines(c: Comparison, name_a: str, name_b: str) -> list[str]:
    def stats(x: np.ndarray, unit: str, k: float = 1.0) -> str:
        if not x.size:
            return "none"
        return (f"mean {np.mean(x) * k:.3g} {unit}, median {np.median(x) * k:.3g}, P95 {np.percentile(x, 95) * k:.3g}, "
                f"max {np.max(x) * k:.3g} ({x.size})")

    return [
        f"frames: A {c.frames_a}, B {c.frames_b}, both {c.frames_both}",
        f"estimates paired (<= match distance): {c.paired} = {100 * c.coverage_a:.1f} % of A's {c.estimates_a}, "
        f"{100 * c.coverage_b:.1f} % of B's {c.estimates_b}",
        f"distance between paired estimates: {stats(c.distances_m, 'mm', 1e3)}",
        f"objects: A {c.objects_a}, B {c.objects_b}; A objects matched to one B object: {c.objects_matched}",
        f"reprojection A ({name_a}), to {c.reproj_how_a}: {stats(c.reproj_a, 'px')}",
        f"reprojection B ({name_b}), to {c.reproj_how_b}: {stats(c.reproj_b, 'px')}",
    ]
