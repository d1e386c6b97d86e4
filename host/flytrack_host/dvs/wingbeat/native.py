"""ctypes binding to the edge's wing-beat tracker (edge/events/algos/wingbeat.c, in
libflytrack_event_algos): the C twin of `analysis.track_wings` with the EKF, which flytrack-edge runs
with `--wingbeat 1`. Used to check the two against each other and to time them on the same events.

    tr = NativeWingbeat(128, 128)
    beats = tr.feed(events)          # BEAT_DTYPE: per edge and beat, t_us, wing, edge, freq_hz, amplitude
    tr.geometry, tr.wings(), tr.stats
"""

from __future__ import annotations

import ctypes
import functools

import numpy as np

from flytrack_host.dvs.events.files import EVENT_DTYPE
from flytrack_host.dvs.wingbeat.geometry import WingbeatError
from flytrack_host.dvs.wingbeat.wra import BeatSeries
from flytrack_host.util.native import NativeLibraryError, load_library

MAX_HARMONICS = 4
#: One beat of one edge, as ft_wb_beat lays it out (edge 0 leading / OFF, 1 trailing / ON).
BEAT_DTYPE = np.dtype([("t_us", "<i8"), ("wing", "u1"), ("edge", "u1"), ("pad", "u1", (2,)),
                       ("freq_hz", "<f4"), ("amplitude", "<f4"), ("pad2", "u1", (4,))])  # 24 bytes, as C aligns it
ESTIMATE_DTYPE = np.dtype([("angle", "<f4"), ("amplitude", "<f4"), ("freq_hz", "<f4"), ("phase", "<f4"),
                           ("updates", "<u8")])


class _Params(ctypes.Structure):
    _fields_ = [(n, ctypes.c_uint32) for n in ("width", "height", "init_us", "init_max_events", "harmonics",
                                                "events_per_update")] + [
        (n, ctypes.c_double) for n in ("measurement_std_rad", "q_centre", "q_shape", "q_phase", "q_omega",
                                       "gate_sigma", "initial_phase_std", "initial_freq_std_hz", "start_freq_hz")]


class _Geometry(ctypes.Structure):
    _fields_ = [(n, ctypes.c_double) for n in ("body_x", "body_y", "heading", "size_px", "inner_px")] + [
        (n, ctypes.c_double * 2) for n in ("mean_stroke", "spread", "start_freq_hz")]


class _Stats(ctypes.Structure):
    _fields_ = [(n, ctypes.c_uint64) for n in ("events", "in_roi", "updates", "gated", "beats", "beats_dropped",
                                                "init_attempts", "init_failures", "bad_events")]


@functools.cache
def lib() -> ctypes.CDLL:
    so = load_library("flytrack_event_algos", "edge/events/algos", "event-algorithm library", NativeLibraryError)
    vp, sz = ctypes.c_void_p, ctypes.c_size_t
    so.ft_wb_defaults.argtypes = [ctypes.POINTER(_Params), ctypes.c_uint32, ctypes.c_uint32]
    so.ft_wb_create.argtypes = [ctypes.POINTER(_Params)]
    so.ft_wb_create.restype = vp
    so.ft_wb_feed.argtypes = [vp, vp, sz, vp, sz]
    so.ft_wb_feed.restype = sz
    so.ft_wb_state.argtypes = [vp]
    so.ft_wb_last_error.argtypes = [vp, ctypes.POINTER(ctypes.c_uint64)]
    so.ft_wb_last_error.restype = ctypes.c_char_p
    so.ft_wb_get_geometry.argtypes = [vp, ctypes.POINTER(_Geometry)]
    so.ft_wb_edges.argtypes = [vp, vp]
    so.ft_wb_wings.argtypes = [vp, vp]
    so.ft_wb_get_stats.argtypes = [vp, ctypes.POINTER(_Stats)]
    so.ft_wb_destroy.argtypes = [vp]
    return so


class NativeWingbeat:
    """The C tracker; parameters as `EkfParams` names them (harmonics, events_per_update, q_omega, ...)
    plus init_us, init_max_events and start_freq_hz (0 = found in the first window)."""

    def __init__(self, width: int = 128, height: int = 128, **overrides: float) -> None:
        self._so = lib()
        p = _Params()
        self._so.ft_wb_defaults(ctypes.byref(p), width, height)
        names = {f[0] for f in p._fields_} - {"width", "height"}
        for k, v in overrides.items():
            if k not in names:
                raise ValueError(f"unknown parameter {k!r}; one of {sorted(names)}")
            setattr(p, k, v)
        self._h = self._so.ft_wb_create(ctypes.byref(p))
        if not self._h:
            raise ValueError(f"bad wing-beat parameters: {dict((f, getattr(p, f)) for f, _ in p._fields_)}")
        self.harmonics = int(p.harmonics)

    def feed(self, events: np.ndarray, max_beats: int | None = None) -> np.ndarray:
        """Feeds time-ordered events; returns the beats that ended (BEAT_DTYPE)."""
        if events.dtype != EVENT_DTYPE:
            raise TypeError(f"events must be EVENT_DTYPE, not {events.dtype}")
        ev = np.ascontiguousarray(events)
        cap = max_beats if max_beats is not None else max(64, len(ev) // 50)
        out = np.zeros(cap, BEAT_DTYPE)
        n = self._so.ft_wb_feed(self._h, ev.ctypes.data, len(ev), out.ctypes.data, cap)
        return out[:n]

    @property
    def tracking(self) -> bool:
        return self._so.ft_wb_state(self._h) == 1

    def last_error(self) -> tuple[str, int]:
        """Why the last initialisation window found no fly, and how many windows failed."""
        n = ctypes.c_uint64()
        msg = self._so.ft_wb_last_error(self._h, ctypes.byref(n))
        return msg.decode(), int(n.value)

    @property
    def geometry(self) -> dict:
        g = _Geometry()
        if self._so.ft_wb_get_geometry(self._h, ctypes.byref(g)) != 0:
            msg, _ = self.last_error()
            raise WingbeatError(msg or "no fly found yet (the first window is still filling)")
        return {"body": (g.body_x, g.body_y), "heading_rad": g.heading, "size_px": g.size_px,
                "inner_px": g.inner_px, "mean_stroke": tuple(g.mean_stroke), "spread": tuple(g.spread),
                "start_freq_hz": tuple(g.start_freq_hz)}

    def edges(self) -> np.ndarray:
        out = np.zeros(4, ESTIMATE_DTYPE)
        self._so.ft_wb_edges(self._h, out.ctypes.data)
        return out

    def wings(self) -> np.ndarray:
        out = np.zeros(2, ESTIMATE_DTYPE)
        self._so.ft_wb_wings(self._h, out.ctypes.data)
        return out

    @property
    def stats(self) -> dict[str, int]:
        s = _Stats()
        self._so.ft_wb_get_stats(self._h, ctypes.byref(s))
        return {f: int(getattr(s, f)) for f, _ in s._fields_}

    def close(self) -> None:
        if getattr(self, "_h", None):
            self._so.ft_wb_destroy(self._h)
            self._h = None

    def __del__(self) -> None:
        self.close()


def edge_beats(beats: np.ndarray, wing: int, edge: int) -> BeatSeries:
    """One edge's beats as the Python tracker's BeatSeries."""
    b = beats[(beats["wing"] == wing) & (beats["edge"] == edge)]
    return BeatSeries(b["t_us"].astype(np.float64), b["freq_hz"].astype(np.float64),
                      b["amplitude"].astype(np.float64))
