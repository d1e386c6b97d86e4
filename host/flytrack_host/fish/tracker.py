"""The per-frame tracking loop of seed 004 §4: predict each fish (smoother's forward filter), associate
silhouettes by eq. 4.1 in every camera, fit pose and shape by eq. 4.2 (SA + quasi-Newton), fishes that
share a silhouette fitted together (each in turn, with the others' surfaces explaining their share of the
contour), then fold the fit into the filter. Offline, the RTS pass smooths the whole track.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from flytrack_host.fish import fit as F
from flytrack_host.fish.association import associate
from flytrack_host.fish.claims import unclaimed
from flytrack_host.fish.shape import ShapeModel, midline_world
from flytrack_host.fish.silhouette import Silhouettes
from flytrack_host.fish.smoother import SmootherConfig, TrackFilter
from flytrack_host.fish.views import GridProjection, View, refracts

F64 = NDArray[np.float64]


@dataclass
class TrackerConfig:
    fit: F.FitConfig = field(default_factory=F.FitConfig)
    smoother: SmootherConfig = field(default_factory=SmootherConfig)
    gate_px: float = 12.0  # eq. 4.1 score per midline point above which a fish is not in that silhouette
    n_mid: int = 15  # midline points for the association
    rounds: int = 2  # passes over the fish of an occlusion group
    min_cameras: int = 1  # fit only with lines in at least this many cameras
    # a fish sharing a silhouette may be partly or wholly hidden in it: the prediction then weighs more
    # a fish touching an unmodelled one has lost the contour inside its claim: the prediction weighs more
    # a blob shared with an unmodelled fish: its contour lines farther than this from the model do not pull
    # (2 fish crossing, one unmodelled: heading max 26 -> 1 deg)
    claimed_line_cap_mm: float = 1.5
    occluded_prior_weight: float = 3.0  # 3-fish crossing: midline max 4.6 -> 3.0 px, heading max 3.6 -> 2.4 deg


@dataclass
class FrameResult:
    X: F64  # (F, 11) the fit (NaN where a fish had no silhouette)
    assoc: list[list[int]]  # [camera][fish] blob index or -1
    cost: F64
    evaluations: int
    seconds: float
    groups: list[list[int]]


def mm_per_px(view: View, X: F64) -> float:
    """Scale of a view at a point: mm per pixel (from two projected points 1 mm apart, horizontally)."""
    r = X[:3]
    uv = view.project(np.stack([r, r + np.array([0.001, 0.0, 0.0]), r + np.array([0.0, 0.001, 0.0])]))
    d = max(np.linalg.norm(uv[1] - uv[0]), np.linalg.norm(uv[2] - uv[0]))
    return 1.0 / d if np.isfinite(d) and d > 0 else 1.0


class FishTracker:
    def __init__(self, views: Sequence[View], models: Sequence[ShapeModel], X0: F64, fps: float,
                 cfg: TrackerConfig | None = None) -> None:
        self.views = list(views)
        self.models = list(models)
        self.models_mm = [F.model_in_mm(m) for m in models]
        self.cfg = cfg or TrackerConfig()
        self.dt = 1.0 / fps
        self.filters = []
        for X in np.atleast_2d(X0):
            flt = TrackFilter(1.0 / fps, self.cfg.smoother)
            flt.start(X)
            self.filters.append(flt)
        self.est = np.atleast_2d(X0).copy()
        # per fish: the frame (count of steps) of its filter's first entry; -1 for the fish the tracker
        # starts with (their start state precedes the first step and is not output)
        self.offsets = [-1] * len(self.filters)
        self.rng = np.random.default_rng(self.cfg.fit.rng_seed)
        self.frames = 0
        self.last_costs: dict[int, tuple[F.FishCost, F64]] = {}

    @property
    def n_fish(self) -> int:
        return len(self.models)

    def add_fish(self, model: ShapeModel, X: F64) -> int:
        """A fish modelled in the frame just stepped (state X in that frame) joins the tracker; it is
        predicted and fitted from the next step on. Returns its index."""
        self.models.append(model)
        self.models_mm.append(F.model_in_mm(model))
        flt = TrackFilter(self.dt, self.cfg.smoother)
        flt.start(np.asarray(X, float))
        self.filters.append(flt)
        self.est = np.vstack([self.est, np.asarray(X, float)[None]])
        self.offsets.append(self.frames - 1)
        return self.n_fish - 1

    def step(self, sils: Sequence[Silhouettes],
             claimed: Sequence[NDArray[np.uint8] | None] | None = None) -> FrameResult:
        """One frame. `claimed` (per camera, or None): pixels of fish not yet modelled (claims.py); the
        contour points of a tracked fish's blob inside them are left out of its fit."""
        t0 = time.perf_counter()
        cfg = self.cfg
        Xp = np.array([f.predict() for f in self.filters])
        s_mid = np.linspace(0.0, 1.0, cfg.n_mid)
        assoc: list[list[int]] = []
        for view, sil in zip(self.views, sils, strict=True):
            mids = []
            for f in range(self.n_fish):
                m, _ = midline_world(Xp[f], np.concatenate([[-self.models[f].nose], s_mid]))
                mids.append(view.project(m[0]))
            assoc.append(associate(mids, sil.blobs, cfg.gate_px))
        # groups: fish linked by a shared silhouette in any camera
        parent = list(range(self.n_fish))

        def find(i: int) -> int:
            while parent[i] != i:
                parent[i] = parent[parent[i]]
                i = parent[i]
            return i

        for a in assoc:
            for i in range(self.n_fish):
                for j in range(i + 1, self.n_fish):
                    if a[i] >= 0 and a[i] == a[j]:
                        parent[find(i)] = find(j)
        groups: dict[int, list[int]] = {}
        for i in range(self.n_fish):
            groups.setdefault(find(i), []).append(i)
        Xout = np.full((self.n_fish, 11), np.nan)
        costs = np.full(self.n_fish, np.nan)
        evals = 0
        for members in groups.values():
            ev, got = self._fit_group(members, Xp, assoc, sils, claimed)
            evals += ev
            for f, (X, c) in got.items():
                Xout[f] = X
                costs[f] = c
        for f, flt in enumerate(self.filters):
            flt.update(Xout[f] if np.all(np.isfinite(Xout[f])) else None)
            self.est[f] = flt.x[[0, 1, 2, 6, 7, 8, 9, 10, 11, 12, 13]]
        self.frames += 1
        return FrameResult(Xout, assoc, costs, evals, time.perf_counter() - t0, list(groups.values()))

    def _fit_group(self, members: list[int], Xp: F64, assoc: list[list[int]], sils: Sequence[Silhouettes],
                   claimed: Sequence[NDArray[np.uint8] | None] | None = None
                   ) -> tuple[int, dict[int, tuple[F64, float]]]:
        cfg = self.cfg
        r0 = Xp[members, 0:3].mean(axis=0)
        # lines of every (camera, blob) used by the group, once
        lines: dict[tuple[int, int], F.LineSet] = {}
        clipped: set[tuple[int, int]] = set()  # blobs an unmodelled fish's claim took contour points from
        for ci, a in enumerate(assoc):
            for f in members:
                j = a[f]
                if j >= 0 and (ci, j) not in lines:
                    contour = sils[ci].blobs[j].contour
                    if claimed is not None and claimed[ci] is not None:
                        n0 = len(contour)
                        contour = unclaimed(contour, claimed[ci])
                        if len(contour) < n0:
                            clipped.add((ci, j))
                    lines[(ci, j)] = F.contour_lines(self.views[ci], contour, r0,
                                                     cfg.fit.max_lines * sum(1 for g in members if a[g] == j), ci)
        fields = {}
        for ci, sil in enumerate(sils):
            used = sorted({assoc[ci][f] for f in members if assoc[ci][f] >= 0})
            if used:
                boxes = np.array([sil.blobs[j].bbox for j in used])
                pad = 40
                H, W = sil.mask.shape
                win = (max(int(boxes[:, 0].min()) - pad, 0), max(int(boxes[:, 1].min()) - pad, 0),
                       min(int((boxes[:, 0] + boxes[:, 2]).max()) + pad, W),
                       min(int((boxes[:, 1] + boxes[:, 3]).max()) + pad, H))
                fields[ci] = F.OutsideMap.build(self.views[ci], sil.fg, sil.mask, 1.0, r0, win)
        cur = {f: Xp[f].copy() for f in members}
        out: dict[int, tuple[F64, float]] = {}
        evals = 0
        seen = [f for f in members if sum(assoc[ci][f] >= 0 for ci in range(len(assoc))) >= cfg.min_cameras]
        rounds = cfg.rounds if len(seen) > 1 else 1
        for rnd in range(rounds):
            for f in seen:
                keys = [(ci, assoc[ci][f]) for ci in range(len(assoc)) if assoc[ci][f] >= 0]
                sets, others = [], []
                for key in keys:
                    ls = lines[key]
                    sets.append(ls)
                    sharers = [g for g in seen if g != f and assoc[key[0]][g] == key[1]]
                    D = None
                    if sharers:
                        D = np.min([F.line_distances(F.surface_mm(self.models_mm[g], cur[g], r0), ls)[0]
                                    for g in sharers], axis=0)
                    if key in clipped:
                        # what the claim missed of an unmodelled fish's contour must not pull: a line
                        # farther than this from the model counts as explained by something else
                        cap = np.full(len(ls.p), cfg.claimed_line_cap_mm)
                        D = cap if D is None else np.minimum(D, cap)
                    others.append(D)
                oms = []
                for ci in {k[0] for k in keys}:
                    fm = fields[ci]
                    scale = mm_per_px(self.views[ci], Xp[f])
                    view = fm.view
                    if refracts(view):  # tabulate the refracting projection around this fish, once a frame
                        centre = Xp[f][:3] - 0.5 * self.models[f].length * Xp[f][3:6]
                        view = GridProjection(view, centre)
                    oms.append(F.OutsideMap(view, fm.field, scale, r0, fm.origin, fm.beyond))
                zp = F.z_from_state(Xp[f], r0)[0]
                cost = F.make_cost(self.models_mm[f], r0, sets, others, cfg.fit, z_prior=zp, outside=oms)
                if any(o is not None for o in others):  # shared with a tracked fish or an unmodelled one
                    cost.prior_weight = max(cost.prior_weight, cfg.occluded_prior_weight)
                z0 = F.z_from_state(cur[f], r0)[0]
                levels = cfg.fit.max_levels if rnd == 0 else max(2, cfg.fit.max_levels // 3)
                z, c, n = F.fit_fish(cost, z0, cfg.fit, self.rng, sa_levels=levels)
                evals += n
                cur[f] = F.state_from_z(z, r0)[0]
                out[f] = (cur[f].copy(), c)
                self.last_costs[f] = (cost, r0)
        return evals, out

    def _stack(self, per_fish: list[tuple[F64, F64]]) -> tuple[F64, F64]:
        """Per-fish (states, covariances) from their filters onto the frames stepped: NaN before a fish's
        model was made."""
        T = self.frames
        X = np.full((T, self.n_fish, 11), np.nan)
        P = np.full((T, self.n_fish, 11, 11), np.nan)
        for f, ((xs, Ps), off) in enumerate(zip(per_fish, self.offsets, strict=True)):
            skip = max(0, -off)
            X[off + skip:, f] = xs[skip:]
            P[off + skip:, f] = Ps[skip:]
        return X, P

    def smoothed(self) -> tuple[F64, F64]:
        """(T, F, 11) smoothed states and (T, F, 11, 11) covariances over the frames stepped so far."""
        return self._stack([f.smoothed() for f in self.filters])

    def filtered(self) -> tuple[F64, F64]:
        return self._stack([f.filtered() for f in self.filters])
