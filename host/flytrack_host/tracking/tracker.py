"""The multi-target tracker: one EKF per target, NNSF association, births, deaths, orientation.

One call of `Tracker.process` per trigger frame (seed 000 section 3, Braid's defaults):
  1. predict every target by dt = (trigger_frame - previous trigger_frame) * frame period;
  2. gather the frame's finite points from all cameras (NaN/inf points are skipped and counted);
  3. associate points to targets (association.py) and update each target that got points with the
     EKF through every camera's distorted projection (Joseph form, ekf.py); a target without points
     keeps its prior as posterior;
  4. body orientation from the associated points' image angles (orientation.py);
  5. deaths: a target whose position std passes death_position_std_m is removed; so is one updated by
     fewer than birth_min_cameras cameras for death_weak_frames frames (it left, and chance false
     positives kept it going), and the younger of two targets within duplicate_distance_m for
     duplicate_frames frames (one animal tracked twice); a target without any observation for
     report_max_coast_frames frames is not reported until it has one again. These support rules run in
     Python on both paths;
  6. births from the points no target claimed (birth.py); a newborn is updated at once with them.
Targets live in stacked arrays (state (T, 6), covariance (T, 6, 6), ...) so each step is a handful of
NumPy calls whatever the number of targets and cameras; no per-point Python objects are made.
Steps 1-5 also exist in C (kernel.py, kernel/tracker_kernel.c: one call per frame instead of ~200 NumPy
calls); the tracker uses it when it is built (TrackingParams.kernel, FLYTRACK_TRACKER_KERNEL) and both
paths give the same estimates and identities. Births, clashes and merges stay in NumPy/scipy in both.
"""

from __future__ import annotations

import functools
import logging
import math
import os
from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from flytrack_host.geometry.camera import Camera
from flytrack_host.protocol import POINT_DTYPE
from flytrack_host.tracking import kernel as ckernel
from flytrack_host.tracking.association import PointSet, _assign_camera_globally, _prevent_merges, associate
from flytrack_host.tracking.birth import Birth, search_births
from flytrack_host.tracking.ekf import cv_process_noise, cv_transition, joseph_update, predict
from flytrack_host.tracking.observation import CameraArray
from flytrack_host.tracking.orientation import axes_from_normals
from flytrack_host.tracking.own_covariance import own_covariance_update
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.types import Association, Estimate, FrameBundle, FrameResult

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)
KERNEL_ENV = "FLYTRACK_TRACKER_KERNEL"
_logged: set[str] = set()
_REQUIRED_FIELDS = ("x_dist", "y_dist", "x_undist", "y_undist", "area", "orientation", "eccentricity")

# Words of a protocol point (11 x 4 bytes) holding, in order, the fields of _REQUIRED_FIELDS.
_WORDS = np.array([0, 1, 2, 3, 4, 6, 7])

STAT_KEYS = (
    "frames",  # bundles processed
    "stale_bundles",  # bundles whose trigger_frame did not advance: ignored
    "skipped_frames",  # trigger frames that never arrived (gaps between bundles)
    "points",  # finite points used
    "nonfinite_points",  # points with NaN/inf position or area: skipped
    "nonfinite_orientation",  # points with an infinite angle or eccentricity: used, without orientation
    "unknown_camera_points",  # points from a camera index the tracker has no calibration for: skipped
    "births",  # targets started (tentative)
    "birth_hypotheses",  # birth hypotheses (seed pairs) evaluated
    "birth_frames_cut",  # frames whose birth search hit birth_max_hypotheses (seeds left for later)
    "confirmed",  # targets confirmed and reported
    "deaths",  # reported targets that died
    "tentative_dropped",  # targets that died before confirmation
    "rejected_updates",  # EKF updates refused because the posterior was not finite / positive definite
    "conflicts_resolved",  # cameras where targets clashed over a point (global assignment)
    "merges_prevented",  # targets stripped of shared points by the merge-prevention rule
    "own_cov_points",  # points with their own covariance (event cameras) offered
    "own_cov_used",  # ... that updated a target with that covariance
    "own_cov_gated_out",  # ... outside every target's gate
    "own_cov_bad",  # ... whose covariance was not finite positive definite: not used
)


