"""Finalising a recording: tables larger than a copy chunk are copied whole and in bounded memory
(A5); the rig is kept whether it came as TOML or as JSON (A6); `recording recover` says what is
wrong with its argument (D)."""

from __future__ import annotations

import importlib
import json
import time
import tracemalloc

import h5py
import numpy as np
from typer.testing import CliRunner

from flytrack_host.cli import app
from flytrack_host.pipeline import HostPipeline
from flytrack_host.recording import Recorder, finalize, load_recording
from flytrack_host.recording.latency import LatencyStats, latency_summary
from flytrack_host.recording.reader import _load_raw
from flytrack_host.recording.schema import DATA2D, LATENCY

finalize_mod = importlib.import_module("flytrack_host.recording.finalize")  # the package exports a function


def _raw_recording(folder, n_rows: int, partial: int = 0):
    rec = Recorder(folder, flush_interval_s=0.05)
    rec.start()
    rec.stop(finalize=False)
    rows = np.zeros(n_rows, dtype=DATA2D)
    rows["trigger_frame"] = np.arange(n_rows)
    rows["x_dist"] = (np.arange(n_rows) % 977).astype(np.float32)
    rows["cam_received_timestamp"] = 1000.0 + np.arange(n_rows) * 1e-3
    with open(folder / "data2d_distorted.bin", "ab") as f:
        f.write(rows.tobytes())
        f.write(b"\x01" * partial)  # a row cut by a crash
    lat = np.zeros(5000, dtype=LATENCY)
    lat["trigger_time"] = 100.0 + np.arange(5000) * 0.01
    lat["last_arrival"] = lat["trigger_time"] + 0.001 + (np.arange(5000) % 50) * 1e-4
    lat["estimate_time"] = lat["last_arrival"] + 0.0005
    lat["estimate_time"][7] = np.nan
    with open(folder / "latency.bin", "ab") as f:
        f.write(lat.tobytes())
    return rows, lat


def test_finalize_copies_in_chunks_in_bounded_memory(tmp_path, monkeypatch):
    chunk = 1 << 20
    monkeypatch.setattr(finalize_mod, "CHUNK_BYTES", chunk)
    n = (40 << 20) // DATA2D.itemsize  # a 40 MB table: 40 chunks
    rows, lat = _raw_recording(tmp_path / "r", n, partial=5)
    tracemalloc.start()
    try:
        rep = finalize(tmp_path / "r")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 8 * chunk, f"finalize held {peak / 1e6:.1f} MB at once for a {rows.nbytes / 1e6:.0f} MB table"
    assert rep.rows["data2d_distorted"] == n and rep.partial_bytes_dropped == {"data2d_distorted": 5}
    assert rep.last_host_time == rows["cam_received_timestamp"][-1]
    with h5py.File(rep.h5_path) as h5:
        d2 = h5["data2d_distorted"]
        assert d2.maxshape == (None,) and d2.shape == (n,)
        assert np.array_equal(d2[...], rows)
        g = h5["latency_histogram"]
        exact = latency_summary(lat)
        for k in ("total_p50_ms", "total_p99_ms", "arrival_p50_ms", "tracking_max_ms"):
            assert abs(g.attrs[k] - exact[k]) <= 0.1 + 1e-6, (k, g.attrs[k], exact[k])  # 0.1 ms bins
        assert g["counts"][...].sum() == 4999  # the NaN row is not counted
        live = LatencyStats()
        for r in lat:
            live.row(r["trigger_frame"], r["trigger_time"], r["first_arrival"], r["last_arrival"],
                     r["estimate_time"], 0, 0)
        assert np.array_equal(g["counts"][...], live.counts["total"])


def test_rig_json_is_kept_when_there_is_no_rig_text(helpers, tmp_path):
    pipe = HostPipeline(helpers.make_rig(2), cameras={}, tracker_factory=None, recording_path=tmp_path / "r",
                        bind="127.0.0.1:0")  # no rig_text: the rig is stored as rig.json
    pipe.start()
    time.sleep(0.05)
    summary = pipe.stop()
    rec = load_recording(summary["recording"])
    assert "rig.json" in rec.files
    assert json.loads(rec.files["rig.json"])["name"] == "testrig"
    assert "rig.json" in _load_raw(tmp_path / "r" / "part-0001").files  # the raw folder, as before finalising


def test_recover_a_folder_that_does_not_exist(tmp_path):
    r = CliRunner().invoke(app, ["recording", "recover", str(tmp_path / "nonexistent")])
    out = " ".join(r.output.split())  # rich wraps long lines
    assert r.exit_code == 2
    assert "no such folder" in out and "meta.json" not in out
    f = tmp_path / "afile"
    f.write_text("x")
    r = CliRunner().invoke(app, ["recording", "recover", str(f)])
    assert r.exit_code == 2 and "not a folder" in " ".join(r.output.split())
