"""ctypes binding of the fish fit's C kernel (kernel/fish_kernel.c): the line-to-surface distances of
eq. 4.2 for a batch of states. `line_distances_c` returns None when the library is not built, and the
fit then uses its NumPy path (the same rule; tests check they agree)."""

from __future__ import annotations

import ctypes

import numpy as np
from numpy.typing import NDArray

from flytrack_host.util.native import NativeLibraryError, load_library

F64 = NDArray[np.float64]
LIB = "flytrack_fish_kernel"
SUBDIR = "host/flytrack_host/fish/kernel"
ABI_VERSION = 1
_lib: ctypes.CDLL | None = None
_tried = False


def load() -> ctypes.CDLL | None:
    global _lib, _tried
    if _tried:
        return _lib
    _tried = True
    try:
        lib = load_library(LIB, SUBDIR, "fish fit kernel")
    except NativeLibraryError:
        return None
    lib.ffk_abi_version.restype = ctypes.c_int
    if lib.ffk_abi_version() != ABI_VERSION:
        return None
    vp, i64 = ctypes.c_void_p, ctypes.c_int64
    lib.ffk_line_distances.restype = ctypes.c_int
    lib.ffk_line_distances.argtypes = [vp, i64, i64, i64, vp, vp, i64, vp]
    _lib = lib
    return lib


def line_distances_c(S: F64, p: F64, v: F64) -> F64 | None:
    """S (B, Ns, Nu, 3), p (N, 3), v (N, 3) -> D (B, N), or None without the library."""
    lib = load()
    if lib is None:
        return None
    S = np.ascontiguousarray(S, dtype=np.float64)
    p = np.ascontiguousarray(p, dtype=np.float64)
    v = np.ascontiguousarray(v, dtype=np.float64)
    B, Ns, Nu, _ = S.shape
    N = p.shape[0]
    D = np.empty((B, N))
    rc = lib.ffk_line_distances(S.ctypes.data, B, Ns, Nu, p.ctypes.data, v.ctypes.data, N, D.ctypes.data)
    if rc != 0:
        raise ValueError(f"fish kernel refused sizes B={B} Ns={Ns} Nu={Nu} N={N}")
    return D
