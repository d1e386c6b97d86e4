"""Finding the C programs and loading the C shared libraries that CMake builds (`make build`) for the
host's ctypes bindings: `lib<name>.so` under `$FLYTRACK_BUILD_DIR/<subdir>/` (the Makefile exports it), else under
`<repo>/build/<subdir>/`, where <subdir> is the library's source folder (CMake mirrors the tree)."""

from __future__ import annotations

import ctypes
import os
import shutil
from pathlib import Path

BUILD_ENV = "FLYTRACK_BUILD_DIR"
REPO = Path(__file__).resolve().parents[3]


class NativeLibraryError(OSError):
    """A C library is missing or cannot be loaded (an OSError, as ctypes load failures are)."""


def build_dir() -> Path:
    """The CMake build directory: $FLYTRACK_BUILD_DIR, else <repo>/build."""
    env = os.environ.get(BUILD_ENV)
    return Path(env) if env else REPO / "build"


def library_path(name: str, subdir: str) -> Path:
    """Where lib<name>.so should be."""
    return build_dir() / subdir / f"lib{name}.so"


def load_library(name: str, subdir: str, what: str,
                 error: type[NativeLibraryError] = NativeLibraryError) -> ctypes.CDLL:
    """Loads lib<name>.so; raises `error` that names the file and says to run `make build`."""
    path = library_path(name, subdir)
    if not path.is_file():
        raise error(f"the {what} {path} is not built: run `make build` in the repository, or set {BUILD_ENV} "
                    "to the CMake build directory")
    try:
        return ctypes.CDLL(str(path))
    except OSError as exc:
        raise error(f"cannot load the {what} {path}: {exc}; rebuild it with `make build`") from exc


def find_edge_binary(explicit: Path | None = None) -> Path:
    """The `flytrack-edge` program: `explicit` when given, else the build directory's, else the one on
    PATH (an installed edge). Raises NativeLibraryError naming where it looked."""
    cands = [explicit] if explicit else []
    env = os.environ.get(BUILD_ENV)
    if env:
        cands.append(Path(env) / "edge" / "feature_extractor" / "flytrack-edge")
    cands.append(REPO / "build" / "edge" / "feature_extractor" / "flytrack-edge")
    which = shutil.which("flytrack-edge")
    if which:
        cands.append(Path(which))
    for c in cands:
        if c is not None and c.is_file() and os.access(c, os.X_OK):
            return c
    raise NativeLibraryError("the edge extractor `flytrack-edge` is not built (looked in "
                             + ", ".join(str(c) for c in cands if c) + "); run `make build`")
