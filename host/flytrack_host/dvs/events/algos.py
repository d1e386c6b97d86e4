"""ctypes binding to libflytrack_event_algos (edge/events/algos): the edge's noise filters and cluster
tracker with its Kalman filters, for tests, benchmarks and offline analysis on the host. The C API and
the algorithms are described in edge/events/include/flytrack/event_algos.h.

    nf = NoiseFilter(346, 260)                 # libcaer's defaults
    kept = nf.apply(events)                    # EVENT_DTYPE array -> the survivors (a copy)
    ct = ClusterTracker(346, 260)
    ct.feed(kept)
    clusters = ct.clusters(t_us=kept["t"][-1])  # CLUSTER_DTYPE array
"""

from __future__ import annotations

import ctypes
import functools

import numpy as np

from flytrack_host.dvs.events.files import EVENT_DTYPE
from flytrack_host.util.native import NativeLibraryError, load_library


class EventAlgosLibraryError(NativeLibraryError):
    """libflytrack_event_algos is missing or cannot be loaded (run `make build`)."""


class _NfParams(ctypes.Structure):
    _fields_ = [(n, ctypes.c_uint32) for n in ("width", "height", "ba_window_us", "stc_min_neighbours",
                                                "refractory_us", "hot_pixel_count", "hot_pixel_window_us")]


class _NfStats(ctypes.Structure):
    _fields_ = [(n, ctypes.c_uint64) for n in ("in_", "out", "ba_removed", "stc_removed",
                                                "refractory_removed", "hot_removed")] + [
        ("hot_pixels", ctypes.c_uint32)]


class _CtParams(ctypes.Structure):
    _fields_ = [("width", ctypes.c_uint32), ("height", ctypes.c_uint32), ("max_clusters", ctypes.c_uint32),
                ("radius_px", ctypes.c_float), ("mixing", ctypes.c_float), ("mass_decay_us", ctypes.c_uint32),
                ("min_mass", ctypes.c_float), ("merge_max_dv", ctypes.c_float), ("velocity_tau_us", ctypes.c_float),
                ("kalman", ctypes.c_int), ("kf_interval_us", ctypes.c_uint32), ("feedback", ctypes.c_int),
                ("dynamic_variances", ctypes.c_int), ("kf_ramp", ctypes.c_uint32),
                ("events_until_track", ctypes.c_uint64), ("max_meas_var", ctypes.c_float),
                ("min_proc_var", ctypes.c_float), ("kf_centroid", ctypes.c_int),
                ("centroid_var", ctypes.c_float), ("centroid_gate_px", ctypes.c_float)]


class _CtStats(ctypes.Structure):
    _fields_ = [(n, ctypes.c_uint64) for n in ("events", "created", "died", "merged", "unassigned", "kf_updates")]


#: One cluster as ft_ct_cluster lays it out.
CLUSTER_DTYPE = np.dtype([("id", "<u4"), ("x", "<f4"), ("y", "<f4"), ("vx", "<f4"), ("vy", "<f4"),
                          ("size", "<f4"), ("mass", "<f4"), ("var_x", "<f4"), ("var_y", "<f4"),
                          ("cov_xy", "<f4"), ("events", "<u4"), ("tracking", "<i4")])
MAX_CLUSTERS = 64


@functools.cache
def lib() -> ctypes.CDLL:
    so = load_library("flytrack_event_algos", "edge/events/algos", "event-algorithm library",
                      EventAlgosLibraryError)
    vp, sz = ctypes.c_void_p, ctypes.c_size_t
    so.ft_nf_defaults.argtypes = [ctypes.POINTER(_NfParams), ctypes.c_uint32, ctypes.c_uint32]
    so.ft_nf_create.argtypes = [ctypes.POINTER(_NfParams)]
    so.ft_nf_create.restype = vp
    so.ft_nf_apply.argtypes = [vp, vp, sz]
    so.ft_nf_apply.restype = sz
    so.ft_nf_get_stats.argtypes = [vp, ctypes.POINTER(_NfStats)]
    so.ft_nf_destroy.argtypes = [vp]
    so.ft_ct_defaults.argtypes = [ctypes.POINTER(_CtParams), ctypes.c_uint32, ctypes.c_uint32]
    so.ft_ct_create.argtypes = [ctypes.POINTER(_CtParams)]
    so.ft_ct_create.restype = vp
    so.ft_ct_feed.argtypes = [vp, vp, sz]
    so.ft_ct_clusters.argtypes = [vp, ctypes.c_int64, vp, sz]
    so.ft_ct_clusters.restype = sz
    so.ft_ct_get_stats.argtypes = [vp, ctypes.POINTER(_CtStats)]
    so.ft_ct_destroy.argtypes = [vp]
    return so


