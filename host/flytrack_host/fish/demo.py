"""`flytrack fish demo`: a synthetic school rendered through a top camera and two side cameras (one only for
validation, as seed 004 §5.2 does), tracked, and scored against the ground truth."""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from flytrack_host.fish.curvature import detect_fast_starts, total_curvature
from flytrack_host.fish.pipeline import TrackResult, midlines, track
from flytrack_host.fish.render import render_sequence
from flytrack_host.fish.school import School, make_school
from flytrack_host.fish.shape import default_model
from flytrack_host.fish.tracker import TrackerConfig
from flytrack_host.fish.views import AirView, View, tank_rig

F64 = NDArray[np.float64]
GOALS = {"midline_mean_px": 1.0, "head_mm": 2.0, "heading_deg": 3.0, "association_errors": 0,
         "fish_frames_per_s": 10.0}


def _polyline_distance(pts: F64, line: F64) -> F64:
    """Distance of each point (N,2) to the polyline (M,2) (orthogonal where the foot is on a segment)."""
    a = line[:-1][None]
    b = line[1:][None]
    p = pts[:, None]
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, axis=2) / np.maximum(np.sum(ab * ab, axis=2), 1e-12), 0.0, 1.0)
    foot = a + t[..., None] * ab
    return np.linalg.norm(p - foot, axis=2).min(axis=1)


def model_frames(res: TrackResult) -> NDArray[np.int64]:
    """Per tracked fish, the index (on the result's frame axis) of the frame its model was made in."""
    mf = np.asarray(res.model_frame, np.int64)
    return mf if mf.size == res.n_fish else np.zeros(res.n_fish, np.int64)


def match_identities(res: TrackResult, school: School) -> list[int]:
    """Truth fish for each tracked fish, by head distance in the frame its model was made in (Hungarian)."""
    from scipy.optimize import linear_sum_assignment

    mf = model_frames(res)
    est = res.raw[mf, np.arange(res.n_fish), :3]
    tru = school.truth[res.first_frame + mf, :, :3]  # (F, N, 3): the truth in each fish's model frame
    D = np.linalg.norm(est[:, None] - tru, axis=2)
    D = np.where(np.isfinite(D), D, 1e3)
    r, c = linear_sum_assignment(D)
    ident = [-1] * res.n_fish
    for i, j in zip(r, c, strict=True):
        ident[i] = int(j)
    return ident


def score(res: TrackResult, school: School, views: list[View], validation: View) -> dict:
    """The issue's figures: midline error in the top view, head, heading, curvature, association errors,
    validation-camera midline error, detected fast starts. Each fish is scored from the frame its model was
    made in; the frames before are counted per fish as "not yet modelled", not as errors."""
    k0 = res.first_frame
    T = res.smoothed.shape[0]
    truth = school.truth[k0:k0 + T]
    ident = match_identities(res, school)
    mf = model_frames(res)
    true_model = default_model(school.length)
    est = res.smoothed
    top = views[0]
    mid_err, val_err, head_err, heading_err, curv_err, curv_true = [], [], [], [], [], []
    assoc_errors = 0
    per_fish = []
    for f, j in enumerate(ident):
        if j < 0:
            continue
        t0 = int(mf[f])
        Xe = est[t0:, f]
        Xt = truth[t0:, j]
        me = midlines(Xe, res.models[f])
        mt = midlines(Xt, true_model, 60)
        for view, bucket in ((top, mid_err), (validation, val_err)):
            ue = view.project(me)
            ut = view.project(mt)
            for k in range(len(Xe)):
                bucket.append(_polyline_distance(ue[k], ut[k]))
        head_err.append(np.linalg.norm(Xe[:, :3] - Xt[:, :3], axis=1) * 1000)
        heading_err.append(np.degrees(np.arccos(np.clip(np.sum(Xe[:, 3:6] * Xt[:, 3:6], axis=1), -1, 1))))
        curv_err.append(np.abs(total_curvature(Xe[:, 6:]) - total_curvature(Xt[:, 6:])))
        curv_true.append(total_curvature(Xt[:, 6:]))
        # association: the estimate is nearer another fish's head than its own
        d_all = np.linalg.norm(res.raw[t0:, f, None, :3] - truth[t0:, :, :3], axis=2)
        ok = np.isfinite(d_all).all(axis=1)
        errs = int(np.sum(np.argmin(d_all[ok], axis=1) != j))
        assoc_errors += errs
        per_fish.append({"fish": f, "truth_fish": j, "model_frame": k0 + t0, "not_yet_modelled_frames": t0,
                         "association_errors": errs, "head_mm_mean": float(np.mean(head_err[-1])),
                         "heading_deg_mean": float(np.mean(heading_err[-1]))})
    never = sorted(set(range(school.truth.shape[1])) - set(ident))
    mid = np.concatenate(mid_err)
    val = np.concatenate(val_err)
    head = np.concatenate(head_err)
    hd = np.concatenate(heading_err)
    ce = np.concatenate(curv_err)
    # fast starts: detected on the smoothed estimate (from the fish's model frame) vs the scenario's onsets
    def found_in(f: int) -> list:
        t0 = int(mf[f])
        out = detect_fast_starts(est[t0:, f, 6:], school.fps, school.length, f)
        for d in out:
            d.onset += t0
            d.peak += t0
        return out

    starts = []
    for ev in school.events:
        if ev.kind not in ("C-start", "S-start"):
            continue
        f = ident.index(ev.fish) if ev.fish in ident else -1
        found = found_in(f) if f >= 0 else []
        onset_true = ev.frame - k0
        near = [d for d in found if abs(d.onset - onset_true) <= 10]
        d = min(near, key=lambda d: abs(d.onset - onset_true)) if near else None
        starts.append({"fish": ev.fish, "kind": ev.kind, "onset_frame": onset_true,
                       "detected_kind": d.kind if d else None, "detected_onset": d.onset if d else None,
                       "frame_error": (d.onset - onset_true) if d else None})
    false_starts = 0
    for f in range(res.n_fish):
        for d in found_in(f):
            if not any(s["detected_onset"] == d.onset and ident[f] == s["fish"] for s in starts):
                false_starts += 1
    fish_frames = int(np.sum(T - mf))
    return {
        "fish": res.n_fish,
        "fish_in_school": int(school.truth.shape[1]),
        "frames": T,
        "first_frame": k0,
        "scoring": "each fish is scored from the frame its model was made in (per_fish model_frame); its frames "
                   "before are counted in not_yet_modelled_fish_frames, not as errors; never_modelled_fish: "
                   "fish of the school that never got a model",
        "fish_frames": fish_frames,
        "not_yet_modelled_fish_frames": int(np.sum(mf)),
        "never_modelled_fish": never,
        "per_fish": per_fish,
        "midline_mean_px": float(np.mean(mid)),
        "midline_max_px": float(np.max(mid)),
        "head_mm_mean": float(np.mean(head)),
        "head_mm_max": float(np.max(head)),
        "heading_deg_mean": float(np.mean(hd)),
        "heading_deg_max": float(np.max(hd)),
        "curvature_error_mean_per_m": float(np.mean(ce)),
        "curvature_total_mean_per_m": float(np.mean(np.concatenate(curv_true))),
        "association_errors": assoc_errors,
        "validation_midline_mean_px": float(np.mean(val)),
        "validation_midline_max_px": float(np.max(val)),
        "fish_frames_per_s": float(fish_frames / res.seconds),
        "fish_frames_per_cpu_s": float(fish_frames / max(res.cpu_seconds, 1e-9)),
        "max_occlusion_group": int(res.shared.max()),
        "occluded_fish_frames": int(np.sum(res.shared > 1)),
        "fast_starts": starts,
        "false_fast_starts": false_starts,
    }


