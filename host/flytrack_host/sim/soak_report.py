"""The soak's analysis (sim/soak.py), from a run's figures and its samples: the series, each process's memory
growth by a linear fit, the first and last latency windows, what an 8 h and a 24 h recording would cost,
the PNG figure of every series against time, soak.json and the printed summary. `finish` is all of it, and
`--from-json` runs it again on a soak's files without a new run.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.sim.soak_sampling import MB, hist_percentile, merge_hists

FIT_SKIP_S = 300.0  # memory is fitted after the first 5 minutes ...
SHORT_RUN_FIT_FRACTION = 0.2  # ... or after the first 20 % when 5 minutes is more than that (under 25 min)
GROWTH_GOAL_MB_PER_H = 1.0
LATENCY_WINDOW_S = 600.0  # last 10 minutes against the first 10 ...
LATENCY_WINDOW_FRACTION = 1.0 / 6.0  # ... or a sixth of the run each for a run under an hour
LATENCY_GOAL_CHANGE = 0.10
PROJECT_HOURS = (8.0, 24.0)
FINALISE_SPLIT_S = 60.0  # a finalise longer than this: recordings would better be split into parts


def linear_fit(t_h: np.ndarray, y: np.ndarray) -> dict[str, float] | None:
    """Slope per hour of y against time by least squares, its standard error, and the points used."""
    ok = np.isfinite(t_h) & np.isfinite(y)
    t_h, y = t_h[ok], y[ok]
    if len(t_h) < 3 or np.ptp(t_h) <= 0:
        return None
    (slope, icpt), cov = np.polyfit(t_h, y, 1, cov=True)
    return {"slope_per_h": float(slope), "stderr_per_h": float(math.sqrt(max(cov[0, 0], 0.0))),
            "intercept": float(icpt), "points": len(t_h), "from_s": float(t_h[0] * 3600),
            "to_s": float(t_h[-1] * 3600)}


def series(samples: list[dict[str, Any]]) -> dict[str, Any]:
    """Every sampled figure as a list over the samples (None where it was not read)."""
    t = [s["t_s"] for s in samples]
    out: dict[str, Any] = {"t_s": t, "end": [bool(s.get("end")) for s in samples], "proc": {}}
    names: list[str] = []
    for s in samples:
        for n in (s.get("proc") or {}):
            if n != "error" and n not in names:
                names.append(n)
    for n in names:
        keys: list[str] = []
        for s in samples:
            for k in ((s.get("proc") or {}).get(n) or {}):
                if k not in keys:
                    keys.append(k)
        out["proc"][n] = {k: [((s.get("proc") or {}).get(n) or {}).get(k) for s in samples] for k in keys}
    for part in ("frames", "queues", "disk", "clients", "page", "closed_loop"):
        keys = []
        for s in samples:
            for k, v in (s.get(part) or {}).items():
                if k not in keys and k != "error" and not isinstance(v, str):
                    keys.append(k)
        out[part] = {k: [(s.get(part) or {}).get(k) for s in samples] for k in keys}
    out["latency"] = {k: [(s.get("latency") or {}).get(k) for s in samples] for k in ("n", "p50_ms", "p99_ms")}
    return out


def sim_cameras_expected_growth(cameras: int, fps: float) -> float:
    """MB/h the simulated cameras' process grows by design: its per-frame timing arrays (sim/frames.py
    FrameFeeder: shared memory sized for the whole run, one float64 per frame for the hand-over, the trigger
    edge and its true time, and one per camera for the write) are touched a frame at a time."""
    return (cameras + 3) * 8 * fps * 3600 / MB


def memory_growth(sr: dict[str, Any], duration_s: float, expected: dict[str, tuple[float, str]] | None = None
                  ) -> dict[str, Any]:
    """Each process's memory growth (MB/h) by a linear fit after the first 5 minutes (the first 20 % for a
    run under 25 minutes): RSS for a process, PSS summed for the browser's tree of processes."""
    short = duration_s * SHORT_RUN_FIT_FRACTION < FIT_SKIP_S
    skip = duration_s * SHORT_RUN_FIT_FRACTION if short else FIT_SKIP_S
    t = np.asarray(sr["t_s"], dtype=float)
    out: dict[str, Any] = {"fit_after_s": skip, "short_run": short,
                           "rule": (f"after the first 20 % of the run ({skip:.0f} s): the run is under 25 minutes"
                                    if short else "after the first 5 minutes"),
                           "goal_mb_per_h": GROWTH_GOAL_MB_PER_H, "processes": {}}
    for name, figs in sr["proc"].items():
        key = "pss_mb" if name == "browser" else "rss_mb"
        y = np.asarray([np.nan if v is None else v for v in figs.get(key, [])], dtype=float)
        sel = (t >= skip - 1e-6) & ~np.asarray(sr["end"], dtype=bool)
        fit = linear_fit(t[sel] / 3600.0, y[sel]) if len(y) == len(t) else None
        d: dict[str, Any] = {"memory": key, "fit": fit}
        if expected and name in expected:  # growth the simulation has by design, to compare with
            d["expected_mb_per_h"], d["expected_why"] = expected[name]
        if fit is not None:
            slope, err = fit["slope_per_h"], fit["stderr_per_h"]
            d["growth_mb_per_h"] = slope
            d["meets_goal"] = slope < GROWTH_GOAL_MB_PER_H
            # The goal is decided only when the slope is 2 standard errors clear of it either way; a run
            # too short or too noisy for that says so.
            d["verdict"] = ("met" if slope + 2 * err < GROWTH_GOAL_MB_PER_H else
                            "missed" if slope - 2 * err > GROWTH_GOAL_MB_PER_H else "within noise")
            # Whether the run was long and steady enough to tell 1 MB/h from nothing at all.
            d["resolved"] = 2.0 * err < GROWTH_GOAL_MB_PER_H
            run = ~np.asarray(sr["end"], dtype=bool)  # first and last of the run (the end sample left out)
            finite = y[run & np.isfinite(y)]
            d["first_mb"], d["last_mb"] = float(finite[0]), float(finite[-1])
            fds = [v for v, r in zip(figs.get("fds", []), run, strict=False) if v is not None and r]
            thr = [v for v, r in zip(figs.get("threads", []), run, strict=False) if v is not None and r]
            d["fds_first_last"] = [fds[0], fds[-1]] if fds else None
            d["threads_first_last"] = [thr[0], thr[-1]] if thr else None
        out["processes"][name] = d
    return out


