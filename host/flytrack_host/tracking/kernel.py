"""ctypes binding to libflytrack_tracker_kernel, the C version of the tracker's per-frame hot path.

The library (host/flytrack_host/tracking/kernel/tracker_kernel.c) gathers a frame's points, predicts,
projects, gates, associates and updates all targets in one call; `Tracker` uses it when it is built
and falls back to the NumPy path otherwise (tracker.py says which). Every buffer is a NumPy array owned
here and handed over once as a pointer in the `Buffers` struct: a frame allocates nothing.
Where the library is: flytrack_host.util.native (`host/flytrack_host/tracking/kernel/` under
$FLYTRACK_BUILD_DIR, else under <repo>/build; built by `make cbuild`).
"""

from __future__ import annotations

import ctypes
import sys

import numpy as np
from numpy.typing import NDArray

from flytrack_host.tracking.association import PointSet
from flytrack_host.tracking.birth import _SEED_GATE
from flytrack_host.tracking.observation import CameraArray
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.util.native import NativeLibraryError, library_path, load_library

LIB = "flytrack_tracker_kernel"
SUBDIR = "host/flytrack_host/tracking/kernel"
ABI_VERSION = 3
CAM_STRIDE = 52  # FTK_CAM_STRIDE: doubles per camera in the packed table

# Indices of the stats array (enum in tracker_kernel.h).
(ST_POINTS, ST_NONFINITE, ST_NONFINITE_ORI, ST_MAX_PER_CAMERA, ST_CONFLICTS, ST_RESOLVE, ST_UPDATED,
 ST_REJECTED, ST_DEAD, ST_UNCLAIMED, ST_BIRTH_PAIRS, ST_COUNT) = range(12)
_ERRORS = {-1: "invalid argument", -2: "buffer capacity exceeded"}


class KernelUnavailable(NativeLibraryError):
    """The C library is missing or does not match these bindings."""


class KernelParams(ctypes.Structure):
    """Mirror of ftk_params."""

    _fields_ = [(name, ctypes.c_double) for name in (
        "gate_px", "area_gate_ratio", "min_area_px", "max_mahalanobis", "r2", "motion_noise_scale",
        "death_var", "area_smoothing", "min_eccentricity", "min_plane_tan_half", "birth_seed_gate_px",
    )] + [("exclusive_points", ctypes.c_int64), ("birth_min_cameras", ctypes.c_int64)]


_TARGET_PTRS = ("x", "P", "area", "n_obs", "axis")
_POINT_PTRS = ("slot", "index", "rank", "starts", "uv", "uvi", "parea", "ori", "ecc", "rays", "ori_ok", "claimed")
_PAIR_PTRS = ("cost", "d2")
_CAM_TARGET_PTRS = ("puv", "J", "front", "assign")
_PER_TARGET_PTRS = ("n_cams", "dead")


class Buffers(ctypes.Structure):
    """Mirror of ftk_buffers."""

    _fields_ = [(n, ctypes.c_int64) for n in ("n_cameras", "t_cap", "n_cap", "scratch_len")] + [
        (n, ctypes.c_void_p)
        for n in _TARGET_PTRS + _POINT_PTRS + _PAIR_PTRS + _CAM_TARGET_PTRS + _PER_TARGET_PTRS + ("scratch",)
    ]


_lib: ctypes.CDLL | None = None


def load() -> ctypes.CDLL:
    """Loads the library once; raises KernelUnavailable with the fix when it is missing."""
    global _lib
    if _lib is not None:
        return _lib
    if sys.byteorder != "little":
        raise KernelUnavailable("the tracker kernel reads little-endian protocol points; this host is big-endian")
    path = library_path(LIB, SUBDIR)
    lib = load_library(LIB, SUBDIR, "tracker kernel", KernelUnavailable)
    lib.ftk_abi_version.restype = ctypes.c_int
    lib.ftk_sizeof_params.restype = ctypes.c_size_t
    lib.ftk_sizeof_buffers.restype = ctypes.c_size_t
    if (lib.ftk_abi_version() != ABI_VERSION or lib.ftk_sizeof_params() != ctypes.sizeof(KernelParams)
            or lib.ftk_sizeof_buffers() != ctypes.sizeof(Buffers)):
        raise KernelUnavailable(f"{path} does not match these bindings: rebuild with `make cbuild`")
    vp, i64 = ctypes.c_void_p, ctypes.c_int64
    lib.ftk_scratch_len.restype = i64
    lib.ftk_scratch_len.argtypes = [i64, i64]
    for name in ("ftk_frame", "ftk_associate"):
        fn = getattr(lib, name)
        fn.restype = ctypes.c_int
        fn.argtypes = [vp, vp, vp, vp, vp, i64, ctypes.c_double, vp]
    lib.ftk_update.restype = ctypes.c_int
    lib.ftk_update.argtypes = [vp, vp, vp, i64, vp]
    _lib = lib
    return lib


