"""A recording in parts reads as the same recording written unparted: load_recording, the .braidz and CSV
exports (part by part), a re-track (the tracker's state carried from part to part), compare, batch and
`recording info`. The pair is written from one stream of items (conftest.py); old unparted recordings
are the other half of every comparison."""

from __future__ import annotations

import gzip
import io
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
from typer.testing import CliRunner

from flytrack_host.cli import app
from flytrack_host.io.braidz import export_braidz
from flytrack_host.io.csv_export import export_csv
from flytrack_host.io.hdr import decode
from flytrack_host.io.retrack import cameras_for, load_2d, retrack
from flytrack_host.recording import load_recording
from flytrack_host.recording.parts import part_dirs
from flytrack_host.recording.schema import FLAG_TRACKED
from flytrack_host.recording.source import open_source
from flytrack_host.tracking.params import TrackingParams

RECORDER_LINES = ("part ", "part-")  # the recorder's own lines about its parts (only a recording in parts has them)


def _log(lines: list[dict]) -> list[tuple]:
    return [(r["source"], r["message"]) for r in lines  # (host times: the two were written one after the other)
            if not (r["source"] == "recorder" and r["message"].startswith(RECORDER_LINES))]


def test_the_pair_is_what_it_should_be(pair) -> None:  # noqa: ANN001
    parts = part_dirs(pair.parted)
    assert len(parts) >= 5, "the parted recording should have several parts"
    assert not (pair.whole / "part-0001").exists() and (pair.whole / "recording.h5").exists()
    assert all((p / "recording.h5").exists() for p in parts)
    # Late rows crossed a part boundary at least once (what the readers must regroup by frame).
    src = open_source(pair.parted)
    crossed = 0
    for t in src.iter_tables(["data2d_distorted"]):
        d = t["data2d_distorted"]
        late = d[(d["flags"] & 2) != 0]
        tracked = d[(d["flags"] & FLAG_TRACKED) != 0]
        if len(tracked) and len(late):
            crossed += int((late["trigger_frame"] < tracked["trigger_frame"].min()).sum())
    print(f"{len(parts)} parts, {crossed} late rows in a later part than their frame")
    assert crossed >= 3


def test_load_recording_of_parts_equals_unparted(pair) -> None:  # noqa: ANN001
    a, b = load_recording(pair.whole), load_recording(pair.parted)
    assert list(a.tables) == list(b.tables)
    for name in a.tables:
        assert a.tables[name].dtype == b.tables[name].dtype, name
        assert a.tables[name].tobytes() == b.tables[name].tobytes(), name
    assert len(a.table("cam_info")) == 4  # the parts repeat it; read as one, it is there once
    assert _log(a.textlog) == _log(b.textlog)
    assert a.files == b.files and b.meta["parts"] == len(part_dirs(pair.parted))
    assert b.fps == a.fps and b.calibration == a.calibration


def test_each_part_reads_alone(pair) -> None:  # noqa: ANN001
    whole = load_recording(pair.whole)
    n = 0
    for p in part_dirs(pair.parted):
        rec = load_recording(p)  # a part is a whole recording of its own: rig, calibration, cameras
        assert rec.calibration == whole.calibration
        assert rec.table("cam_info").tobytes() == whole.table("cam_info").tobytes()
        n += len(rec.table("data2d_distorted"))
    assert n == len(whole.table("data2d_distorted"))


def _members(path: Path) -> dict[str, bytes]:
    with zipfile.ZipFile(path) as z:
        return {n: z.read(n) for n in z.namelist()}


def test_braidz_of_parts_equals_braidz_of_unparted(pair, tmp_path) -> None:  # noqa: ANN001
    ca = export_braidz(pair.whole, tmp_path / "a.braidz")
    cb = export_braidz(pair.parted, tmp_path / "b.braidz")  # part by part
    assert ca == cb
    assert ca["data2d_distorted not exported: no trigger frame"] > 0
    assert ca["data2d_distorted not exported: rejected live"] > 0
    a, b = _members(tmp_path / "a.braidz"), _members(tmp_path / "b.braidz")
    assert sorted(a) == sorted(b)
    for name in ("kalman_estimates.csv.gz", "data2d_distorted.csv.gz", "data_association.csv.gz",
                 "cam_info.csv.gz", "trigger_clock_info.csv.gz", "experiment_info.csv.gz"):
        assert gzip.decompress(a[name]) == gzip.decompress(b[name]), name  # the same CSV rows, byte for byte
    ta = pd.read_csv(io.BytesIO(gzip.decompress(a["textlog.csv.gz"])))
    tb = pd.read_csv(io.BytesIO(gzip.decompress(b["textlog.csv.gz"])))
    keep = ~tb["message"].astype(str).str.startswith(RECORDER_LINES) | (tb["cam_id"] != "recorder")
    assert list(ta["message"][2:]) == list(tb["message"][keep][2:])  # (the first two carry the start time)
    for name in [n for n in a if n.endswith(".hlog")]:
        ha = [ln for ln in a[name].decode().splitlines() if ln and not ln.startswith(("#", '"'))]
        hb = [ln for ln in b[name].decode().splitlines() if ln and not ln.startswith(("#", '"'))]
        assert np.array_equal(decode(ha[0].split(",")[3])[1], decode(hb[0].split(",")[3])[1]), name
    d2 = pd.read_csv(io.BytesIO(gzip.decompress(b["data2d_distorted.csv.gz"])))
    assert (np.diff(d2["frame"].to_numpy()) >= 0).all()  # sorted by frame across the parts


