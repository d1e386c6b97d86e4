"""ctypes binding to libflytrack_events (edge/events), the C library the edge daemon reads event
files with. Loaded through flytrack_host.util.native (`edge/events/` under $FLYTRACK_BUILD_DIR, else under
<repo>/build); the C API is documented in edge/events/include/flytrack/events.h."""

from __future__ import annotations

import ctypes
import functools

from flytrack_host.util.native import NativeLibraryError, load_library

LIB = "flytrack_events"
SUBDIR = "edge/events"


class EventLibraryError(NativeLibraryError):
    """libflytrack_events is missing or cannot be loaded (run `make build`)."""


class Info(ctypes.Structure):
    """Mirror of ft_ev_info."""

    _fields_ = [
        ("format", ctypes.c_int),
        ("width", ctypes.c_int),
        ("height", ctypes.c_int),
        ("compression", ctypes.c_int),
        ("n_events", ctypes.c_uint64),
        ("n_triggers", ctypes.c_uint64),
        ("n_skipped", ctypes.c_uint64),
        ("offset", ctypes.c_uint64),
        ("time_offset", ctypes.c_int64),
    ]


@functools.cache
def lib() -> ctypes.CDLL:
    """The loaded library with its function signatures set."""
    so = load_library(LIB, SUBDIR, "event-file library", EventLibraryError)
    vp, cp, sz = ctypes.c_void_p, ctypes.c_char_p, ctypes.c_size_t
    so.ft_ev_open.argtypes = [cp, ctypes.c_int, cp, sz]
    so.ft_ev_open.restype = vp
    so.ft_ev_open_mem.argtypes = [vp, sz, ctypes.c_int, cp, cp, sz]
    so.ft_ev_open_mem.restype = vp
    so.ft_ev_read.argtypes = [vp, vp, sz]
    so.ft_ev_read.restype = ctypes.c_longlong
    so.ft_ev_get_info.argtypes = [vp, ctypes.POINTER(Info)]
    so.ft_ev_get_info.restype = None
    so.ft_ev_error.argtypes = [vp]
    so.ft_ev_error.restype = cp
    so.ft_ev_error_offset.argtypes = [vp]
    so.ft_ev_error_offset.restype = ctypes.c_longlong
    so.ft_ev_close.argtypes = [vp]
    so.ft_ev_close.restype = None
    so.ft_ev_keep_triggers.argtypes = [vp, ctypes.c_int]
    so.ft_ev_keep_triggers.restype = None
    so.ft_ev_triggers.argtypes = [vp, vp, sz]
    so.ft_ev_triggers.restype = sz
    so.ft_ev_writer_open.argtypes = [cp, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int, cp, sz]
    so.ft_ev_writer_open.restype = vp
    so.ft_ev_writer_open_ex.argtypes = [cp, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int,
                                        ctypes.c_uint, cp, sz]
    so.ft_ev_writer_open_ex.restype = vp
    so.ft_ev_write_triggers.argtypes = [vp, vp, sz]
    so.ft_ev_write_triggers.restype = ctypes.c_longlong
    so.ft_ev_write.argtypes = [vp, vp, sz]
    so.ft_ev_write.restype = ctypes.c_int
    so.ft_ev_writer_time_offset.argtypes = [vp]
    so.ft_ev_writer_time_offset.restype = ctypes.c_int64
    so.ft_ev_writer_error.argtypes = [vp]
    so.ft_ev_writer_error.restype = cp
    so.ft_ev_writer_close.argtypes = [vp, cp, sz]
    so.ft_ev_writer_close.restype = ctypes.c_int
    return so
