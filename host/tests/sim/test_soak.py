"""The soak's machinery (sim/soak.py, soak_sampling.py, soak_report.py) on a tiny rig: a few sampling periods
of 2 cameras, 1 animal, with the recording, the live page in Chromium, the Braid and pose clients and the
closed loop; soak.json holds every series, the fits and the windows, and soak.png is written. The figures
themselves are not judged here (they are this machine's); the run's length is the simulated rig's own, no
test code waits on a clock."""

from __future__ import annotations

import json
import math

import pytest

from flytrack_host.live.web import browser as browser_mod
from flytrack_host.recording.latency import BIN_MS, LatencyStats
from flytrack_host.sim import soak as soak_mod
from flytrack_host.sim import soak_report, soak_sampling
from flytrack_host.sim.run import find_edge_binary

SAMPLE_S = 1.0
SECONDS = 6.0


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    try:
        find_edge_binary()
    except Exception as exc:
        pytest.fail(f"{exc}")
    why = browser_mod.missing()
    if why:
        pytest.fail(why)
    out = tmp_path_factory.mktemp("soak")
    cfg = soak_mod.SoakConfig(minutes=SECONDS / 60.0, sample_s=SAMPLE_S, cameras=2, animals=1, fps=50.0,
                              probe_s=0.0, out=out)
    return soak_mod.soak(cfg, say=lambda s: None), out


@pytest.mark.slow
def test_json_has_every_series_over_the_samples(result) -> None:  # noqa: ANN001
    r, out = result
    data = json.loads((out / "soak.json").read_text())
    assert data["samples"] == r["samples"] >= SECONDS / SAMPLE_S - 1
    sr = data["series"]
    n = len(sr["t_s"])
    assert n == data["samples"] and sr["t_s"] == sorted(sr["t_s"])
    procs = sr["proc"]
    assert {"host", "edge cam1", "edge cam2", "sim cameras", "modbus server", "clients", "browser"} <= set(procs)
    for name, figs in procs.items():
        for key in ("rss_mb", "anon_mb", "pss_mb", "fds", "threads"):
            assert len(figs[key]) == n, (name, key)
        assert figs["rss_mb"][0] > 0 and figs["threads"][0] >= 1, name
    assert procs["browser"]["processes"][0] >= 2  # chromedriver and chromium's own processes
    for part, keys in (
        ("frames", ("triggered", "received", "not_received", "tracked", "lost", "late", "behind_skipped")),
        ("queues", ("recorder_bytes", "udp_rx_queue_bytes", "udp_drops", "live_backlog_frames",
                    "live_client_pending_bytes", "pose_datagrams_sent")),
        ("latency", ("n", "p50_ms", "p99_ms")),
        ("disk", ("recording_bytes", "free_bytes")),
        ("clients", ("sse_updates", "sse_end_of_frame", "pose_datagrams")),
        ("page", ("updates", "js_heap_mb")),
        ("closed_loop", ("fired", "modbus_writes")),
    ):
        for k in keys:
            assert len(sr[part][k]) == n, (part, k)
    # The rig ran and every client got it, as the samples saw.
    assert sr["frames"]["tracked"][-1] > 0 and sr["disk"]["recording_bytes"][-1] > sr["disk"]["recording_bytes"][0]
    assert sr["clients"]["sse_updates"][-1] > 0 and sr["clients"]["pose_datagrams"][-1] > 0
    assert sr["page"]["updates"][-1] > 0
    assert any(p is not None and math.isfinite(p) for p in sr["latency"]["p99_ms"])
    # Every sample's line is in samples.jsonl too (written as the run went).
    assert len((out / "run" / "samples.jsonl").read_text().splitlines()) == n


