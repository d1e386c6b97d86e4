"""`flytrack events convert` on recordings as their own tools write them: dv-processing's AEDAT 4.0
with Unix-epoch microsecond times (as DV records), and external trigger events in EVT 3.0 and AEDAT
4.0, read back by dv-processing, the `evt3` package and our own readers."""

from __future__ import annotations

import re
from pathlib import Path

import dv_processing as dv
import evt3
import numpy as np
from typer.testing import CliRunner

from flytrack_host.cli import app
from flytrack_host.dvs.events import EVENT_DTYPE, EventReader, read_events

W, H = 346, 260
EPOCH_US = 1_712_345_678_901_234  # 2024-04-05, as DV stamps its events


def run(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(app, ["events", *args])
    return r.exit_code, " ".join(r.output.split())  # rich wraps long lines


def dv_epoch_recording(path: Path, n: int = 112_000, seed: int = 0) -> np.ndarray:
    """An AEDAT 4.0 file as DV records one: Unix-epoch times, several packets."""
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = EPOCH_US + np.cumsum(rng.integers(0, 90, n))  # ~5 s
    ev["x"], ev["y"], ev["p"] = rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n)
    cfg = dv.io.MonoCameraWriter.EventOnlyConfig("DAVIS346_00000499", (W, H))
    writer = dv.io.MonoCameraWriter(str(path), cfg)
    for part in np.array_split(ev, 20):
        store = dv.EventStore()
        for t, x, y, p in part[["t", "x", "y", "p"]].tolist():
            store.push_back(t, x, y, bool(p))
        writer.writeEvents(store)
    del writer
    return ev


def test_epoch_times_are_rebased_into_a_small_evt3_file(tmp_path: Path) -> None:
    src = tmp_path / "dv.aedat4"
    ev = dv_epoch_recording(src)
    dst = tmp_path / "out.raw"
    rc, out = run("convert", str(src), str(dst))
    assert rc == 0, out
    # ~2 to 3 words an event: not hundreds of MB of TIME_HIGH padding up to the epoch
    assert dst.stat().st_size < 8 * len(ev), dst.stat().st_size
    head = dst.read_bytes()[:400].decode(errors="replace")
    m = re.search(r"^% time_offset_us (\d+)$", head, re.M)
    assert m, head
    offset = int(m.group(1))
    assert 0 < ev["t"][0] - offset < 2**24
    assert f"{offset:,}" in out or str(offset) in out  # the command says what it did
    # times come back right: ours with the offset added back, a reader that does not know the
    # header line (evt3 from PyPI) relative to it, and both in the same order as written
    back = read_events(dst)
    np.testing.assert_array_equal(back["t"], ev["t"])
    np.testing.assert_array_equal(back["x"], ev["x"])
    theirs = evt3.decode_file(str(dst))
    np.testing.assert_array_equal(theirs.t.astype(np.int64) + offset, ev["t"])
    with EventReader(dst) as r:
        assert r.info.time_offset == offset
    # and back to AEDAT 4.0: the epoch times again, as dv-processing reads them
    again = tmp_path / "again.aedat4"
    rc, out = run("convert", str(dst), str(again))
    assert rc == 0, out
    rec = dv.io.MonoCameraRecording(str(again))
    assert rec.getTimeRange()[0] == ev["t"][0]
    np.testing.assert_array_equal(rec.getNextEventBatch().timestamps()[:100], ev["t"][:100])
