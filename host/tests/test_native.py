"""flytrack_host.util.native: the one finder/loader of the C libraries, used by both ctypes bindings."""

from __future__ import annotations

from pathlib import Path

import pytest

from flytrack_host.edges.features import _lib as features_lib
from flytrack_host.tracking import kernel as tracker_kernel
from flytrack_host.util import native


def test_finds_the_library_under_the_build_dir(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv(native.BUILD_ENV, str(tmp_path))
    assert native.library_path("thing", "a/b") == tmp_path / "a" / "b" / "libthing.so"
    monkeypatch.delenv(native.BUILD_ENV)
    assert native.build_dir() == native.REPO / "build" and (native.REPO / "host" / "flytrack_host").is_dir()


def test_missing_and_broken_libraries_are_clear_errors(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv(native.BUILD_ENV, str(tmp_path))
    with pytest.raises(native.NativeLibraryError, match=r"the thing .*libthing\.so is not built: run `make build`"):
        native.load_library("thing", "x", "thing")
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "libthing.so").write_bytes(b"not an ELF file")
    with pytest.raises(native.NativeLibraryError, match="cannot load the thing .*rebuild it with `make build`"):
        native.load_library("thing", "x", "thing")


@pytest.mark.parametrize(("module", "error"), [(features_lib, features_lib.FeatureLibraryError),
                                                (tracker_kernel, tracker_kernel.KernelUnavailable)])
def test_both_bindings_load_through_it(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, module, error) -> None:  # noqa: ANN001
    assert issubclass(error, native.NativeLibraryError)
    monkeypatch.setattr(module, "_lib", None)
    monkeypatch.setenv(native.BUILD_ENV, str(tmp_path))
    with pytest.raises(error, match=f"{tmp_path}/{module.SUBDIR}/lib{module.LIB}.so is not built: run `make build`"):
        module.load()