def latency_windows(samples: list[dict[str, Any]], duration_s: float) -> dict[str, Any]:
    """Latency P99 of the first and the last window (10 minutes; a sixth of a run under an hour, and at
    least two sample periods), each the merged histograms of the samples whose interval's middle lies in
    it."""
    from flytrack_host.recording.latency import BIN_MS

    scaled = duration_s < 6 * LATENCY_WINDOW_S
    w = duration_s * LATENCY_WINDOW_FRACTION if scaled else LATENCY_WINDOW_S
    lat = [(s["t_s"] - s["window_s"], s["t_s"], s["latency"]) for s in samples
           if isinstance(s.get("latency"), dict) and "bins" in s["latency"]]
    # At least two sample periods a window, and a sample belongs to the window its interval's middle is in:
    # on a loaded machine a sample comes late, and its interval then starts before the window's edge.
    period = float(np.median([b - a for a, b, _ in lat])) if lat else 0.0
    w = max(w, 2.0 * period)
    first = [(a, b, x) for a, b, x in lat if 0.0 < 0.5 * (a + b) <= w + 1e-6]
    last = [(a, b, x) for a, b, x in lat if duration_s - w - 1e-6 <= 0.5 * (a + b) <= duration_s + 1e-6]
    out: dict[str, Any] = {"window_s": w, "scaled": scaled,
                           "rule": (f"a sixth of the run each ({w:.0f} s): the run is under an hour" if scaled
                                    else "the first and the last 10 minutes"),
                           "goal_change": LATENCY_GOAL_CHANGE}
    for name, ws in (("first", first), ("last", last)):
        bins, counts, over = merge_hists([x for _, _, x in ws])
        out[name] = {"samples": len(ws), "frames": int(sum(counts)) + len(over),
                     # the samples' intervals merged: the window as sampled (whole sample periods)
                     "from_s": min((a for a, _, _ in ws), default=math.nan),
                     "to_s": max((b for _, b, _ in ws), default=math.nan),
                     "p50_ms": hist_percentile(bins, counts, over, 50, BIN_MS),
                     "p99_ms": hist_percentile(bins, counts, over, 99, BIN_MS)}
    a, b = out["first"]["p99_ms"], out["last"]["p99_ms"]
    if math.isfinite(a) and math.isfinite(b) and a > 0:
        out["p99_change"] = b / a - 1.0
        out["meets_goal"] = abs(b / a - 1.0) <= LATENCY_GOAL_CHANGE
    return out