def _events(ev: np.ndarray) -> np.ndarray:
    if ev.dtype != EVENT_DTYPE:
        raise TypeError(f"events must be EVENT_DTYPE (flytrack_host.dvs.events), not {ev.dtype}")
    return np.ascontiguousarray(ev)


def _apply_overrides(params: ctypes.Structure, overrides: dict) -> None:
    names = {f[0] for f in params._fields_}
    for k, v in overrides.items():
        if k not in names or k in ("width", "height"):
            raise ValueError(f"unknown parameter {k!r}; one of {sorted(names - {'width', 'height'})}")
        setattr(params, k, v)


class NoiseFilter:
    """Background-activity, correlation, refractory and hot-pixel filters (libcaer's defaults unless
    overridden: ba_window_us=2000, refractory_us=100, hot_pixel_count=10000 per 1 s window, and
    stc_min_neighbours=0, i.e. off)."""

    def __init__(self, width: int, height: int, **overrides: int) -> None:
        self._so = lib()
        p = _NfParams()
        self._so.ft_nf_defaults(ctypes.byref(p), width, height)
        _apply_overrides(p, overrides)
        self._h = self._so.ft_nf_create(ctypes.byref(p))
        if not self._h:
            raise ValueError(f"bad noise-filter parameters: {dict((f, getattr(p, f)) for f, _ in p._fields_)}")

    def apply(self, events: np.ndarray, inplace: bool = False) -> np.ndarray:
        """The events that survive, in order: a new array, or with `inplace` the front of `events`
        itself (no copy; `events` must be C-contiguous EVENT_DTYPE)."""
        out = _events(events) if inplace else _events(events).copy()
        if inplace and out is not events:
            raise ValueError("inplace needs a C-contiguous EVENT_DTYPE array")
        n = self._so.ft_nf_apply(self._h, out.ctypes.data, len(out))
        return out[:n]

    @property
    def stats(self) -> dict[str, int]:
        s = _NfStats()
        self._so.ft_nf_get_stats(self._h, ctypes.byref(s))
        return {("in" if n == "in_" else n): int(getattr(s, n)) for n, _ in s._fields_}

    def __del__(self) -> None:
        if getattr(self, "_h", None):
            self._so.ft_nf_destroy(self._h)
            self._h = None


class ClusterTracker:
    """Cluster tracker with a Kalman filter per cluster (seed 002 part I; jAER's defaults unless
    overridden: max_clusters=10, radius_px=0.1 of the larger side, mixing=0.05, mass_decay_us=10000)."""

    def __init__(self, width: int, height: int, **overrides: float) -> None:
        self._so = lib()
        p = _CtParams()
        self._so.ft_ct_defaults(ctypes.byref(p), width, height)
        _apply_overrides(p, overrides)
        self._h = self._so.ft_ct_create(ctypes.byref(p))
        if not self._h:
            raise ValueError("bad cluster-tracker parameters")

    def feed(self, events: np.ndarray) -> None:
        ev = _events(events)
        self._so.ft_ct_feed(self._h, ev.ctypes.data, len(ev))

    def clusters(self, t_us: int) -> np.ndarray:
        out = np.zeros(MAX_CLUSTERS, CLUSTER_DTYPE)
        n = self._so.ft_ct_clusters(self._h, int(t_us), out.ctypes.data, MAX_CLUSTERS)
        return out[:n]

    @property
    def stats(self) -> dict[str, int]:
        s = _CtStats()
        self._so.ft_ct_get_stats(self._h, ctypes.byref(s))
        return {n: int(getattr(s, n)) for n, _ in s._fields_}

    def __del__(self) -> None:
        if getattr(self, "_h", None):
            self._so.ft_ct_destroy(self._h)
            self._h = None