def test_csv_of_parts_equals_csv_of_unparted(pair, tmp_path) -> None:  # noqa: ANN001
    fa, fb = export_csv(pair.whole, tmp_path / "a"), export_csv(pair.parted, tmp_path / "b")
    assert sorted(fa) == sorted(fb)
    for name in fa:
        if name == "textlog":
            continue
        assert fa[name].read_bytes() == fb[name].read_bytes(), name
    ta, tb = pd.read_csv(fa["textlog"]), pd.read_csv(fb["textlog"])
    tb = tb[~((tb["source"] == "recorder") & tb["message"].str.startswith(RECORDER_LINES))]
    assert list(ta["message"]) == list(tb["message"])


def test_retrack_of_parts_gives_the_estimates_of_unparted(pair, tmp_path) -> None:  # noqa: ANN001
    whole = load_2d(pair.whole)
    streamed = load_2d(pair.parted, stream=True)
    assert streamed.parts is not None and len(streamed.rows) == 0  # nothing read yet
    params = TrackingParams(kernel="numpy")
    ra = retrack(whole, cameras_for(whole), params, whole.fps, out=tmp_path / "a.flytrack", progress=False)
    rb = retrack(streamed, cameras_for(streamed), params, streamed.fps, out=tmp_path / "b.flytrack", progress=False)
    assert ra.frames == rb.frames == pair.frames and ra.estimates == rb.estimates > 0 and ra.objects == rb.objects
    a, b = load_recording(ra.out), load_recording(rb.out)
    for name in ("kalman_estimates", "data_association"):
        assert a.table(name).tobytes() == b.table(name).tobytes(), name
    # The re-track of a recording in parts is one too, part for part, and holds the same 2D rows.
    assert len(part_dirs(tmp_path / "b.flytrack")) == len(part_dirs(pair.parted))
    key = ["trigger_frame", "camera_index", "camera_frame", "frame_pt_idx", "flags"]
    assert np.array_equal(np.sort(a.table("data2d_distorted")[key]), np.sort(b.table("data2d_distorted")[key]))


def test_info_lists_the_parts_without_reading_the_rows(pair) -> None:  # noqa: ANN001
    r = CliRunner().invoke(app, ["recording", "info", str(pair.parted)], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    whole = load_recording(pair.whole)
    for name, rows in whole.tables.items():
        assert f"  {name}: {len(rows)} rows" in r.output, name
    parts = part_dirs(pair.parted)
    assert f"{len(parts)} parts" in r.output and all(p.name in r.output for p in parts)
    assert "finalised" in r.output and "read part by part" in r.output
    old = CliRunner().invoke(app, ["recording", "info", str(pair.whole)], env={"COLUMNS": "200"})
    assert old.exit_code == 0 and "parts" not in old.output.split("\n")[0]


def test_compare_and_batch_take_a_recording_in_parts(pair, tmp_path) -> None:  # noqa: ANN001
    from flytrack_host.batch.plan import ParamSet, Task
    from flytrack_host.batch.tasks import run_task
    from flytrack_host.io.compare import compare, load_tracks

    c = compare(load_tracks(pair.whole), load_tracks(pair.parted))
    assert c.agree() and c.paired == c.estimates_a == c.estimates_b and float(np.max(c.distances_m)) == 0.0
    rows = {}
    for name, src in (("whole", pair.whole), ("parted", pair.parted)):
        rows[name] = run_task(Task("retrack", src, tmp_path / name / "base.flytrack", ParamSet(("kernel=numpy",))))
        ex = run_task(Task("export", src, tmp_path / name / "export", formats=("braidz", "csv")))
        assert (Path(ex["output"]) / "export.braidz").exists()
    for k in ("frames_2d", "frames_covered", "estimates", "objects", "track_len_max", "reproj_points"):
        assert rows["whole"][k] == rows["parted"][k], k
    assert np.isclose(rows["whole"]["reproj_px_median"], rows["parted"]["reproj_px_median"])