def projections(sr: dict[str, Any], growth: dict[str, Any], duration_s: float, finalise_s: float | None,
                raw_end: int, h5_end: int, readback: dict[str, Any] | None, scaling: dict[str, Any] | None,
                free_bytes: int, parts: dict[str, Any] | None = None) -> dict[str, Any]:
    """What an 8 h and a 24 h recording would cost, from the rates measured here. A recording in parts:
    stop finalises the last part only, so that is projected from the bytes finalised at stop and a part's
    size at this rate (not from the whole recording's), and a part-by-part reader's memory is two parts."""
    t = np.asarray(sr["t_s"], dtype=float)
    rec = np.asarray([np.nan if v is None else v for v in sr["disk"].get("recording_bytes", [])], dtype=float)
    fit = linear_fit(t / 3600.0, rec) if len(rec) == len(t) else None
    raw_per_h = fit["slope_per_h"] if fit else (raw_end / (duration_s / 3600.0) if duration_s > 0 else math.nan)
    h5_ratio = h5_end / raw_end if raw_end else math.nan
    expo = (scaling or {}).get("exponent")
    at_stop = (parts or {}).get("finalise_at_stop_bytes") or raw_end
    out: dict[str, Any] = {"raw_bytes_per_h": raw_per_h, "h5_to_raw": h5_ratio, "free_bytes_now": free_bytes,
                           "finalise_s_per_gb": finalise_s / (at_stop / 1e9) if finalise_s and at_stop else None,
                           "finalise_exponent": expo, "hours": {}, "in_parts": parts is not None}
    for hours in PROJECT_HOURS:
        raw = raw_per_h * hours
        scale = raw / raw_end if raw_end else math.nan
        d: dict[str, Any] = {"raw_bytes": raw, "h5_bytes": raw * h5_ratio, "disk_bytes": raw * (1 + h5_ratio)}
        d["fits_free_disk_now"] = bool(d["disk_bytes"] < free_bytes)
        if finalise_s is not None and parts is not None:
            part = _part_bytes_at(raw_per_h, parts, raw)  # the last part, at most
            d["finalise_s"] = out["finalise_s_per_gb"] * part / 1e9 if out["finalise_s_per_gb"] else finalise_s
            d["part_bytes"] = part
            d["read_by_parts_ram_bytes"] = 2 * part
            d["finalise_over_a_minute"] = bool(d["finalise_s"] > FINALISE_SPLIT_S)
        elif finalise_s is not None:
            d["finalise_s"] = finalise_s * scale  # linear in length
            if expo is not None:
                d["finalise_s_power_law"] = finalise_s * scale ** expo
            d["finalise_over_a_minute"] = bool(max(d["finalise_s"], d.get("finalise_s_power_law", 0.0))
                                               > FINALISE_SPLIT_S)
        if readback:  # whole (load_recording)
            d["read_back_s"] = readback["cold_s"] * scale
            d["read_back_ram_bytes"] = readback["table_bytes"] * scale
        mem, unresolved = {}, []
        for name, g in growth["processes"].items():
            if "growth_mb_per_h" in g:
                mem[name] = g["last_mb"] + g["growth_mb_per_h"] * (hours - duration_s / 3600.0)
                if g["verdict"] == "within noise":
                    unresolved.append(name)
        d["memory_mb"] = mem
        d["memory_growth_within_noise"] = unresolved  # these projections rest on a slope within its noise
        out["hours"][f"{hours:g}"] = d
    return out


def _part_bytes_at(raw_per_h: float, parts: dict[str, Any], total: float) -> float:
    """A part's size at this recording rate: part_seconds of it or part_bytes, whichever first."""
    limits = [total]
    if parts.get("part_seconds"):
        limits.append(raw_per_h * parts["part_seconds"] / 3600.0)
    if parts.get("part_bytes"):
        limits.append(float(parts["part_bytes"]))
    return min(limits)


