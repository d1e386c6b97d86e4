"""ctypes binding to libflytrack_features, the C library the edge daemon runs.

The offline tools call exactly the code the edge runs: this module loads the shared library built by
CMake (`make build`) and mirrors its structs. Where to find it: flytrack_host.util.native (`edge/
feature_extractor/` under $FLYTRACK_BUILD_DIR, else under <repo>/build).
"""

from __future__ import annotations

import ctypes

from flytrack_host.util.native import NativeLibraryError, library_path, load_library

LIB = "flytrack_features"
SUBDIR = "edge/feature_extractor"
ABI_VERSION = 1


class FeatureLibraryError(NativeLibraryError):
    """The C library is missing or does not match these bindings (an OSError, as ctypes load failures)."""


class Params(ctypes.Structure):
    """Mirror of ft_fx_params (edge/feature_extractor/include/flytrack/features.h)."""

    _fields_ = [
        ("width", ctypes.c_uint32),
        ("height", ctypes.c_uint32),
        ("stride", ctypes.c_uint32),
        ("pixel_format", ctypes.c_int32),
        ("polarity", ctypes.c_int32),
        ("alpha", ctypes.c_double),
        ("n_sigma", ctypes.c_double),
        ("diff_threshold", ctypes.c_double),
        ("bg_update_interval", ctypes.c_uint32),
        ("clear_fraction", ctypes.c_double),
        ("despeckle_threshold", ctypes.c_double),
        ("min_area", ctypes.c_uint32),
        ("subtract_cut", ctypes.c_int32),
        ("max_points", ctypes.c_uint32),
        ("max_candidates", ctypes.c_uint32),
        ("fx", ctypes.c_double),
        ("fy", ctypes.c_double),
        ("cx", ctypes.c_double),
        ("cy", ctypes.c_double),
        ("skew", ctypes.c_double),
        ("k1", ctypes.c_double),
        ("k2", ctypes.c_double),
        ("p1", ctypes.c_double),
        ("p2", ctypes.c_double),
        ("k3", ctypes.c_double),
    ]


class Point(ctypes.Structure):
    """Mirror of ft_fx_point."""

    _fields_ = [
        ("x_dist", ctypes.c_double),
        ("y_dist", ctypes.c_double),
        ("x_undist", ctypes.c_double),
        ("y_undist", ctypes.c_double),
        ("area", ctypes.c_double),
        ("peak_diff", ctypes.c_double),
        ("orientation", ctypes.c_double),
        ("eccentricity", ctypes.c_double),
        ("mean_val", ctypes.c_double),
        ("sumsq_val", ctypes.c_double),
        ("cur_val", ctypes.c_uint32),
        ("peak_x", ctypes.c_uint32),
        ("peak_y", ctypes.c_uint32),
        ("n_candidates", ctypes.c_uint32),
    ]


class Result(ctypes.Structure):
    """Mirror of ft_fx_result."""

    _fields_ = [
        ("frame_index", ctypes.c_uint64),
        ("n_points", ctypes.c_uint32),
        ("total_points", ctypes.c_uint32),
        ("n_candidates", ctypes.c_uint32),
        ("flags", ctypes.c_uint32),
        ("points", ctypes.POINTER(Point)),
    ]


_lib: ctypes.CDLL | None = None


def load() -> ctypes.CDLL:
    """Loads the library once; raises FeatureLibraryError with the fix when it is missing."""
    global _lib
    if _lib is not None:
        return _lib
    path = library_path(LIB, SUBDIR)
    lib = load_library(LIB, SUBDIR, "feature extractor library", FeatureLibraryError)
    lib.ft_fx_abi_version.restype = ctypes.c_int
    lib.ft_fx_sizeof_params.restype = ctypes.c_size_t
    lib.ft_fx_sizeof_point.restype = ctypes.c_size_t
    if (
        lib.ft_fx_abi_version() != ABI_VERSION
        or lib.ft_fx_sizeof_params() != ctypes.sizeof(Params)
        or lib.ft_fx_sizeof_point() != ctypes.sizeof(Point)
    ):
        raise FeatureLibraryError(f"{path} does not match these bindings: rebuild with `make build`")
    P = ctypes.POINTER
    sigs: dict[str, tuple[object, list[object]]] = {
        "ft_fx_params_default": (None, [P(Params), ctypes.c_uint32, ctypes.c_uint32, ctypes.c_int32]),
        "ft_fx_params_check": (ctypes.c_int, [P(Params), ctypes.c_char_p, ctypes.c_size_t]),
        "ft_fx_create": (ctypes.c_int, [P(Params), ctypes.c_size_t, P(ctypes.c_void_p)]),
        "ft_fx_destroy": (None, [ctypes.c_void_p]),
        "ft_fx_frame_bytes": (ctypes.c_size_t, [P(Params)]),
        "ft_fx_process": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t, P(Result)]),
        "ft_fx_take_background": (None, [ctypes.c_void_p]),
        "ft_fx_set_mask": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_void_p]),
        "ft_fx_set_param": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_double]),
        "ft_fx_get_param": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_char_p, P(ctypes.c_double)]),
        "ft_fx_background_mean": (P(ctypes.c_float), [ctypes.c_void_p]),
        "ft_fx_background_sumsq": (P(ctypes.c_float), [ctypes.c_void_p]),
        "ft_fx_undistort": (
            None,
            [P(Params), ctypes.c_double, ctypes.c_double, P(ctypes.c_double), P(ctypes.c_double)],
        ),
        "ft_fx_strerror": (ctypes.c_char_p, [ctypes.c_int]),
    }
    for name, (res, args) in sigs.items():
        fn = getattr(lib, name)
        fn.restype = res
        fn.argtypes = args
    _lib = lib
    return lib