def unavailable_reason() -> str | None:
    """None when the kernel can be used, else why not."""
    try:
        load()
    except KernelUnavailable as exc:
        return str(exc)
    return None


def _ptr(a: np.ndarray) -> int:
    return a.ctypes.data


class TrackerKernel:
    """The C kernel with its buffers for one tracker (one camera rig, one parameter set)."""

    def __init__(self, cams: CameraArray, params: TrackingParams) -> None:
        self.lib = load()
        self.C = C = cams.n
        table = np.zeros((C, CAM_STRIDE))
        for s, cam in enumerate(cams.cameras):
            K = cam.Kd  # the distortion's K; P's own K is in the ray and projection matrices
            table[s, 0:9] = cam.R.ravel()
            table[s, 9:12] = cam.t
            table[s, 12:17] = (K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2])
            table[s, 17:22] = cam.dist
            table[s, 22:25] = cams.centers[s]
            table[s, 25:34] = cams._ray_B[s].ravel()
            table[s, 34:46] = cams.P[s].ravel()
            table[s, 46:50] = cams._dfA[s, 0].ravel()  # distortion frame (identity for OpenCV's model)
            table[s, 50:52] = cams._dfb[s, 0]
        self._cams = table
        p = params
        self._params = KernelParams(
            gate_px=p.gate_px, area_gate_ratio=p.area_gate_ratio, min_area_px=p.min_area_px,
            max_mahalanobis=p.max_mahalanobis, r2=p.measurement_noise_px**2,
            motion_noise_scale=p.motion_noise_scale, death_var=p.death_position_std_m**2,
            area_smoothing=p.area_smoothing, min_eccentricity=p.min_eccentricity_for_orientation,
            min_plane_tan_half=float(np.tan(np.radians(p.orientation_min_plane_angle_deg) / 2.0)),
            # birth.seed_pairs' gate (Sampson distance <= _SEED_GATE * threshold); the margin makes
            # rounding differences err on the side of running the NumPy birth search.
            birth_seed_gate_px=_SEED_GATE * p.birth_max_reproj_px * (1.0 + 1e-9) + 1e-9,
            exclusive_points=int(p.exclusive_points), birth_min_cameras=p.birth_min_cameras,
        )
        self._buf = Buffers(n_cameras=C)
        self.stats = np.zeros(ST_COUNT, dtype=np.int64)
        self.counts = np.zeros(C, dtype=np.int64)
        self.t_cap = self.n_cap = 0
        self._alloc(t_cap=8, n_cap=64)
        self._args = (ctypes.addressof(self._params), _ptr(self._cams), ctypes.addressof(self._buf))
        self._counts_ptr = _ptr(self.counts)
        self._stats_ptr = _ptr(self.stats)

    # --- buffers ----------------------------------------------------------------------------------
    def _alloc(self, t_cap: int, n_cap: int) -> None:
        """(Re)allocate for at least t_cap targets and n_cap points, keeping the targets' state."""
        C = self.C
        t_new, n_new = t_cap > self.t_cap, n_cap > self.n_cap
        if t_new:
            old = [getattr(self, n, None) for n in _TARGET_PTRS]
            self.x = np.zeros((t_cap, 6))
            self.P = np.zeros((t_cap, 6, 6))
            self.area = np.zeros(t_cap)
            self.n_obs = np.zeros(t_cap, dtype=np.int64)
            self.axis = np.full((t_cap, 3), np.nan)
            for name, a in zip(_TARGET_PTRS, old, strict=True):
                if a is not None:
                    getattr(self, name)[: a.shape[0]] = a
            self.puv = np.zeros(C * t_cap * 2)
            self.J = np.zeros(C * t_cap * 6)
            self.front = np.zeros(C * t_cap, dtype=np.uint8)
            self.assign = np.zeros(C * t_cap, dtype=np.int64)
            self.n_cams = np.zeros(t_cap, dtype=np.int64)
            self.dead = np.zeros(t_cap, dtype=np.uint8)
            self.scratch = np.zeros(int(self.lib.ftk_scratch_len(C, t_cap)))
            self.t_cap = t_cap
        if n_new:
            self.slot = np.zeros(n_cap, dtype=np.int64)
            self.index = np.zeros(n_cap, dtype=np.int64)
            self.rank = np.zeros(n_cap, dtype=np.int64)
            self.starts = np.zeros(C + 1, dtype=np.int64)
            self.uv = np.zeros((n_cap, 2))
            self.uvi = np.zeros((n_cap, 2))
            self.parea = np.zeros(n_cap)
            self.ori = np.zeros(n_cap)
            self.ecc = np.zeros(n_cap)
            self.rays = np.zeros((n_cap, 3))
            self.ori_ok = np.zeros(n_cap, dtype=np.uint8)
            self.claimed = np.zeros(n_cap, dtype=np.uint8)
            self.n_cap = n_cap
        if t_new or n_new:
            self.cost = np.zeros(self.n_cap * self.t_cap)
            self.d2 = np.zeros(self.n_cap * self.t_cap)
        b = self._buf
        b.t_cap, b.n_cap, b.scratch_len = self.t_cap, self.n_cap, self.scratch.size
        for name in _TARGET_PTRS + _POINT_PTRS + _PAIR_PTRS + _CAM_TARGET_PTRS + _PER_TARGET_PTRS + ("scratch",):
            setattr(b, name, _ptr(getattr(self, name)))

    def store(self, x: np.ndarray, P: np.ndarray, area: np.ndarray, n_obs: np.ndarray,
              axis: np.ndarray) -> tuple[np.ndarray, ...]:
        """Copy the targets' state in (growing the buffers when needed); returns the views the tracker
        keeps as its state arrays."""
        T = x.shape[0]
        if T > self.t_cap:
            self._alloc(max(T, 2 * self.t_cap), self.n_cap)
        self.x[:T], self.P[:T], self.area[:T], self.n_obs[:T], self.axis[:T] = x, P, area, n_obs, axis
        return self.views(T)

    def views(self, T: int) -> tuple[np.ndarray, ...]:
        return self.x[:T], self.P[:T], self.area[:T], self.n_obs[:T], self.axis[:T]

    # --- calls ------------------------------------------------------------------------------------
    def frame(self, raw: bytes | None, n_raw: int, T: int, dt: float) -> list[int]:
        """One frame up to the end of the update (or up to the association when stats say RESOLVE).
        counts must hold the points of each camera slot in raw. Returns the stats as a list."""
        if n_raw > self.n_cap:
            self._alloc(self.t_cap, max(n_raw, 2 * self.n_cap))
        p, cams, buf = self._args
        rc = self.lib.ftk_frame(p, cams, buf, raw, self._counts_ptr, T, dt, self._stats_ptr)
        if rc:
            raise RuntimeError(f"tracker kernel: {_ERRORS.get(rc, rc)} (T={T}, points={n_raw}, dt={dt})")
        return self.stats.tolist()

    def update(self, T: int) -> list[int]:
        p, cams, buf = self._args
        rc = self.lib.ftk_update(p, cams, buf, T, self._stats_ptr)
        if rc:
            raise RuntimeError(f"tracker kernel: {_ERRORS.get(rc, rc)} in the update (T={T})")
        return self.stats.tolist()

    # --- results as NumPy views (valid until the next frame) --------------------------------------
    def assign_view(self, T: int) -> NDArray[np.int64]:
        return self.assign[: self.C * T].reshape(self.C, T)

    def pair_view(self, a: np.ndarray, N: int, T: int) -> np.ndarray:
        return a[: N * T].reshape(N, T)

    def pointset(self) -> PointSet:
        N = int(self.stats[ST_POINTS])
        uv, uvi = self.uv[:N], self.uvi[:N]
        return PointSet(
            self.slot[:N], self.index[:N], uv[:, 0], uv[:, 1], uvi[:, 0], uvi[:, 1], self.parea[:N],
            self.ori[:N], self.ecc[:N], self.starts, self.rays[:N], uv, self.ori_ok[:N].view(bool),
            self.rank[:N], int(self.stats[ST_MAX_PER_CAMERA]),
        )