def plot(sr: dict[str, Any], path: Path, title: str, fit_after_s: float | None = None,
         windows: list[tuple[float, float]] | None = None) -> Path:
    """Every series against time: a 3 x 3 grid. `fit_after_s` marks where the memory fits start, `windows`
    ((from, to) s, each) the latency windows compared."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(sr["t_s"], dtype=float) / 60.0
    fig, axes = plt.subplots(3, 3, figsize=(17, 12), constrained_layout=True)
    fig.suptitle(title)

    def line(ax: Any, ys: list | None, label: str, scale: float = 1.0, **kw: Any) -> None:
        if not ys:
            return
        y = np.asarray([np.nan if v is None else v * scale for v in ys], dtype=float)
        ax.plot(t[: len(y)], y, label=label, **kw)

    def edge_style(name: str) -> dict[str, Any]:
        return {"lw": 0.8, "alpha": 0.6} if name.startswith("edge ") else {"lw": 1.6}

    procs = sr["proc"]
    ax = axes[0, 0]
    for name, figs in procs.items():  # growth since the first sample: the absolute sizes differ 100-fold
        ys = figs.get("pss_mb" if name == "browser" else "rss_mb") or []
        first = next((v for v in ys if v is not None), None)
        if first is not None:
            line(ax, [None if v is None else v - first for v in ys], f"{name} ({first:.0f} MB)", **edge_style(name))
    ax.set_ylabel("memory since the first sample (MB)")
    ax.set_title("resident memory (browser: PSS of its processes)", fontsize=9)
    if fit_after_s is not None:
        ax.axvline(fit_after_s / 60.0, color="0.5", ls=":", lw=1)  # the growth is fitted from here
    ax.legend(fontsize=6, ncol=2)
    for ax, key, ylabel in ((axes[0, 1], "fds", "open files"), (axes[0, 2], "threads", "threads")):
        for name, figs in procs.items():
            line(ax, figs.get(key), name, **edge_style(name))
        ax.set_ylabel(ylabel)
    ax = axes[1, 0]
    line(ax, sr["latency"].get("p50_ms"), "P50", marker=".")
    line(ax, sr["latency"].get("p99_ms"), "P99", marker=".")
    ax.set_ylabel("host latency, trigger -> 3D (ms), per sample")
    for a, b in windows or []:  # the first and the last window compared, as sampled
        if math.isfinite(a) and math.isfinite(b):
            ax.axvspan(a / 60.0, b / 60.0, color="tab:green", alpha=0.1)
    ax.legend(fontsize=7)
    ax = axes[1, 1]
    q = sr["queues"]
    line(ax, q.get("recorder_bytes"), "recorder queue (kB)", 1e-3)
    line(ax, q.get("udp_rx_queue_bytes"), "host socket rx queue (kB)", 1e-3)
    line(ax, q.get("live_client_pending_bytes"), "live clients' backlog (kB)", 1e-3)
    line(ax, q.get("live_backlog_frames"), "live server backlog (frames)")
    ax.set_ylabel("queue depth at the sample")
    ax.legend(fontsize=7)
    ax = axes[1, 2]
    f = sr["frames"]
    for k in ("not_received", "lost", "late", "behind_skipped", "stalls", "loop_errors"):
        line(ax, f.get(k), k)
    line(ax, q.get("udp_drops"), "kernel udp drops")
    line(ax, q.get("recorder_dropped_rows"), "recording rows dropped")
    ax.set_ylabel("frames (cumulative; not_received: at the sample)")
    ax.legend(fontsize=7)
    ax = axes[2, 0]
    d = sr["disk"]
    line(ax, d.get("recording_bytes"), "recording (GB)", 1e-9)
    ax.set_ylabel("recording size, raw files (GB)")
    ax2 = ax.twinx()
    line(ax2, d.get("free_bytes"), "free disk (GB)", 1e-9, color="tab:red")
    ax2.set_ylabel("free disk (GB)", color="tab:red")
    for a in (ax, ax2):
        a.ticklabel_format(axis="y", useOffset=False, style="plain")
    ax = axes[2, 1]
    c, p = sr["clients"], sr["page"]
    for k, lab in (("sse_updates", "Braid Update events"), ("sse_end_of_frame", "Braid EndOfFrame"),
                   ("pose_datagrams", "pose datagrams")):
        line(ax, c.get(k), lab)
    line(ax, p.get("updates"), "page updates")
    line(ax, f.get("tracked"), "frames tracked")
    ax.set_ylabel("received (cumulative)")
    ax.set_yscale("symlog")
    ax.legend(fontsize=7)
    ax = axes[2, 2]
    cl = sr["closed_loop"]
    line(ax, cl.get("fired"), "rules fired")
    line(ax, cl.get("modbus_writes"), "Modbus coil writes")
    line(ax, cl.get("failed"), "firings failed")
    ax.set_ylabel("closed loop (cumulative)")
    ax2 = ax.twinx()
    line(ax2, p.get("js_heap_mb"), "page JS heap (MB)", color="tab:purple", ls="--")
    ax2.set_ylabel("page JS heap (MB)", color="tab:purple")
    ax.legend(fontsize=7, loc="upper left")
    for ax in axes.flat:
        ax.set_xlabel("minutes since the trigger started")
        ax.grid(alpha=0.3)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _fmt(x: Any, spec: str = ".2f") -> str:
    return "n/a" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x


def finish(result: dict[str, Any], samples: list[dict[str, Any]], out: Path, say: Any = print) -> dict[str, Any]:
    """From a run's figures and its samples: the series, the fits, the windows, the projections; soak.json,
    soak.png and the summary printed. `--from-json` runs it again on a soak's files (no new run)."""
    sr = series(samples)
    duration = result["duration_s"]
    rec = result["recording"]
    rate = result["rate"]
    growth = memory_growth(sr, duration, {"sim cameras": (
        sim_cameras_expected_growth(rate["cameras"], rate["fps"]),
        "its per-frame timing arrays, sized for the run, touched a frame at a time (simulation only)")})
    result["memory_growth"] = growth
    if "free_bytes_end" not in result:  # a soak.json written before it was kept apart
        result["free_bytes_end"] = (result.get("projections") or {}).get("free_bytes_now", 0)
    result["latency_windows"] = latency_windows(samples, duration)
    result["projections"] = projections(sr, growth, duration, rec["finalise_s"], rec["raw_bytes"], rec["h5_bytes"],
                                        rec["read_back"], rec["finalise_scaling"], result["free_bytes_end"],
                                        rec.get("parts"))
    result["series"] = sr
    m0 = result["machine"]["start"]
    title = (f"FlyTrack soak: {rate['cameras']} cameras x {rate['animals']} animals x {rate['fps']:g} fps, "
             f"{duration / 60:.1f} min, {m0['cpus_usable']} CPUs")
    lw = result["latency_windows"]
    result["png"] = str(plot(sr, out / "soak.png", title, fit_after_s=growth["fit_after_s"],
                             windows=[(lw[k]["from_s"], lw[k]["to_s"]) for k in ("first", "last")]))
    result["json"] = str(out / "soak.json")
    Path(result["json"]).write_text(json.dumps(_jsonable(result), indent=1))
    for line in summary_lines(result):
        say(line)
    return result


