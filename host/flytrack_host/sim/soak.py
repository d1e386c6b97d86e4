"""The soak (issue 24, "A whole rig day"): the simulated rig for an hour, watched as it runs.

    python -m flytrack_host.sim.soak --minutes 60          (make soak SOAK_MINUTES=60)

The whole `flytrack demo` rig (sim/run.py): simulated cameras, one real `flytrack-edge` per camera, the
trigger firmware in simavr, the real host recording, the closed-loop rules of examples/closed_loop.toml
driving a real Modbus server (and the firmware's pulse line and a CAN bus), the live server with the page
open in headless Chromium, and a Braid event-stream client and a VR pose client in a process of their own
(sim/soak_clients.py).

First it finds the rate this machine sustains: short runs of the same set-up (`--probe-s`) from the asked
cameras x animals x fps down a ladder of frame rates (then of cameras), until one loses no frame, the host
tracks its frames in time, and the simulated cameras render every frame. Then the soak runs at that rate
for `--minutes`, and every `--sample-s` writes one line of samples/jsonl (nothing is kept in the host
process, whose memory is under test): resident memory, open files and threads of the host and of every
other process of the rig (/proc); the recorder's queue, the host socket's kernel queue and drops, the live
server's backlog; latency P50/P99 of the frames tracked since the last sample; frames lost, late,
untracked; the recording's size and the free disk; what the clients and the page got.

At the end: frames lost (goal 0); each process's memory growth by a linear fit after the first 5 minutes
(the first 20 % for runs under 25 minutes; goal < 1 MB/h); latency P99 of the last 10 minutes against
the first 10 (a sixth of the run each for runs under an hour; goal within 10 %); the time the host took to
finalise the recording, and to read it back whole; finalising a quarter, a half and all of the recording's
rows again, to see how its time grows with length; what an 8 h and a 24 h recording would cost (disk,
finalise time, read-back, memory), extrapolated from the figures measured. Written to soak.json and
soak.png (every series against time) in `--out`.

This module runs it and is its command line; sim/soak_sampling.py takes the samples, sim/soak_recording.py
measures the recording after the run, and sim/soak_report.py fits, projects, draws and prints.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from flytrack_host.sim.demo_config import ROOT, DemoConfig, DemoError
from flytrack_host.sim.soak_recording import finalise_scaling, h5_files, raw_bytes, read_back
from flytrack_host.sim.soak_report import _fmt, _parts_summary, finish
from flytrack_host.sim.soak_sampling import Sampler, load_samples

DEFAULT_RULES = ROOT / "examples" / "closed_loop.toml"
FPS_LADDER = 0.7  # each probe after a failed one asks this fraction of the rate before


@dataclass
class SoakConfig:
    minutes: float = 60.0
    sample_s: float = 60.0
    cameras: int = 11
    animals: int = 10
    fps: float = 100.0
    probe_s: float = 10.0  # 0: no probe; run at cameras x animals x fps as asked
    min_fps: float = 5.0
    out: Path = field(default_factory=lambda: ROOT / "build" / "soak")
    rules: Path | None = DEFAULT_RULES
    browser: bool = True
    clients: bool = True
    trigger: str = "auto"
    seed: int = 0
    scaling: bool = True  # finalise a quarter, a half and all of the rows again (time against length)


# --- one run ---------------------------------------------------------------------------------------
def run_once(cfg: SoakConfig, cameras: int, animals: int, fps: float, seconds: float, sample_s: float,
             out: Path) -> dict[str, Any]:
    """One run of the rig at this rate, sampled; the demo's report and the sampler's samples."""
    from flytrack_host.sim.run import run_demo

    out.mkdir(parents=True, exist_ok=True)
    sampler = Sampler(out, sample_s, cfg.browser, cfg.clients)
    demo = DemoConfig(cameras=cameras, animals=animals, fps=fps, seconds=seconds, seed=cfg.seed, out=out,
                      trigger=cfg.trigger, progress=False, rules=cfg.rules, score=False,
                      attach=[sampler.attach], on_running=[sampler.running])
    t0 = time.monotonic()
    try:
        report = run_demo(demo)
    finally:
        sampler.stop()
        end = sampler.close()
    wall = time.monotonic() - t0
    return {"report": report, "samples": load_samples(sampler.samples_path), "end": end, "wall_s": wall,
            "sample_errors": sampler.sample_errors, "last_sample_error": sampler.last_error,
            "samples_path": str(sampler.samples_path)}


def frames_summary(run: dict[str, Any]) -> dict[str, Any]:
    """Frames lost (handed to an edge, never received by the host), late, misnumbered and the rest, from the
    demo's report (exact, from the recording) and the last sample (the kernel's drops)."""
    r = run["report"]
    hs = r.host_summary or {}
    last = run["samples"][-1] if run["samples"] else {}
    q = last.get("queues", {})
    recorder = hs.get("recorder", {}) or {}
    return {
        "frames_triggered": r.frames_triggered,
        "camera_frames_sent": r.camera_frames_sent,
        "camera_frames_received": r.camera_frames_received,
        "frames_lost": max(0, r.camera_frames_sent - r.camera_frames_received),
        "packets_lost": r.packets_lost,  # gaps in the edges' sequence numbers
        "kernel_udp_drops": q.get("udp_drops"),
        "frames_late": r.packets_late,
        "frames_misnumbered": r.frames_misnumbered,
        "frames_untracked": hs.get("untracked", {}),
        "frames_behind_skipped": hs.get("behind_skipped", 0),
        "frames_tracked": r.frames_tracked,
        "frames_in_time": r.frames_in_time,
        "host_kept_up": r.host_kept_up,
        "frames_rendered": r.frames_rendered,
        "render_realtime_factor": r.render_realtime_factor,
        "camera_lateness_ms": r.exposure_lateness,
        "recorder_rows_dropped": sum((recorder.get("dropped_rows") or {}).values()),
        "recorder_write_errors": recorder.get("write_errors", 0),
    }


def sustained(fr: dict[str, Any], expected_frames: int) -> list[str]:
    """Why a run did not sustain its rate ([] when it did)."""
    why = []
    if fr["frames_lost"]:
        why.append(f"{fr['frames_lost']} camera frames lost")
    if fr["kernel_udp_drops"]:
        why.append(f"{fr['kernel_udp_drops']} datagrams dropped by the kernel")
    if not fr["host_kept_up"]:
        why.append(f"host tracked {fr['frames_in_time']}/{fr['frames_triggered']} frames within a period")
    if fr["frames_behind_skipped"]:
        why.append(f"{fr['frames_behind_skipped']} frames recorded, not tracked (host 1 s behind)")
    if fr["frames_rendered"] < expected_frames:
        why.append(f"simulated cameras rendered {fr['frames_rendered']}/{expected_frames} frames")
    elif fr["render_realtime_factor"] < 1.0:
        why.append(f"simulated cameras render at {fr['render_realtime_factor']:.2f}x real time")
    if fr["recorder_rows_dropped"]:
        why.append(f"{fr['recorder_rows_dropped']} recording rows dropped")
    return why


def rate_ladder(cfg: SoakConfig) -> list[tuple[int, int, float]]:
    """Rates to probe, the asked one first: frame rates down by FPS_LADDER to min_fps, then at min_fps
    fewer cameras."""
    out: list[tuple[int, int, float]] = []
    fps = cfg.fps
    while fps >= cfg.min_fps - 1e-9:
        out.append((cfg.cameras, cfg.animals, fps))
        nxt = float(math.floor(fps * FPS_LADDER))
        if nxt >= fps:
            break
        fps = nxt
    low = out[-1][2] if out else cfg.min_fps
    cams = cfg.cameras
    while cams > 2:
        cams = max(2, int(round(cams * FPS_LADDER)))
        out.append((cams, cfg.animals, low))
    return out


def find_rate(cfg: SoakConfig, say: Any) -> tuple[tuple[int, int, float], list[dict[str, Any]], bool]:
    """The first rate of the ladder that a short run of the whole set-up sustains."""
    probes: list[dict[str, Any]] = []
    ladder = rate_ladder(cfg)
    for cams, animals, fps in ladder:
        say(f"probe: {cams} cameras x {animals} animals x {fps:g} fps for {cfg.probe_s:g} s ...")
        run = run_once(cfg, cams, animals, fps, cfg.probe_s, max(1.0, cfg.probe_s / 4),
                       cfg.out / f"probe_{cams}x{animals}x{fps:g}")
        fr = frames_summary(run)
        expected = int(round(cfg.probe_s * fps))
        why = sustained(fr, expected)
        hs = run["report"].host_summary or {}
        probes.append({"cameras": cams, "animals": animals, "fps": fps, "seconds": cfg.probe_s,
                       "sustained": not why, "why_not": why, "frames": fr,
                       "latency_host": run["report"].latency_host, "cpu_seconds": run["report"].cpu_seconds,
                       "recording_finalize_s": hs.get("recording_finalize_s"),
                       "recording_raw_bytes": raw_bytes(run["report"].recording),
                       "wall_s": run["wall_s"]})
        lat = fr["camera_lateness_ms"]
        say(f"  {'sustained' if not why else 'NOT sustained: ' + '; '.join(why)} "
            f"(host latency P99 {_fmt(run['report'].latency_host.get('p99_ms'))} ms, camera lateness P99 "
            f"{_fmt(lat.get('p99_ms'))} ms)")
        if not why:
            return (cams, animals, fps), probes, True
    return ladder[-1], probes, False


def machine() -> dict[str, Any]:
    load = os.getloadavg()
    try:
        mem = int(Path("/proc/meminfo").read_text().split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        mem = 0
    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpus": os.cpu_count(), "cpus_usable": len(os.sched_getaffinity(0)), "cpu_model": model,
            "memory_bytes": mem, "load_average_1_5_15": list(load)}


# --- the soak --------------------------------------------------------------------------------------
def soak(cfg: SoakConfig, say: Any = print) -> dict[str, Any]:
    seconds = cfg.minutes * 60.0
    DemoConfig(cameras=cfg.cameras, animals=cfg.animals, fps=cfg.fps, seconds=seconds).check()
    if not cfg.sample_s > 0:
        raise DemoError(f"the sample period must be positive, got {cfg.sample_s}")
    cfg.out.mkdir(parents=True, exist_ok=True)
    m0 = machine()
    say(f"soak: {cfg.minutes:g} min, a sample every {cfg.sample_s:g} s; machine: {m0['cpus_usable']} CPUs "
        f"({m0['cpu_model']}), {m0['memory_bytes'] / 1e9:.1f} GB, load average "
        + "/".join(f"{x:.2f}" for x in m0["load_average_1_5_15"]))
    asked = (cfg.cameras, cfg.animals, cfg.fps)
    probes: list[dict[str, Any]] = []
    found = True
    if cfg.probe_s > 0:
        rate, probes, found = find_rate(cfg, say)
    else:
        rate = asked
    cams, animals, fps = rate
    if not found:
        say(f"no rate tried was sustained: the soak runs at the lowest, {cams} x {animals} x {fps:g} fps")
    elif rate != asked:
        say(f"this machine sustains {cams} cameras x {animals} animals x {fps:g} fps (asked "
            f"{asked[0]} x {asked[1]} x {asked[2]:g}): the soak runs at that")
    say(f"soak: {cams} cameras x {animals} animals x {fps:g} fps for {cfg.minutes:g} min, recording, live page "
        f"in Chromium: {'yes' if cfg.browser else 'no'}, Braid + pose clients: {'yes' if cfg.clients else 'no'}, "
        f"closed loop: {cfg.rules if cfg.rules else 'off'}")
    run = run_once(cfg, cams, animals, fps, seconds, cfg.sample_s, cfg.out / "run")
    report = run["report"]
    samples = run["samples"]
    say(f"run done: {len(samples)} samples, {run['wall_s']:.0f} s wall")
    fr = frames_summary(run)
    hs = report.host_summary or {}
    finalise_s = hs.get("recording_finalize_s")
    h5 = Path(report.recording) if report.recording else None
    raw_end = raw_bytes(report.recording)
    h5_end = sum(f.stat().st_size for f in h5_files(h5)) if h5 is not None and h5.exists() else 0
    parts = _parts_summary(h5, hs.get("recorder") or {})
    rb = read_back(h5) if h5 is not None and h5.exists() else None
    scaling = finalise_scaling(h5, cfg.out / "scaling") if cfg.scaling and h5 is not None and h5.exists() else None
    duration = float(samples[-1]["t_s"]) if samples else 0.0
    result: dict[str, Any] = {
        "config": asdict(cfg),
        "machine": {"start": m0, "end": machine()},
        "asked": {"cameras": asked[0], "animals": asked[1], "fps": asked[2]},
        "rate": {"cameras": cams, "animals": animals, "fps": fps, "sustained_in_probe": found,
                 "probed": cfg.probe_s > 0},
        "probes": probes,
        "duration_s": duration,
        "wall_s": run["wall_s"],
        "samples": len(samples),
        "sample_errors": run["sample_errors"],
        "last_sample_error": run["last_sample_error"],
        "frames": fr,
        "frames_lost_goal_met": fr["frames_lost"] == 0,
        "sustained_whole_run": not sustained(fr, int(round(seconds * fps))),
        "why_not_sustained": sustained(fr, int(round(seconds * fps))),
        "latency_whole_run": report.latency_host,
        "recording": {"h5": str(h5) if h5 else None, "raw_bytes": raw_end, "h5_bytes": h5_end,
                      "finalise_s": finalise_s, "read_back": rb, "finalise_scaling": scaling, "parts": parts},
        "free_bytes_end": shutil.disk_usage(cfg.out).free,
        "closed_loop": _closed_loop_summary(report.actuation),
        "clients_end": run["end"],
        "cpu_seconds": report.cpu_seconds,
        "cpu_placement": report.cpu_placement,
        "trigger": report.trigger,
        "notes": report.notes,
        "samples_file": run["samples_path"],
    }
    return finish(result, samples, cfg.out, say)


def _closed_loop_summary(act: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, d in (act or {}).get("rules", {}).items():
        out[name] = {k: d.get(k) for k in ("fired", "expected", "missed", "false_fires", "scored", "latency_ms_p50",
                                           "latency_ms_p99", "frame_error_max")}
    if act:
        out["modbus_coil_writes"] = act.get("modbus_coil_writes")
        out["can_frames"] = act.get("can_frames")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    d = SoakConfig()
    ap.add_argument("--minutes", type=float, default=d.minutes)
    ap.add_argument("--sample-s", type=float, default=d.sample_s, help="seconds between samples")
    ap.add_argument("--cameras", type=int, default=d.cameras)
    ap.add_argument("--animals", type=int, default=d.animals)
    ap.add_argument("--fps", type=float, default=d.fps)
    ap.add_argument("--probe-s", type=float, default=d.probe_s,
                    help="length of each probe run that finds the rate this machine sustains; 0: no probe")
    ap.add_argument("--min-fps", type=float, default=d.min_fps)
    ap.add_argument("--out", type=Path, default=d.out)
    ap.add_argument("--rules", default=str(d.rules), help="closed-loop rules file; 'none' for no closed loop")
    ap.add_argument("--no-browser", action="store_true")
    ap.add_argument("--no-clients", action="store_true")
    ap.add_argument("--no-scaling", action="store_true", help="do not finalise parts of the recording again")
    ap.add_argument("--trigger", default=d.trigger)
    ap.add_argument("--seed", type=int, default=d.seed)
    ap.add_argument("--from-json", type=Path, help="no run: the fits, figure and summary again from a soak's "
                    "soak.json and its samples")
    a = ap.parse_args(argv)
    if a.from_json is not None:
        result = json.loads(a.from_json.read_text())
        finish(result, load_samples(Path(result["samples_file"])), a.from_json.parent,
               say=lambda s: print(s, flush=True))
        return 0
    cfg = SoakConfig(minutes=a.minutes, sample_s=a.sample_s, cameras=a.cameras, animals=a.animals, fps=a.fps,
                     probe_s=a.probe_s, min_fps=a.min_fps, out=a.out.resolve(),
                     rules=None if a.rules.lower() in ("none", "off", "") else Path(a.rules),
                     browser=not a.no_browser, clients=not a.no_clients, trigger=a.trigger, seed=a.seed,
                     scaling=not a.no_scaling)
    try:
        soak(cfg, say=lambda s: print(s, flush=True))
    except DemoError as exc:
        print(f"soak cannot run: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