def select_kernel(params: TrackingParams) -> tuple[str, str]:
    """Which path a tracker with these params runs: ("c" | "numpy", why). TrackingParams.kernel wins,
    then the FLYTRACK_TRACKER_KERNEL environment variable, then C when the library is built."""
    want: str = params.kernel
    if want == "auto":
        env = os.environ.get(KERNEL_ENV, "").strip().lower()
        if env not in ("", "auto", "numpy", "c"):
            raise ValueError(f"{KERNEL_ENV} must be 'numpy' or 'c' (or unset), got {env!r}")
        want = env or "auto"
        how = f"{KERNEL_ENV}={env}" if env else "the library is built"
    else:
        how = f"TrackingParams.kernel={want!r}"
    if want == "numpy":
        return "numpy", how
    reason = ckernel.unavailable_reason()
    if reason is None:
        return "c", how
    if want == "c":
        raise ckernel.KernelUnavailable(f"{how} asks for the C tracker kernel, but {reason}")
    return "numpy", f"C kernel not available: {reason}"


class Tracker:
    """Multi-target 3D tracker. `cameras`: camera_index -> Camera (as in the rig file);
    `frame_period_s`: the trigger period (1 / fps)."""

    def __init__(self, cameras: Mapping[int, Camera], params: TrackingParams, frame_period_s: float) -> None:
        if not (math.isfinite(frame_period_s) and frame_period_s > 0):
            raise ValueError(f"frame_period_s must be a positive number of seconds, got {frame_period_s!r}")
        self.cams = CameraArray(cameras)
        self.params = params
        self.frame_period_s = float(frame_period_s)
        self.stats: dict[str, int] = dict.fromkeys(STAT_KEYS, 0)
        self._last_frame: int | None = None
        # The births of the latest frame (tentative targets started from unclaimed points).
        self.last_births: list[Birth] = []
        self._next_obj_id = 0
        p = params
        self._P0 = np.diag([p.initial_position_std_m**2] * 3 + [p.initial_velocity_std_m_s**2] * 3)
        self._r2 = p.measurement_noise_px**2
        self._R_cache: dict[int, F64] = {}
        self._death_var = p.death_position_std_m**2
        self._ok_dtypes: set[np.dtype] = set()
        self._own_cov_bundle: FrameBundle | None = None
        self._own_cov_pairs: list[tuple[int, int, int]] = []
        self._slot_edges = np.arange(self.cams.n + 1)
        self._aranges = np.arange(256)
        # Targets, stacked. obj_id is -1 while tentative.
        self._x = np.empty((0, 6))
        self._P = np.empty((0, 6, 6))
        self._area = np.empty(0)
        self._obj_id = np.empty(0, dtype=np.int64)
        self._n_obs = np.empty(0, dtype=np.int64)
        self._axis = np.empty((0, 3))
        # Consecutive frames: without any observation (coast), with fewer than birth_min_cameras
        # cameras (weak), within duplicate_distance_m of an older target (dup).
        self._coast = np.empty(0, dtype=np.int64)
        self._weak = np.empty(0, dtype=np.int64)
        self._dup = np.empty(0, dtype=np.int64)
        if self.cams.refractive:
            # The C kernel's observation model is pinhole + distortion; refraction (Camera.interface,
            # e.g. <water>) is only in the NumPy path.
            if params.kernel == "c":
                raise ckernel.KernelUnavailable(
                    "TrackingParams.kernel='c' asks for the C tracker kernel, but the calibration has a "
                    "refractive interface (<water>), which only the NumPy path models")
            self.kernel_path, why = "numpy", "the calibration has a refractive interface (<water>), which the C " \
                "kernel does not model"
        else:
            self.kernel_path, why = select_kernel(params)
        msg = f"tracker: {'C kernel' if self.kernel_path == 'c' else 'NumPy'} path ({why})"
        if msg not in _logged:  # once per process and reason
            _logged.add(msg)
            (log.warning if "does not model" in why else log.info)(msg)
        self._kern: ckernel.TrackerKernel | None = None
        if self.kernel_path == "c":
            self._kern = ckernel.TrackerKernel(self.cams, params)
            self._adopt()

    # --- public ---------------------------------------------------------------------------------
    @property
    def n_targets(self) -> int:
        """Targets alive, tentative ones included."""
        return int(self._x.shape[0])

    def process(self, bundle: FrameBundle) -> FrameResult:
        own_cov = bundle.point_cov
        if own_cov:
            # Points with their own covariance take their own update (_own_cov_update), not the frame
            # cameras' association, update and births.
            self._own_cov_bundle = bundle
            bundle = FrameBundle(bundle.trigger_frame, bundle.timestamp,
                                 {c: a for c, a in bundle.detections.items() if c not in own_cov},
                                 bundle.missing_cameras)
        else:
            self._own_cov_bundle = None
        self._own_cov_pairs = []
        frame = int(bundle.trigger_frame)
        result = FrameResult(trigger_frame=frame, timestamp=bundle.timestamp)
        self.last_births = []
        if self._last_frame is not None:
            steps = frame - self._last_frame
            if steps <= 0:
                # Time cannot run backwards in a filter: the bundle is ignored (the recorder keeps it).
                self.stats["stale_bundles"] += 1
                self._report(result, None, None, np.zeros(self.n_targets, dtype=np.intp))
                return result
            self.stats["skipped_frames"] += steps - 1
        else:
            steps = 1
        self._last_frame = frame
        self.stats["frames"] += 1
        p = self.params
        dt = steps * self.frame_period_s
        if self._kern is not None:
            self._process_c(bundle, result, dt)
            return result

        # 1. Predict.
        if self.n_targets:
            self._x, self._P = predict(
                self._x, self._P, cv_transition(dt), cv_process_noise(dt, p.motion_noise_scale)
            )

        # 2. Points.
        pts = self._gather(bundle)
        C = self.cams.n
        claimed = np.zeros(pts.n, dtype=bool)
        assign = np.full((C, self.n_targets), -1, dtype=np.intp)

        # 3. Associate and update.
        if self.n_targets and pts.n:
            uv, J, front = self.cams.project_jacobian(self._x[:, :3])
            res = associate(
                pts, C, uv, front, self._x[:, :3], self._P[:, :3, :3], self._area, self.cams.centers, p
            )
            assign = res.assign
            self.stats["conflicts_resolved"] += res.conflicts_resolved
            self.stats["merges_prevented"] += res.merges_prevented
            has = assign >= 0
            upd = np.flatnonzero(has.any(axis=0))
            if upd.size:
                claimed[assign[has]] = True
                accepted = self._update(upd, assign[:, upd], uv[:, upd], J[:, upd], pts)
                if not accepted.all():
                    assign[:, upd[~accepted]] = -1
                    upd = upd[accepted]
                if upd.size:
                    self._orient(upd, assign[:, upd], J[:, upd], pts)
        self._own_cov_update()
        n_cams = (assign >= 0).sum(axis=0)

        # 5. Deaths.
        pos_var = np.max(np.diagonal(self._P[:, :3, :3], axis1=1, axis2=2), axis=1) if self.n_targets else None
        if pos_var is not None:
            dead = ~(pos_var <= self._death_var)  # NaN dies too
            dead |= self._support_deaths(n_cams, pts.n > 0)
            if dead.any():
                assign, n_cams = self._deaths(result, dead, assign, n_cams)

        # 6. Births.
        if pts.n - int(claimed.sum()) >= p.birth_min_cameras:
            assign, n_cams = self._births(pts, ~claimed, assign, n_cams)
        self._confirm(result)
        self._report(result, assign, pts.index, n_cams)
        return result

    def _process_c(self, bundle: FrameBundle, result: FrameResult, dt: float) -> None:
        """Steps 1-5 in the C kernel (one call unless a clash or flydra's merge rule needs Python)."""
        k = self._kern
        assert k is not None
        p = self.params
        s = self.stats
        raw, n_raw = self._gather_raw(bundle, k.counts)
        T = self.n_targets
        st = k.frame(raw, n_raw, T, dt)
        s["points"] += st[ckernel.ST_POINTS]
        any_points = st[ckernel.ST_POINTS] > 0  # finite points, as pts.n on the NumPy path
        s["nonfinite_points"] += st[ckernel.ST_NONFINITE]
        s["nonfinite_orientation"] += st[ckernel.ST_NONFINITE_ORI]
        if st[ckernel.ST_RESOLVE]:
            st = self._settle(k, T, st[ckernel.ST_POINTS])
        s["conflicts_resolved"] += st[ckernel.ST_CONFLICTS]
        s["rejected_updates"] += st[ckernel.ST_REJECTED]
        self._own_cov_update()  # self._x, self._P view the kernel's buffers: updated in place
        assign = k.assign_view(T)
        n_cams = k.n_cams[:T]
        extra = self._support_deaths(n_cams, any_points)
        if st[ckernel.ST_DEAD] or extra.any():
            assign, n_cams = self._deaths(result, k.dead[:T].astype(bool) | extra, assign, n_cams)
        # The kernel's prefilter found no seed pair of unclaimed points (birth.seed_pairs' gate): then
        # the birth search would return nothing, so it is not called.
        if st[ckernel.ST_UNCLAIMED] >= p.birth_min_cameras and st[ckernel.ST_BIRTH_PAIRS]:
            pts = k.pointset()
            assign, n_cams = self._births(pts, k.claimed[: pts.n] == 0, assign, n_cams)
        self._confirm(result)
        self._report(result, assign, k.index, n_cams)

    def _settle(self, k: ckernel.TrackerKernel, T: int, N: int) -> list[int]:
        """The association decisions the kernel leaves to Python, with the NumPy path's functions:
        clashes over a point (scipy's linear_sum_assignment), or flydra's merge-prevention rule."""
        assign = k.assign_view(T)
        best = np.full(assign.shape, np.inf)  # written by the helpers, not needed here
        if self.params.exclusive_points:
            cost = k.pair_view(k.cost, N, T)
            starts = k.starts
            for c in range(self.cams.n):
                row = assign[c][assign[c] >= 0]
                if row.size > 1 and np.unique(row).size < row.size:
                    a, b = int(starts[c]), int(starts[c + 1])
                    _assign_camera_globally(c, cost[a:b], a, assign, best)
        else:
            self.stats["merges_prevented"] += _prevent_merges(assign, k.pair_view(k.d2, N, T), best)
        return k.update(T)

    def _support_deaths(self, n_cams: NDArray[np.intp], any_points: bool) -> NDArray[np.bool_]:
        """Updates the coast, weak and duplicate counters from this frame's cameras per target and
        returns who dies by death_weak_frames or as the younger of a duplicate (both paths, here).
        A frame in which no camera sent any point (the whole rig out) is no evidence that a target
        left: the coast and weak counts hold still, and the covariance rule alone applies."""
        p = self.params
        T = self.n_targets
        seen = np.asarray(n_cams[:T])
        if any_points:
            self._coast = np.where(seen > 0, 0, self._coast + 1)
            self._weak = np.where(seen >= p.birth_min_cameras, 0, self._weak + 1)
        dead = np.zeros(T, dtype=bool)
        if p.death_weak_frames:
            dead |= self._weak >= p.death_weak_frames
        if p.duplicate_distance_m > 0 and T > 1:
            X = self._x[:, :3]
            d2 = ((X[:, None, :] - X[None, :, :]) ** 2).sum(axis=2)
            # Targets are stored oldest first: each is compared with the older ones only.
            near = ((d2 < p.duplicate_distance_m**2) & _older_than(T)).any(axis=1)
            self._dup = np.where(near, self._dup + 1, 0)
            dead |= self._dup >= p.duplicate_frames
        return dead

    def _deaths(
        self, result: FrameResult, dead: NDArray[np.bool_], assign: NDArray[np.intp], n_cams: NDArray[np.intp]
    ) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        ids = self._obj_id[dead]
        result.died.extend(int(i) for i in ids[ids >= 0])
        self.stats["deaths"] += int((ids >= 0).sum())
        self.stats["tentative_dropped"] += int((ids < 0).sum())
        keep = ~dead
        self._keep(keep)
        return assign[:, keep], n_cams[keep]

    def _births(
        self, pts: PointSet, free: NDArray[np.bool_], assign: NDArray[np.intp], n_cams: NDArray[np.intp]
    ) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        search = search_births(self.cams, pts, free, self.params, self._x[:, :3] if self.n_targets else None)
        self.stats["birth_hypotheses"] += search.evaluated
        self.stats["birth_frames_cut"] += search.deferred > 0
        births = search.births
        if births:
            self.last_births = births
            assign, n_cams = self._add_births(births, pts, assign, n_cams)
        return assign, n_cams

    def _confirm(self, result: FrameResult) -> None:
        """Confirmation of targets seen in enough frames."""
        new = (self._obj_id < 0) & (self._n_obs >= self.params.confirm_min_frames)
        for k in np.flatnonzero(new):
            self._obj_id[k] = self._next_obj_id
            result.born.append(self._next_obj_id)
            self._next_obj_id += 1
            self.stats["confirmed"] += 1

    # --- steps ----------------------------------------------------------------------------------
    def _gather(self, bundle: FrameBundle) -> PointSet:
        slot_of = self.cams.slot_of
        parts: list[tuple[int, np.ndarray]] = []
        for ci, arr in bundle.detections.items():
            s = slot_of.get(ci)
            if s is None:
                self.stats["unknown_camera_points"] += len(arr)
                continue
            if len(arr):
                self._check_dtype(ci, arr)
                parts.append((s, arr))
        C = self.cams.n
        if not parts:
            e = np.empty(0)
            ei = np.empty(0, dtype=np.intp)
            return PointSet(ei, ei, e, e, e, e, e, e, e, np.zeros(C + 1, dtype=np.intp), np.empty((0, 3)),
                            np.empty((0, 2)), np.empty(0, dtype=bool), ei, 0)
        if len(parts) > 1 and any(parts[k][0] > parts[k + 1][0] for k in range(len(parts) - 1)):
            parts.sort(key=lambda sa: sa[0])
        counts = [len(a) for _, a in parts]
        slot = np.repeat(np.array([s for s, _ in parts], dtype=np.intp), counts)
        starts = np.searchsorted(slot, self._slot_edges).astype(np.intp)
        index = self._arange(slot.size) - starts[slot]
        if all(a.dtype == POINT_DTYPE and a.flags.c_contiguous for _, a in parts):
            # Fast path: a protocol point is 11 little-endian 4-byte words (f4 but for the u2 pair at
            # word 8), so the cameras' bytes joined are one (n, 11) float32 table, read with one call
            # instead of NumPy's slow structured-dtype concatenation. Words 0-7 are the fields used here,
            # in order; the table is kept as contiguous float64 rows, one per field.
            raw = parts[0][1].data if len(parts) == 1 else b"".join([a.data for _, a in parts])
            tab = np.frombuffer(raw, "<f4").reshape(-1, 11).T[_WORDS].astype(np.float64)
        else:
            cat = parts[0][1] if len(parts) == 1 else np.concatenate([a[list(_REQUIRED_FIELDS)] for _, a in parts])
            tab = np.stack([cat[f].astype(np.float64) for f in _REQUIRED_FIELDS])
        # tab rows: u, v, u_ideal, v_ideal, area, orientation, eccentricity.
        finite = np.isfinite(tab[:5]).all(axis=0)
        n_bad = slot.size - int(np.count_nonzero(finite))
        if n_bad:
            self.stats["nonfinite_points"] += n_bad
            slot, index, tab = slot[finite], index[finite], tab[:, finite]
            starts = np.searchsorted(slot, self._slot_edges).astype(np.intp)
            rank = self._arange(slot.size) - starts[slot]
            max_per_camera = int(np.diff(starts).max())
        else:
            rank, max_per_camera = index, max(counts)
        if np.isinf(tab[5:7]).any():
            inf_ori = np.isinf(tab[5:7]).any(axis=0)
            self.stats["nonfinite_orientation"] += int(inf_ori.sum())
            tab[5, inf_ori] = np.nan
        u, v, ui, vi, area, ori, ecc = tab
        self.stats["points"] += int(slot.size)
        origins = None
        if self.cams.refractive:
            origins, rays = self.cams.ray_lines(slot, ui, vi)
        else:
            rays = self.cams.ray_directions(slot, ui, vi)
        ori_ok = np.isfinite(ori) & (ecc >= self.params.min_eccentricity_for_orientation)  # NaN: False
        return PointSet(slot, index, u, v, ui, vi, area, ori, ecc, starts, rays, tab[:2].T, ori_ok,
                        rank, max_per_camera, origins)

    def _gather_raw(self, bundle: FrameBundle, counts: NDArray[np.int64]) -> tuple[bytes | None, int]:
        """For the C kernel: the cameras' protocol point bytes joined in slot order, and counts[slot]."""
        slot_of = self.cams.slot_of
        counts.fill(0)
        parts: list[tuple[int, np.ndarray]] = []
        n = 0
        for ci, arr in bundle.detections.items():
            s = slot_of.get(ci)
            if s is None:
                self.stats["unknown_camera_points"] += len(arr)
                continue
            m = len(arr)
            if m:
                self._check_dtype(ci, arr)
                if arr.dtype != POINT_DTYPE or not arr.flags.c_contiguous:
                    arr = _as_protocol(arr)
                parts.append((s, arr))
                counts[s] = m
                n += m
        if not parts:
            return None, 0
        if len(parts) > 1 and any(parts[k][0] > parts[k + 1][0] for k in range(len(parts) - 1)):
            parts.sort(key=lambda sa: sa[0])
        return b"".join([a.data for _, a in parts]), n

    def _adopt(self) -> None:
        """C path: the state arrays live in the kernel's buffers (copied in after births and deaths)."""
        if self._kern is not None:
            self._x, self._P, self._area, self._n_obs, self._axis = self._kern.store(
                self._x, self._P, self._area, self._n_obs, self._axis
            )

    def _arange(self, n: int) -> NDArray[np.intp]:
        if n > self._aranges.size:
            self._aranges = np.arange(2 * n)
        return self._aranges[:n]

    def _check_dtype(self, ci: int, arr: np.ndarray) -> None:
        dt = getattr(arr, "dtype", None)
        if dt in self._ok_dtypes:
            return
        names = dt.names if dt is not None else None
        if not names or any(f not in names for f in _REQUIRED_FIELDS):
            raise TypeError(
                f"camera {ci}: detections must be a NumPy structured array of the protocol point dtype "
                f"(fields {', '.join(_REQUIRED_FIELDS)}), got {dt!r}"
            )
        self._ok_dtypes.add(dt)

    def _R(self, m: int) -> F64:
        R = self._R_cache.get(m)
        if R is None:
            R = self._R_cache[m] = self._r2 * np.eye(m)
        return R

    def _update(
        self, upd: NDArray[np.intp], sel: NDArray[np.intp], uv: F64, J: F64, pts: PointSet
    ) -> NDArray[np.bool_]:
        """EKF update of targets `upd` with points sel (C, Tu) (-1: none); uv (C, Tu, 2) and J
        (C, Tu, 2, 3) are the observation model at the prior. Returns the accepted mask (Tu,)."""
        x, P, accepted = self._ekf(self._x[upd], self._P[upd], sel, uv, J, pts)
        self._x[upd] = x
        self._P[upd] = P
        if not accepted.all():
            self.stats["rejected_updates"] += int((~accepted).sum())
        has = sel >= 0
        # Running area of each target, from this frame's mean point area.
        n = has.sum(axis=0)
        area_sum = np.where(has, pts.area[sel], 0.0).sum(axis=0)
        a = self.params.area_smoothing
        good = accepted & (n > 0)
        self._area[upd[good]] = (1 - a) * self._area[upd[good]] + a * area_sum[good] / n[good]
        self._n_obs[upd[accepted]] += 1
        return accepted

    def _ekf(
        self, x: F64, P: F64, sel: NDArray[np.intp], uv: F64, J: F64, pts: PointSet
    ) -> tuple[F64, F64, NDArray[np.bool_]]:
        """Stack each target's observations over the cameras that have any, zero-padding the rest
        (a zero row of H with zero innovation carries no information), and run the Joseph update."""
        has = sel >= 0
        used = has.any(axis=1)
        if not used.all():
            sel, has, uv, J = sel[used], has[used], uv[used], J[used]
        Cu, Tu = sel.shape
        m = 2 * Cu
        obs = pts.uv[np.where(has, sel, 0)]  # (Cu, Tu, 2)
        z = np.where(has[..., None], obs, uv).transpose(1, 0, 2).reshape(Tu, m)
        H = np.zeros((Tu, Cu, 2, 6))
        H[..., :3] = np.where(has[..., None, None], J, 0.0).transpose(1, 0, 2, 3)
        return joseph_update(x, P, z, uv.transpose(1, 0, 2).reshape(Tu, m), H.reshape(Tu, m, 6), self._R(m))

    def _orient(self, upd: NDArray[np.intp], sel: NDArray[np.intp], J: F64, pts: PointSet) -> None:
        has = sel >= 0
        rows = np.where(has, sel, 0)
        use = has & pts.orientation_ok[rows]
        enough = np.count_nonzero(use, axis=0) >= 2
        if not enough.any():
            self._axis[upd] = np.nan
            return
        if not enough.all():
            use, rows, J = use[:, enough], rows[:, enough], J[:, enough]
        # Unit plane normals (orientation.plane_normals), zeroed where a camera does not contribute.
        theta = np.where(use, pts.orientation[rows], 0.0)  # unknown angles are NaN
        a_perp = np.stack([-np.sin(theta), np.cos(theta)], axis=-1)  # (C, Te, 2)
        n = (a_perp[..., None, :] @ J)[..., 0, :]  # J^T a_perp, (C, Te, 3)
        norm = np.sqrt(np.einsum("cti,cti->ct", n, n))
        n *= (use / np.where(norm > 0, norm, 1.0))[..., None]
        axes, ok = axes_from_normals(n.transpose(1, 0, 2), self.params.orientation_min_plane_angle_deg)
        idx = upd[enough]
        prev = self._axis[idx]
        # The sign is unobservable: keep it continuous, or along the velocity for a first estimate.
        ref = np.where(np.isfinite(prev), prev, self._x[idx, 3:])
        flip = np.einsum("ij,ij->i", axes, ref) < 0
        axes[flip] *= -1.0
        axes[~ok] = np.nan
        self._axis[upd] = np.nan
        self._axis[idx] = axes

    def _keep(self, keep: NDArray[np.bool_]) -> None:
        self._x = self._x[keep]
        self._P = self._P[keep]
        self._area = self._area[keep]
        self._obj_id = self._obj_id[keep]
        self._n_obs = self._n_obs[keep]
        self._axis = self._axis[keep]
        self._coast = self._coast[keep]
        self._weak = self._weak[keep]
        self._dup = self._dup[keep]
        self._adopt()

    def _add_births(
        self, births: list[Birth], pts: PointSet, assign: NDArray[np.intp], n_cams: NDArray[np.intp]
    ) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        B = len(births)
        C = self.cams.n
        X = np.stack([b.position for b in births])
        x0 = np.zeros((B, 6))
        x0[:, :3] = X
        P0 = np.broadcast_to(self._P0, (B, 6, 6)).copy()
        sel = np.full((C, B), -1, dtype=np.intp)
        for k, b in enumerate(births):
            sel[pts.slot[b.rows], k] = b.rows
        # The newborn's first update uses its birth points, linearised at the triangulated point.
        uv, J, _ = self.cams.project_jacobian(X)
        x, P, accepted = self._ekf(x0, P0, sel, uv, J, pts)
        self.stats["births"] += B
        self.stats["rejected_updates"] += int((~accepted).sum())
        area = np.array([pts.area[b.rows].mean() for b in births])
        self._x = np.concatenate([self._x, x])
        self._P = np.concatenate([self._P, P])
        self._area = np.concatenate([self._area, area])
        self._obj_id = np.concatenate([self._obj_id, np.full(B, -1, dtype=np.int64)])
        self._n_obs = np.concatenate([self._n_obs, accepted.astype(np.int64)])
        self._axis = np.concatenate([self._axis, np.full((B, 3), np.nan)])
        zeros = np.zeros(B, dtype=np.int64)
        self._coast = np.concatenate([self._coast, zeros])
        self._weak = np.concatenate([self._weak, zeros])
        self._dup = np.concatenate([self._dup, zeros])
        self._adopt()
        sel[:, ~accepted] = -1
        if B:
            start = self.n_targets - B
            upd = np.arange(start, self.n_targets)[accepted]
            if upd.size:
                self._orient(upd, sel[:, accepted], J[:, accepted], pts)
        return np.concatenate([assign, sel], axis=1), np.concatenate([n_cams, (sel >= 0).sum(axis=0)])

    def _report(
        self, result: FrameResult, assign: NDArray[np.intp] | None, point_index: NDArray[np.intp] | None,
        n_cams: NDArray[np.intp],
    ) -> None:
        """Estimates of the confirmed targets; with assign (C, T) and the rows' indices in their
        cameras' detection arrays, their associations too."""
        reported = self._obj_id >= 0
        if self.params.report_max_coast_frames:
            reported &= self._coast < self.params.report_max_coast_frames
        conf = np.flatnonzero(reported)
        if conf.size == 0:
            return
        # One fancy-indexed copy per array; each Estimate holds rows of these fresh arrays.
        xs, Ps, axes = self._x[conf], self._P[conf], self._axis[conf]
        ids = self._obj_id[conf].tolist()
        ncs = n_cams[conf].tolist()
        has_axis = np.isfinite(axes[:, 0]).tolist()
        result.estimates.extend(
            Estimate(obj_id=ids[i], state=xs[i], covariance=Ps[i], n_cameras=ncs[i],
                     orientation=axes[i] if has_axis[i] else None)
            for i in range(conf.size)
        )
        if assign is not None and point_index is not None:
            sub = assign[:, conf]
            cs, ks = np.nonzero(sub >= 0)
            if cs.size:
                cam_index = [self.cams.indices[c] for c in cs.tolist()]
                pidx = point_index[sub[cs, ks]].tolist()
                result.associations.extend(
                    Association(ids[k], c, p) for k, c, p in zip(ks.tolist(), cam_index, pidx, strict=True)
                )
        if self._own_cov_pairs:
            shown = set(ids)
            result.associations.extend(Association(o, c, p) for o, c, p in self._own_cov_pairs if o in shown)

    def _own_cov_update(self) -> None:
        """The update by the points with their own covariance (tracking/own_covariance.py); the pairs
        are kept by object id (deaths reorder the rows) for _report."""
        b = self._own_cov_bundle
        if b is None:
            return
        pairs, st = own_covariance_update(self._x, self._P, self.cams, b.detections, b.point_cov,
                                          scale=self.params.own_cov_scale)
        s = self.stats
        s["own_cov_points"] += st["points"]
        s["own_cov_used"] += st["used"]
        s["own_cov_gated_out"] += st["gated_out"]
        s["own_cov_bad"] += st["bad_covariance"]
        s["rejected_updates"] += st["rejected"]
        self._own_cov_pairs = [(int(self._obj_id[r]), c, p) for r, c, p in pairs if self._obj_id[r] >= 0]


@functools.lru_cache(maxsize=64)
def _older_than(n: int) -> NDArray[np.bool_]:
    """(n, n) mask of the pairs (i, j) with j < i (np.tril's k=-1), made once per target count: np.tril
    itself cost ~10 us a frame on the tracking thread. Read-only."""
    m = np.tri(n, n, -1, dtype=bool)
    m.flags.writeable = False
    return m


def _as_protocol(arr: np.ndarray) -> np.ndarray:
    """A detection array of another structured dtype as protocol points (the fields used, as float32:
    the wire format; the NumPy path reads them at their own precision)."""
    out = np.zeros(len(arr), POINT_DTYPE)
    for f in _REQUIRED_FIELDS:
        out[f] = arr[f]
    return out