def _parts_summary(recording: Path | None, recorder: dict[str, Any]) -> dict[str, Any] | None:
    """A recording in parts: how many, their limits, what stop finalised (None: an unparted recording)."""
    from flytrack_host.recording.parts import read_parts_json

    if recording is None or not recording.is_dir():
        return None
    about = read_parts_json(recording)
    return {"count": recorder.get("parts", 0), "part_seconds": about.get("part_seconds"),
            "part_bytes": about.get("part_bytes"), "largest_part_bytes": recorder.get("largest_part_bytes", 0),
            "finalise_at_stop_bytes": recorder.get("finalise_at_stop_bytes", 0),
            "finalised_in_background": recorder.get("parts_finalised_background", 0)}


VERDICT = {"met": "met", "missed": "MISSED", "within noise": "undecided (within 2 standard errors of it)"}


def summary_lines(r: dict[str, Any]) -> list[str]:
    fr, g, lw, rec, pj = r["frames"], r["memory_growth"], r["latency_windows"], r["recording"], r["projections"]
    rate = r["rate"]
    yes = {True: "yes", False: "NO"}
    out = ["", f"=== soak: {rate['cameras']} cameras x {rate['animals']} animals x {rate['fps']:g} fps, "
           f"{r['duration_s'] / 60:.1f} min, {r['samples']} samples ==="]
    if r["probes"]:
        out.append("rate: " + ", ".join(f"{p['cameras']}x{p['animals']}x{p['fps']:g} fps "
                                        f"{'sustained' if p['sustained'] else 'not'}" for p in r["probes"]))
    out.append(f"frames lost: {fr['frames_lost']} of {fr['camera_frames_sent']} camera frames (goal 0: "
               f"{yes[fr['frames_lost'] == 0]}); sequence gaps {fr['packets_lost']}, kernel drops "
               f"{fr['kernel_udp_drops']}, late {fr['frames_late']}, misnumbered {fr['frames_misnumbered']}, "
               f"recorded not tracked {fr['frames_behind_skipped']}, recording rows dropped "
               f"{fr['recorder_rows_dropped']}")
    out.append(f"host kept up: {fr['frames_in_time']}/{fr['frames_triggered']} frames tracked within a period; "
               f"camera lateness P99 {_fmt(fr['camera_lateness_ms'].get('p99_ms'), '.1f')} ms")
    if not r["sustained_whole_run"]:
        out.append("NOT sustained over the whole run: " + "; ".join(r["why_not_sustained"]))
    out.append(f"memory growth, linear fit {g['rule']} (goal < {g['goal_mb_per_h']:g} MB/h):")
    for name, d in g["processes"].items():
        if "growth_mb_per_h" not in d:
            out.append(f"  {name:18s} too few samples to fit")
            continue
        fit = d["fit"]
        fds, thr = d.get("fds_first_last"), d.get("threads_first_last")
        out.append(f"  {name:18s} {d['growth_mb_per_h']:+8.2f} +- {fit['stderr_per_h']:.2f} MB/h "
                   f"({d['memory']} {d['first_mb']:.1f} -> {d['last_mb']:.1f} MB, {fit['points']} points) "
                   f"goal {VERDICT[d['verdict']]}"
                   + (f"; files {fds[0]}->{fds[1]}" if fds else "") + (f", threads {thr[0]}->{thr[1]}" if thr else ""))
        if "expected_mb_per_h" in d:
            out.append(f"  {'':18s} expected {d['expected_mb_per_h']:.2f} MB/h: {d['expected_why']}")
    f, la = lw["first"], lw["last"]
    out.append(f"latency P99, {lw['rule']}: first {_fmt(f['p99_ms'])} ms ({f['frames']} frames, "
               f"{_fmt(f['from_s'], '.0f')}-{_fmt(f['to_s'], '.0f')} s), last {_fmt(la['p99_ms'])} ms ({la['frames']} "
               f"frames, {_fmt(la['from_s'], '.0f')}-{_fmt(la['to_s'], '.0f')} s): change "
               + (f"{lw['p99_change'] * 100:+.1f} % (goal within {lw['goal_change'] * 100:.0f} %: "
                  f"{yes[lw['meets_goal']]})" if "p99_change" in lw else "n/a"))
    whole = r["latency_whole_run"]
    out.append(f"latency over the run: P50 {_fmt(whole.get('p50_ms'))} ms, P99 {_fmt(whole.get('p99_ms'))} ms, "
               f"max {_fmt(whole.get('max_ms'))} ms")
    rb = rec["read_back"] or {}
    pa = rec.get("parts")
    if pa:
        every = _fmt((pa['part_seconds'] or 0) / 60, '.0f')
        out.append(f"recording in {pa['count']} parts (a new one every {every} min "
                   f"or {(pa['part_bytes'] or 0) / 1e9:.2f} GB), {pa['finalised_in_background']} finalised in the "
                   f"background; at stop {pa['finalise_at_stop_bytes'] / MB:.1f} MB finalised, largest part "
                   f"{pa['largest_part_bytes'] / MB:.1f} MB")
    out.append(f"recording: raw {rec['raw_bytes'] / MB:.1f} MB, HDF5 {rec['h5_bytes'] / MB:.1f} MB; finalised in "
               f"{_fmt(rec['finalise_s'])} s by the host at stop; read back whole in {_fmt(rb.get('cold_s'))} s "
               f"from disk ({'page cache dropped' if rb.get('cache_dropped') else 'cache NOT dropped'}), "
               f"{_fmt(rb.get('warm_s'))} s warm, {rb.get('table_bytes', 0) / MB:.1f} MB of tables in RAM")
    sc = rec["finalise_scaling"]
    if sc:
        out.append("finalise again, time against length: " + ", ".join(
            f"{p['raw_bytes'] / MB:.0f} MB {p['finalise_s']:.2f} s" for p in sc["points"])
            + (f"; exponent {sc['exponent']:.2f} (1 = linear)" if "exponent" in sc else ""))
    out.append(f"rates: recording {pj['raw_bytes_per_h'] / 1e9:.2f} GB/h raw (+{pj['h5_to_raw'] * 100:.0f} % as "
               f"HDF5 beside it), finalise {_fmt(pj['finalise_s_per_gb'])} s/GB")
    for h, d in pj["hours"].items():
        mem = d["memory_mb"]
        edges = [v for k, v in mem.items() if k.startswith("edge ")]
        fin = f"finalise {_fmt(d.get('finalise_s'), '.0f')} s"
        if "finalise_s_power_law" in d:
            fin += f" ({_fmt(d['finalise_s_power_law'], '.0f')} s by the measured exponent)"
        if "part_bytes" in d:
            fin = (f"finalise at stop {_fmt(d.get('finalise_s'), '.1f')} s (the last part, "
                   f"{d['part_bytes'] / 1e9:.2f} GB), read part by part in "
                   f"{d['read_by_parts_ram_bytes'] / 1e9:.2f} GB RAM")
        out.append(f"{h} h recording: disk {d['disk_bytes'] / 1e9:.1f} GB (raw {d['raw_bytes'] / 1e9:.1f} + HDF5 "
                   f"{d['h5_bytes'] / 1e9:.1f}; fits the {pj['free_bytes_now'] / 1e9:.0f} GB free now: "
                   f"{yes[d['fits_free_disk_now']]}), {fin}"
                   + (" -> over a minute: split recordings into parts" if d.get("finalise_over_a_minute") else "")
                   + f", read back {_fmt(d.get('read_back_s'), '.0f')} s needing "
                   f"{d.get('read_back_ram_bytes', 0) / 1e9:.1f} GB RAM; memory host {_fmt(mem.get('host'), '.0f')} MB"
                   + (f", edges up to {max(edges):.0f} MB" if edges else "")
                   + (f" (growth within noise for {', '.join(d['memory_growth_within_noise'])})"
                      if d["memory_growth_within_noise"] else ""))
    cl = r["closed_loop"]
    for name, d in cl.items():
        if isinstance(d, dict):
            scored = (f"missed {d['missed']}, false {d['false_fires']}" if d.get("missed") is not None
                      else "not scored (only the latest firings were kept; the recording has them all)")
            out.append(f"closed loop {name}: fired {d['fired']}/{d['expected']}, {scored}, ack P50/P99 "
                       f"{_fmt(d['latency_ms_p50'])}/{_fmt(d['latency_ms_p99'])} ms; "
                       f"Modbus writes {cl.get('modbus_coil_writes')}")
    ce = r["clients_end"].get("clients") or {}
    pg = r["clients_end"].get("page") or {}
    if ce:
        # Connections and errors while the rig ran (the last sample before its end): once the host stops,
        # the stream ends and the client's attempts to reconnect fail, as they should.
        errs = [e for e, end in zip(r["series"]["clients"].get("sse_errors", []), r["series"]["end"], strict=False)
                if not end and e is not None]
        conns = [e for e, end in zip(r["series"]["clients"].get("sse_connects", []), r["series"]["end"], strict=False)
                 if not end and e is not None]
        out.append(f"clients: Braid {ce.get('sse_updates')} Update / {ce.get('sse_end_of_frame')} EndOfFrame events "
                   f"({conns[-1] if conns else 'n/a'} connection(s), {errs[-1] if errs else 'n/a'} errors while "
                   "the rig ran), pose "
                   f"{ce.get('pose_datagrams')} datagrams; page {pg.get('updates')} updates, JS heap "
                   f"{_fmt(pg.get('js_heap_mb'), '.1f')} MB")
    if r["sample_errors"]:
        out.append(f"sample errors: {r['sample_errors']} (last: {r['last_sample_error']})")
    for n in r["notes"]:
        out.append(f"note: {n}")
    out.append(f"json {r['json']}")
    out.append(f"png  {r['png']}")
    return out
