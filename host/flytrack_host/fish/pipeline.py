"""From synchronised frames of a top and a side camera to smoothed fish tracks: background model (eq. 5.1),
model generation for each fish in its own first clear frame (§3), tracking (§4), smoothing (eqs 4.3-4.4).

Frames come as an iterator of per-camera lists, so a video need not fit in memory.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from flytrack_host.fish.claims import Claims
from flytrack_host.fish.model_init import ModelError, ModelResult, generate_model, landmarks, lift, side_line
from flytrack_host.fish.shape import ShapeModel, midline_world
from flytrack_host.fish.silhouette import BackgroundModel, Blob, Silhouettes
from flytrack_host.fish.tracker import FishTracker, TrackerConfig, mm_per_px
from flytrack_host.fish.views import View

F64 = NDArray[np.float64]
Frames = Sequence[NDArray[np.uint8]]


class TrackingError(ValueError):
    """The input cannot be tracked (no fish to model, views that do not fit): one clear message."""


@dataclass
class TrackResult:
    fps: float
    first_frame: int  # index (after the background frames) of the frame the models were made in
    models: list[ShapeModel]
    raw: F64  # (T, F, 11) per-frame fits (NaN: no silhouette)
    filtered: F64
    smoothed: F64
    covariance: F64  # (T, F, 11, 11) smoothed
    seen: NDArray[np.int8]  # (T, F, C) 1 where the fish had a silhouette in camera c
    shared: NDArray[np.int8]  # (T, F) size of the occlusion group the fish was fitted in
    seconds: float  # wall time of segmentation + tracking
    cpu_seconds: float
    messages: list[str] = field(default_factory=list)
    model_results: list[ModelResult] = field(default_factory=list)
    exposure: list[NDArray[np.uint8]] = field(default_factory=list)  # per view: darkest of every 10th frame
    exposure_every: int = 10
    # per fish: index (on the frame axis above) of the frame its model was made in; before it the fish was
    # not yet modelled (NaN states, seen 0), which is not an error
    model_frame: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def n_fish(self) -> int:
        return len(self.models)


def match_side_blobs(top: View, side: View, sil_top: Silhouettes, sil_side: Silhouettes,
                     zrange: tuple[float, float], top_blobs: Sequence[int] | None = None,
                     side_blobs: Sequence[int] | None = None, max_error: float = 0.08,
                     margin: float = 0.05) -> list[tuple[int, int]]:
    """Pair top-view blobs with the side-view blobs that see the same fish. The top blob's nose and tail are
    lifted onto each side blob's line (the seed's l_m, l_r) and projected into the side view; the pairing
    error is how far the projected nose and tail fall from the two ends of the side blob along u (px). The
    pairs are the assignment with the least total error (Hungarian). A pair is kept only if its error is
    under `max_error` of the side blob's extent and every other candidate (other side blobs for the top
    blob, other top blobs for the side blob) is worse by at least `margin` of it: two fish at different
    depths can line up so that either pairing fits, and such an unclear pairing waits. Top blobs without a
    consistent side blob (hidden, touching another fish) are left out.

    `top_blobs`, `side_blobs`: the candidate blobs (default all): blobs already explained by tracked fish
    are left out by the caller, which also settles pairings that are ambiguous only with a tracked fish.
    (An extent overlap (IoU) of the lifted fish and the side blob is lenient: a fish whose side view is
    shorter than another's and inside it scores nearly as high, so pairs of fish with mirrored headings
    were ambiguous for whole runs; the two ends separate them by several px.)"""
    from scipy.optimize import linear_sum_assignment

    ts = list(range(len(sil_top.blobs))) if top_blobs is None else list(top_blobs)
    ss = list(range(len(sil_side.blobs))) if side_blobs is None else list(side_blobs)
    if not ts or not ss:
        return []
    big = 1e6
    err = np.full((len(ts), len(ss)), big)
    lines = [side_line(sil_side.blobs[js]) for js in ss]
    ext = np.array([np.ptp(sil_side.blobs[js].contour[:, 0]) if len(sil_side.blobs[js].contour) else 0.0
                    for js in ss])
    for it, jt in enumerate(ts):
        try:
            _, _, nose, tail = landmarks(sil_top.blobs[jt], sil_top.mask.shape)
        except ModelError:
            continue
        for i_s, js in enumerate(ss):
            bs = sil_side.blobs[js]
            if ext[i_s] <= 0:
                continue
            try:
                a = lift(top, side, nose, lines[i_s], zrange)
                b = lift(top, side, tail, lines[i_s], zrange)
            except ModelError:
                continue
            ua, ub = side.project(np.stack([a, b]))[:, 0]
            if not (np.isfinite(ua) and np.isfinite(ub)):
                continue
            x0, x1 = float(bs.contour[:, 0].min()), float(bs.contour[:, 0].max())
            err[it, i_s] = abs(min(ua, ub) - x0) + abs(max(ua, ub) - x1)
    rows, cols = linear_sum_assignment(err)
    pairs = []
    for it, i_s in zip(rows, cols, strict=True):
        e = err[it, i_s]
        if e >= big or e > max_error * ext[i_s]:
            continue
        rivals = np.concatenate([np.delete(err[it], i_s), np.delete(err[:, i_s], it)])
        if rivals.size and float(rivals.min()) - e < margin * ext[i_s]:
            continue
        pairs.append((ts[it], ss[i_s]))
    return pairs


def track(frames: Iterable[list[NDArray[np.uint8]]], views: Sequence[View], fps: float, n_background: int = 0,
          background: Sequence[NDArray[np.uint8]] | None = None, n_fish: int | None = None,
          zrange: tuple[float, float] = (0.0, 0.4), cfg: TrackerConfig | None = None, model_retry: int = 5,
          progress: Callable[[int], None] | None = None, log: Callable[[str], None] | None = None,
          incremental: bool = True, claims: bool = True, max_area_ratio: float = 1.35,
          blas_threads: int | None = 1) -> TrackResult:
    """Track the fish in `frames` (each item: one image per view, top first, then the side view used for
    the models, then any other tracking views). The first `n_background` items are fish-free frames for the
    background (alpha 0.05); `background` gives B_0 directly instead.

    Models are made incrementally (seed 004 §3 per fish): tracking starts in the first frame where any fish
    is in clear view in the top and side views, and in every later frame the blobs that no tracked fish
    explains (in the top and in the side view) are paired and each fish found there in clear view gets its
    model in that frame and joins the running tracker, until `n_fish` are tracked (default: no limit). A
    candidate that gave no model is tried again after `model_retry` frames (model generation is costly).
    A candidate whose top-view area (mm^2, at its depth) is over `max_area_ratio` times that of one fish
    (the median of the fish tracked alone in their blobs, or of the candidates) is several fish and waits.
    Blobs that no tracked fish explains are claimed (claims.py) until their fish is modelled, and tracked
    fish do not fit the contour inside a claim when such a blob merges with theirs (`claims=False`: off).
    `incremental=False` models only in the first frame (for comparison).

    `blas_threads`: BLAS threads while tracking (None: the library's default). The fit's matrices are tiny
    (tens of rows), so more threads only spin: with OpenBLAS's default two threads on this 2-core machine the
    8-fish demo took 189 CPU s (and 1.9x the wall time) for the same result as 114 CPU s on one thread."""
    if blas_threads is None:
        return _track(frames, views, fps, n_background, background, n_fish, zrange, cfg, model_retry, progress,
                      log, incremental, claims, max_area_ratio)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=blas_threads, user_api="blas"):
        return _track(frames, views, fps, n_background, background, n_fish, zrange, cfg, model_retry, progress,
                      log, incremental, claims, max_area_ratio)


def _track(frames: Iterable[list[NDArray[np.uint8]]], views: Sequence[View], fps: float, n_background: int,
           background: Sequence[NDArray[np.uint8]] | None, n_fish: int | None, zrange: tuple[float, float],
           cfg: TrackerConfig | None, model_retry: int, progress: Callable[[int], None] | None,
           log: Callable[[str], None] | None, incremental: bool, claims: bool, max_area_ratio: float) -> TrackResult:
    messages: list[str] = []

    def note(msg: str) -> None:
        messages.append(msg)
        if log:
            log(msg)

    if len(views) < 2:
        raise TrackingError("fish tracking needs a top view and a side view")
    it: Iterator[list[NDArray[np.uint8]]] = iter(frames)
    bms: list[BackgroundModel] | None = None
    if background is not None:
        bms = [BackgroundModel(b) for b in background]
    for _ in range(n_background):
        imgs = next(it, None)
        if imgs is None:
            raise TrackingError(f"the videos end within the {n_background} background frames")
        if bms is None:
            bms = [BackgroundModel(im) for im in imgs]
        else:
            for bm, im in zip(bms, imgs, strict=True):
                bm.update(im)
    if bms is None:
        raise TrackingError("no background: give fish-free frames (--background-frames) or a background image")
    for bm in bms:
        bm.fish_present()
    t_wall = time.perf_counter()
    t_cpu = time.process_time()
    tracker: FishTracker | None = None
    exposure: list[NDArray[np.uint8]] = []
    models: list[ModelResult] = []
    model_frame: list[int] = []  # per fish: index (from `first`) of the frame its model was made in
    raw: list[F64] = []
    seen: list[NDArray[np.int8]] = []
    shared: list[NDArray[np.int8]] = []
    first = -1
    k = -1
    next_try = 0  # frame from which unexplained blobs are tried again after a try that gave no model
    no_fish = 0
    claim_sets: list[Claims] = []

    def models_in(k: int, sils: list[Silhouettes], top_blobs: list[int] | None = None,
                  side_blobs: list[int] | None = None, ref_area: float | None = None) -> list[ModelResult]:
        got = []
        for jt, js in match_side_blobs(views[0], views[1], sils[0], sils[1], zrange, top_blobs, side_blobs):
            try:
                got.append(generate_model(views[0], views[1], sils[0], sils[1], jt, js, zrange))
            except ModelError as exc:
                note(f"frame {k}: top blob {jt}: {exc}")
        # several fish lying along each other can make one thin blob that passes the clear-view test: in a
        # school of similar fish such a blob has a larger top-view area (mm^2, at its depth) than one fish
        areas = [top_area_mm2(views[0], sils[0].blobs[m.blobs[0]], m.X) for m in got]
        ref = ref_area if ref_area is not None else (float(np.median(areas)) if len(areas) >= 3 else None)
        if ref is None:
            return got
        keep = []
        for m, a in zip(got, areas, strict=True):
            if a > max_area_ratio * ref:
                note(f"frame {k}: top blob {m.blobs[0]}: {a / ref:.2f} x the top-view area of one fish: several "
                     "fish touching, not modelled")
            else:
                keep.append(m)
        return keep

    for k, imgs in enumerate(it):
        if len(imgs) != len(views):
            raise TrackingError(f"frame {k}: {len(imgs)} images for {len(views)} cameras")
        sils = [bm.segment(im) for bm, im in zip(bms, imgs, strict=True)]
        if progress:
            progress(1)
        if tracker is None:
            if not sils[0].blobs:
                no_fish += 1
                continue
            got = models_in(k, sils)[: n_fish or None]
            if not got:
                continue
            if no_fish:
                note(f"{no_fish} frames with no fish in the top view before the first model")
            models = list(got)
            tracker = FishTracker(views, [m.model for m in got], np.array([m.X for m in got]), fps, cfg)
            first = k
            model_frame = [0] * len(got)
            note(f"frame {k}: {len(got)} fish modelled")
            # the model frame itself is tracked as well, starting from the model's state
        t = k - first
        if claims and not claim_sets:
            claim_sets = [Claims(s_.mask.shape) for s_ in sils]
        res = tracker.step(sils, [c.mask(k) for c in claim_sets] if claim_sets else None)
        if t % 10 == 0:  # the multi-exposure image of Figure 9
            exposure = [im.copy() for im in imgs] if t == 0 else [np.minimum(e, im) for e, im in
                                                                   zip(exposure, imgs, strict=True)]
        X = res.X
        sn = np.array([[a[f] >= 0 for a in res.assoc] for f in range(tracker.n_fish)], np.int8)
        sh = np.ones(tracker.n_fish, np.int8)
        for g in res.groups:
            for f in g:
                sh[f] = len(g)
        want = n_fish is None or tracker.n_fish < n_fish
        new: list[ModelResult] = []
        if incremental and want and k >= next_try:
            new = _new_fish(k, sils, res.assoc, tracker, models_in)
            if n_fish is not None:
                new = new[: n_fish - tracker.n_fish]
            if not new:
                next_try = k + model_retry
        for m in new:
            tracker.add_fish(m.model, m.X)
            models.append(m)
            model_frame.append(t)
            X = np.vstack([X, m.X[None]])
            sn = np.vstack([sn, np.ones((1, len(views)), np.int8)])
            sh = np.append(sh, np.int8(1))
            note(f"frame {k}: fish {tracker.n_fish - 1} modelled (in clear view in the top and side views)")
        for ci, cs in enumerate(claim_sets):
            used = [m.blobs[ci] for m in new] if ci < 2 else []
            cs.update(k, sils[ci].blobs, _unexplained(views[ci], sils[ci], res.assoc[ci], tracker, used), used)
        raw.append(X)
        seen.append(sn)
        shared.append(sh)
    if tracker is None:
        raise TrackingError(f"no frame of {k + 1} shows {'the ' + str(n_fish) + ' ' if n_fish else ''}fish in clear "
                            "view in the top and side cameras: no model could be made")
    if n_fish is not None and tracker.n_fish < n_fish:
        note(f"only {tracker.n_fish} of {n_fish} fish were seen in clear view in the top and side cameras: "
             f"tracking those {tracker.n_fish} (the first modelled in frame {first})")
    wall = time.perf_counter() - t_wall
    cpu = time.process_time() - t_cpu
    sm, cov = tracker.smoothed()
    fl, _ = tracker.filtered()
    nf = tracker.n_fish
    raw_a = np.full((len(raw), nf, 11), np.nan)
    seen_a = np.zeros((len(raw), nf, len(views)), np.int8)
    shared_a = np.zeros((len(raw), nf), np.int8)
    for i, (x, s_, h_) in enumerate(zip(raw, seen, shared, strict=True)):
        raw_a[i, : len(x)] = x
        seen_a[i, : len(s_)] = s_
        shared_a[i, : len(h_)] = h_
    mf = np.array(model_frame, np.int64)
    for f in range(nf):
        n_missing = int(np.sum(~np.any(seen_a[mf[f]:, f].astype(bool), axis=1)))
        if n_missing:
            note(f"fish {f}: no silhouette in {n_missing} frames (left the view or hidden); predicted there")
    return TrackResult(fps, first, [m.model for m in models], raw_a, fl, sm, cov, seen_a, shared_a, wall,
                       cpu, messages, models, exposure, model_frame=mf)


def top_area_mm2(view: View, blob: Blob, X: F64) -> float:
    """A top-view blob's area in mm^2 at the depth of state X (so near and far fish compare)."""
    return float(blob.area) * mm_per_px(view, X) ** 2


def _unexplained(view: View, sil: Silhouettes, assoc: list[int], tracker: FishTracker, used: list[int]) -> list[int]:
    """Blobs of one camera that no tracked fish explains: not associated with one, not just modelled, and
    with no tracked fish's midline inside (its association may have failed this frame)."""
    taken = set(assoc) | set(used)
    free = [j for j in range(len(sil.blobs)) if j not in taken]
    if not free:
        return free
    H, W = sil.labels.shape
    inside: set[int] = set()
    for f in range(tracker.n_fish):
        m, _ = midline_world(tracker.est[f], np.linspace(0.0, 1.0, 7))
        uv = np.round(view.project(m[0])).astype(int)
        ok = np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        inside.update(int(v) for v in sil.labels[uv[ok, 1], uv[ok, 0]])
    return [j for j in free if sil.blobs[j].label not in inside]


def _new_fish(k: int, sils: list[Silhouettes], assoc: list[list[int]], tracker: FishTracker,
              models_in: Callable[..., list[ModelResult]]) -> list[ModelResult]:
    """Models of fish in clear view in blobs that no tracked fish explains (in the top and the side view),
    made in this frame. A model whose head is within 0.3 body lengths of a tracked fish's is the same fish
    (its own silhouette was not associated this frame) and is dropped."""
    free_top = [j for j in range(len(sils[0].blobs)) if j not in set(assoc[0])]
    free_side = [j for j in range(len(sils[1].blobs)) if j not in set(assoc[1])]
    if not free_top or not free_side:
        return []
    alone = [j for j in set(assoc[0]) if j >= 0 and assoc[0].count(j) == 1]
    ref = None
    if alone:
        ref = float(np.median([top_area_mm2(tracker.views[0], sils[0].blobs[j], tracker.est[assoc[0].index(j)])
                               for j in alone]))
    out = []
    for m in models_in(k, sils, free_top, free_side, ref):
        d = np.linalg.norm(tracker.est[:, :3] - m.X[:3], axis=1)
        if d.size and float(d.min()) < 0.3 * m.model.length:
            continue
        out.append(m)
    return out


def midlines(X: F64, model: ShapeModel, n: int = 30) -> F64:
    """World midline points from the nose to the tail for states (T, 11): (T, n + 1, 3)."""
    s = np.concatenate([[-model.nose], np.linspace(0.0, 1.0, n)])
    m, _ = midline_world(np.atleast_2d(X), s)
    return m