@pytest.mark.slow
def test_fits_windows_and_projections_are_computed(result) -> None:  # noqa: ANN001
    r, _ = result
    g = r["memory_growth"]
    assert g["short_run"] and "20 %" in g["rule"]
    assert g["fit_after_s"] == pytest.approx(0.2 * r["duration_s"])
    host = g["processes"]["host"]
    assert host["fit"]["points"] >= 3 and math.isfinite(host["growth_mb_per_h"])
    assert host["fit"]["from_s"] >= g["fit_after_s"] - 1e-6
    assert isinstance(host["meets_goal"], bool) and host["verdict"] in ("met", "missed", "within noise")
    # The simulated cameras grow by design (per-frame timing arrays): what they should is said beside it.
    assert g["processes"]["sim cameras"]["expected_mb_per_h"] == pytest.approx((2 + 3) * 8 * 50.0 * 3600 / 1e6)
    lw = r["latency_windows"]
    assert lw["scaled"] and lw["window_s"] == pytest.approx(max(r["duration_s"] / 6, 2 * SAMPLE_S), rel=0.2)
    assert lw["first"]["frames"] > 0 and lw["last"]["frames"] > 0 and math.isfinite(lw["last"]["p99_ms"])
    assert lw["first"]["samples"] >= 1 and lw["last"]["samples"] >= 1
    fr = r["frames"]
    assert fr["camera_frames_sent"] > 0 and fr["frames_lost"] >= 0
    rec = r["recording"]
    assert rec["finalise_s"] > 0 and rec["read_back"]["cold_s"] > 0 and rec["read_back"]["table_bytes"] > 0
    assert [p["fraction"] for p in rec["finalise_scaling"]["points"]] == [0.25, 0.5, 1.0]
    pj = r["projections"]
    for h in ("8", "24"):
        d = pj["hours"][h]
        assert d["disk_bytes"] > 0 and d["finalise_s"] > 0 and "host" in d["memory_mb"]
    assert pj["hours"]["24"]["raw_bytes"] == pytest.approx(3 * pj["hours"]["8"]["raw_bytes"])


@pytest.mark.slow
def test_png_is_written(result) -> None:  # noqa: ANN001
    r, out = result
    png = out / "soak.png"
    assert r["png"] == str(png)
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000


def test_window_percentiles_match_the_hosts_histogram() -> None:
    """A sample's latency window (the growth of the host's histogram) gives the host's own percentiles."""
    st = LatencyStats()
    win = soak_sampling.LatencyWindow(st)
    for i in range(1000):
        st.row(i, 0.0, 0.0, 0.0, (0.5 + (i % 97) * 0.13) / 1e3, 2, 0)
    st.row(1000, 0.0, 0.0, 0.0, 1.7, 2, 0)  # past the histogram's end: kept exactly
    w = win.take()
    assert w["n"] == 1001 and w["over_ms"] == [pytest.approx(1700.0)]
    assert w["p50_ms"] == pytest.approx(st.percentile("total", 50))
    assert w["p99_ms"] == pytest.approx(st.percentile("total", 99))
    assert soak_sampling.hist_percentile(w["bins"], w["counts"], w["over_ms"], 100, BIN_MS) == pytest.approx(1700.0)
    assert win.take()["n"] == 0  # the next window starts empty


def test_linear_fit_and_rate_ladder() -> None:
    import numpy as np

    t = np.linspace(0, 1, 13)
    fit = soak_report.linear_fit(t, 100 + 0.5 * t)
    assert fit["slope_per_h"] == pytest.approx(0.5) and fit["stderr_per_h"] < 1e-9 and fit["points"] == 13
    assert soak_report.linear_fit(t[:2], t[:2]) is None
    ladder = soak_mod.rate_ladder(soak_mod.SoakConfig(cameras=11, animals=10, fps=100, min_fps=5))
    assert ladder[0] == (11, 10, 100) and ladder[1] == (11, 10, 70)
    fps = [f for c, _, f in ladder if c == 11]
    assert fps == sorted(fps, reverse=True) and fps[-1] >= 5
    assert ladder[-1][0] == 2 and ladder[-1][2] == fps[-1]