def run_demo(n_fish: int = 4, frames: int = 200, seed: int = 0, top_size: tuple[int, int] = (1280, 1024),
             side_size: tuple[int, int] = (512, 384), out: Path | None = None, noise: float = 3.0,
             progress: bool = False, plots: bool = True, cross_frame: int | None = None,
             top_zoom: float = 1.0, cfg: TrackerConfig | None = None, water: float | None = None,
             incremental: bool = True, claims: bool = True, track_fish: int | None = None,
             blas_threads: int | None = 1) -> dict:
    """Render, track and score a synthetic school of `n_fish`. `track_fish` caps the fish that get a model
    (the others stay unmodelled silhouettes: the case the claims are for); `incremental`, `claims`,
    `blas_threads` (None: the BLAS library's default): see pipeline.track."""
    cv2.setNumThreads(1)  # one core, as the figure is quoted
    school = make_school(n_fish, frames, seed=seed, cross_frame=cross_frame)
    rig = tank_rig(top_size, side_size, top_zoom=top_zoom, water=water)
    views = [AirView(rig["top"]), AirView(rig["side"])]
    validation = AirView(rig["end"])
    model = default_model(school.length)
    rng = np.random.default_rng(seed + 100)
    t0 = time.perf_counter()
    n_bg = 5
    imgs = render_sequence(views + [validation], model, school.truth, rng, n_background=n_bg, noise=noise)
    render_s = time.perf_counter() - t0
    stream = ([imgs[0][k], imgs[1][k]] for k in range(len(imgs[0])))
    bar = None
    if progress:
        from rich.progress import Progress

        bar = Progress(transient=True)
        bar.start()
        task = bar.add_task("tracking", total=frames)
    try:
        res = track(stream, views, school.fps, n_background=n_bg, n_fish=track_fish or n_fish, cfg=cfg,
                    incremental=incremental, claims=claims, blas_threads=blas_threads,
                    progress=(lambda n: bar.advance(task, n)) if bar else None)
    finally:
        if bar:
            bar.stop()
    summary = score(res, school, views, validation)
    summary["render_seconds"] = render_s
    summary["blas_threads"] = blas_threads  # while tracking (None: the library's default)
    summary["events"] = [asdict(e) for e in school.events]
    summary["goals"] = GOALS
    summary["messages"] = res.messages
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        from flytrack_host.fish.io import write_tracks

        write_tracks(out / "tracks.h5", res, [v.name for v in views])
        if plots:
            from flytrack_host.fish.plots import write_plots

            write_plots(out, res, views)
    return summary


def goals_met(summary: dict) -> dict[str, bool]:
    starts_ok = all(s["detected_kind"] == s["kind"] and abs(s["frame_error"]) <= 3
                    for s in summary["fast_starts"]) if summary["fast_starts"] else True
    return {
        "every fish modelled": summary["fish"] == summary.get("fish_in_school", summary["fish"]),
        "midline mean < 1 px": summary["midline_mean_px"] < 1.0,
        "head < 2 mm": summary["head_mm_mean"] < 2.0,
        "heading < 3 deg": summary["heading_deg_mean"] < 3.0,
        "no association error": summary["association_errors"] == 0,
        ">= 10 fish-frames/s per core": summary["fish_frames_per_cpu_s"] >= 10.0,
        "fast starts at the right frames": starts_ok,
    }


def dump(summary: dict, path: Path) -> None:
    path.write_text(json.dumps(summary, indent=2))
