"""From synchronised frames of a top and a side camera to smoothed fish tracks: background model (eq. 5.1),
model generation for every fish in the first frame (§3), tracking (§4), smoothing (eqs 4.3-4.4).

Frames come as an iterator of per-camera lists, so a video need not fit in memory.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from flytrack_host.fish.model_init import ModelError, ModelResult, generate_model, landmarks, lift, side_line
from flytrack_host.fish.shape import ShapeModel, midline_world
from flytrack_host.fish.silhouette import BackgroundModel, Silhouettes
from flytrack_host.fish.tracker import FishTracker, TrackerConfig
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

    @property
    def n_fish(self) -> int:
        return len(self.models)


def match_side_blobs(top: View, side: View, sil_top: Silhouettes, sil_side: Silhouettes,
                     zrange: tuple[float, float], margin: float = 0.25) -> list[tuple[int, int]]:
    """Pair each top-view blob with the side-view blob that sees the same fish: lift the top blob's head
    and tail onto each side blob's line and score how well the lifted fish's extent along u covers the side
    blob (IoU); the pairs are the assignment with the best total score (Hungarian). A top blob whose best
    side blob does not beat its second best by `margin` is ambiguous (two fish at different depths can
    line up so that either pairing fits) and is left out, as are top blobs without a consistent side blob
    (hidden, touching another fish)."""
    from scipy.optimize import linear_sum_assignment

    nt, ns = len(sil_top.blobs), len(sil_side.blobs)
    if nt == 0 or ns == 0:
        return []
    score = np.zeros((nt, ns))
    for jt, bt in enumerate(sil_top.blobs):
        try:
            head, _, _, tail = landmarks(bt, sil_top.mask.shape)
        except ModelError:
            continue
        for js, bs in enumerate(sil_side.blobs):
            line = side_line(bs)
            try:
                a = lift(top, side, head, line, zrange)
                b = lift(top, side, tail, line, zrange)
            except ModelError:
                continue
            ua, ub = side.project(np.stack([a, b]))[:, 0]
            lo, hi = min(ua, ub), max(ua, ub)
            x0, x1 = bs.bbox[0], bs.bbox[0] + bs.bbox[2]
            inter = max(0.0, min(hi, x1) - max(lo, x0))
            score[jt, js] = inter / max(max(hi, x1) - min(lo, x0), 1e-6)
    rows, cols = linear_sum_assignment(-score)
    pairs = []
    for jt, js in zip(rows, cols, strict=True):
        others = np.delete(score[jt], js)
        second = float(others.max()) if others.size else 0.0
        if score[jt, js] > 0.5 and score[jt, js] - second >= margin:
            pairs.append((int(jt), int(js)))
    return pairs


def track(frames: Iterable[list[NDArray[np.uint8]]], views: Sequence[View], fps: float, n_background: int = 0,
          background: Sequence[NDArray[np.uint8]] | None = None, n_fish: int | None = None,
          zrange: tuple[float, float] = (0.0, 0.4), cfg: TrackerConfig | None = None, model_wait: int = 50,
          progress: Callable[[int], None] | None = None, log: Callable[[str], None] | None = None) -> TrackResult:
    """Track the fish in `frames` (each item: one image per view, top first, then the side view used for
    the models, then any other tracking views). The first `n_background` items are fish-free frames for the
    background (alpha 0.05); `background` gives B_0 directly instead. Models are made in the first frame
    where `n_fish` fish (default: as many as are in clear view) are in clear view in the top and side; if
    no frame within `model_wait` frames of the first modelled fish shows them all, in the one showing most."""
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
    raw, seen, shared = [], [], []
    first = -1
    k = -1
    def source() -> Iterator[tuple[int, list[NDArray[np.uint8]], list[Silhouettes]]]:
        for k, imgs in enumerate(it):
            if len(imgs) != len(views):
                raise TrackingError(f"frame {k}: {len(imgs)} images for {len(views)} cameras")
            sils = [bm.segment(im) for bm, im in zip(bms, imgs, strict=True)]
            if progress:
                progress(1)
            yield k, imgs, sils

    def models_in(k: int, sils: list[Silhouettes]) -> list[ModelResult]:
        got = []
        for jt, js in match_side_blobs(views[0], views[1], sils[0], sils[1], zrange):
            try:
                got.append(generate_model(views[0], views[1], sils[0], sils[1], jt, js, zrange))
            except ModelError as exc:
                note(f"frame {k}: top blob {jt}: {exc}")
        return got

    src = source()
    queue: list[tuple[int, list[NDArray[np.uint8]], list[Silhouettes]]] = []
    waiting: list[tuple[int, list[NDArray[np.uint8]], list[Silhouettes], list[ModelResult]]] = []
    k = -1
    while True:
        item: tuple | None
        if queue:
            k, imgs, sils = queue.pop(0)
            item = (k, imgs, sils)
        else:
            item = next(src, None)
            if item is None and not (tracker is None and waiting):
                break  # (the video ended; while waiting for models it settles for the best frame below)
            if item is not None:
                k, imgs, sils = item
        if tracker is None:
            start: tuple[int, list[NDArray[np.uint8]], list[Silhouettes], list[ModelResult]] | None = None
            if item is not None:
                if not sils[0].blobs:
                    note(f"frame {k}: no fish in the top view")
                got = models_in(k, sils) if sils[0].blobs else []
                if got and (n_fish is None or len(got) >= n_fish):
                    start = (k, imgs, sils, got[: n_fish or len(got)])
                elif got or waiting:
                    waiting.append((k, imgs, sils, got))
            if start is None and waiting and (len(waiting) >= model_wait or item is None):
                # no frame shows every fish in clear view: take the frame that shows the most
                i = max(range(len(waiting)), key=lambda j: (len(waiting[j][3]), -j))
                start = waiting[i]
                queue = [(kk, ii, ss) for kk, ii, ss, _ in waiting[i + 1:]] + queue
                note(f"no frame in {waiting[0][0]}..{waiting[-1][0]} shows {n_fish} fish in clear view: "
                     f"tracking the {len(start[3])} modelled in frame {start[0]}")
                waiting = []
            if start is None:
                continue
            k, imgs, sils, got = start
            models = got
            tracker = FishTracker(views, [m.model for m in got], np.array([m.X for m in got]), fps, cfg)
            first = k
            note(f"frame {k}: {len(got)} fish modelled")
            # the model frame itself is tracked as well, starting from the model's state
        res = tracker.step(sils)
        if len(raw) % 10 == 0:  # the multi-exposure image of Figure 9
            exposure = [im.copy() for im in imgs] if not raw else [np.minimum(e, im) for e, im in
                                                                    zip(exposure, imgs, strict=True)]
        raw.append(res.X)
        seen.append(np.array([[a[f] >= 0 for a in res.assoc] for f in range(tracker.n_fish)], np.int8))
        sh = np.ones(tracker.n_fish, np.int8)
        for g in res.groups:
            for f in g:
                sh[f] = len(g)
        shared.append(sh)
    if tracker is None:
        raise TrackingError(f"no frame of {k + 1} shows {'the ' + str(n_fish) + ' ' if n_fish else ''}fish in clear "
                            "view in the top and side cameras: no model could be made")
    wall = time.perf_counter() - t_wall
    cpu = time.process_time() - t_cpu
    sm, cov = tracker.smoothed()
    fl, _ = tracker.filtered()
    raw_a = np.array(raw)
    seen_a = np.array(seen)
    lost = np.flatnonzero(~np.any(seen_a.astype(bool), axis=2).all(axis=0))
    for f in lost:
        frames_missing = int(np.sum(~np.any(seen_a[:, f].astype(bool), axis=1)))
        note(f"fish {f}: no silhouette in {frames_missing} frames (left the view or hidden); predicted there")
    return TrackResult(fps, first, [m.model for m in models], raw_a, fl, sm, cov, seen_a, np.array(shared), wall,
                       cpu, messages, models, exposure)


def midlines(X: F64, model: ShapeModel, n: int = 30) -> F64:
    """World midline points from the nose to the tail for states (T, 11): (T, n + 1, 3)."""
    s = np.concatenate([[-model.nose], np.linspace(0.0, 1.0, n)])
    m, _ = midline_world(np.atleast_2d(X), s)
    return m
