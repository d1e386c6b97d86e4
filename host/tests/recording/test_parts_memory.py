"""The readers that stream hold about two parts, whatever the number of parts: the peak memory (tracemalloc,
which sees NumPy's and pandas' buffers) of exporting (.braidz, CSV) and re-tracking a recording of 3 times
as many parts stays where it was, while reading it whole grows with it. Judged by bytes, not seconds."""

from __future__ import annotations

import tracemalloc
from collections.abc import Callable
from pathlib import Path

import pytest

from flytrack_host.io.braidz import export_braidz
from flytrack_host.io.csv_export import export_csv
from flytrack_host.io.retrack import cameras_for, load_2d, retrack
from flytrack_host.recording import load_recording
from flytrack_host.recording.parts import part_dirs
from flytrack_host.tracking.params import TrackingParams

from .conftest import write_pair


def peak(fn: Callable[[], object]) -> int:
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.slow
def test_streaming_readers_hold_about_two_parts_whatever_the_length(tmp_path: Path) -> None:
    recs = {s: write_pair(tmp_path / f"{s}s", duration_s=s).parted for s in (2.0, 6.0)}
    n_parts = {s: len(part_dirs(p)) for s, p in recs.items()}
    assert n_parts[6.0] >= 2.5 * n_parts[2.0]
    params = TrackingParams(kernel="numpy")

    def do_retrack(p: Path, out: Path) -> None:
        data = load_2d(p, stream=True)
        retrack(data, cameras_for(data), params, data.fps, out=out, progress=False)

    figures: dict[str, dict[float, int]] = {}
    for s, p in [(0.0, recs[2.0]), *recs.items()]:  # once first unmeasured: imports and caches are not the reader's
        d = tmp_path / f"out{s}"
        d.mkdir()
        for name, fn in (("braidz", lambda p=p, d=d: export_braidz(p, d / "x.braidz")),
                         ("csv", lambda p=p, d=d: export_csv(p, d / "csv")),
                         ("retrack", lambda p=p, d=d: do_retrack(p, d / "rt.flytrack")),
                         ("load whole", lambda p=p: load_recording(p))):
            figures.setdefault(name, {})[s] = peak(fn)
    for name, f in figures.items():
        print(f"{name:10s} peak {f[2.0] / 1e6:6.2f} MB with {n_parts[2.0]} parts, {f[6.0] / 1e6:6.2f} MB with "
              f"{n_parts[6.0]} parts (x{f[6.0] / f[2.0]:.2f})")
    for name in ("braidz", "csv", "retrack"):
        assert figures[name][6.0] <= 1.3 * figures[name][2.0], (name, figures[name])
    assert figures["load whole"][6.0] >= 2.0 * figures["load whole"][2.0]  # (what the streaming avoids)
