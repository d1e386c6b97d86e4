"""The fault-injection suite: one short simulated run per fault, each in its own process, a table.

    python -m flytrack_host.sim.faults            # every scenario, 3 at a time, the table (make test-faults)
    python -m flytrack_host.sim.faults one NAME   # one scenario in this process, its row as JSON

Each scenario is `flytrack demo` (3 cameras, 2 animals, 100 fps, 3 s: real `flytrack-edge` processes,
loopback UDP, the real host, the firmware in simavr where the trigger matters, else the software
trigger) with one fault injected 1 s after the trigger started (`inject.py`). Its row: frames lost,
frames misnumbered, seconds from the end of the fault until the numbering was right again, and the
first log line that named the fault, with how many lines did (`measure.py`).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.sim.faults import inject as fi
from flytrack_host.util import children

RESULT_TAG = "FAULT-RESULT "


@dataclass
class Scenario:
    name: str
    label: str
    fault: type[fi.Fault]
    params: dict[str, Any] = field(default_factory=dict)
    message: str = "."  # regex of the log line that names the fault
    trigger: str = "software"
    fixed_clock: bool = False
    lost_ok: bool = False  # the fault itself loses frames (a killed edge): lost is reported, not a failure
    seconds: float = 3.0
    kill_host_after_s: float | None = None  # SIGKILL the whole run this long after recording began


SCENARIOS: list[Scenario] = [
    Scenario("none", "no fault (baseline)", fi.NoFault, message="$^"),
    Scenario("wall-1", "host wall clock steps -1 s", fi.WallStep, {"seconds": -1.0}, "wall clock stepped",
             trigger="auto"),
    Scenario("wall-30", "host wall clock steps -30 s", fi.WallStep, {"seconds": -30.0}, "wall clock stepped",
             trigger="auto"),
    Scenario("wall+3600", "host wall clock steps +1 h", fi.WallStep, {"seconds": 3600.0}, "wall clock stepped",
             trigger="auto"),
    Scenario("wall-1-fixed", "host wall clock steps -1 s, host on fixed-rate clock (--no-trigger)", fi.WallStep,
             {"seconds": -1.0}, "wall clock stepped", fixed_clock=True),
    Scenario("misnumber", "edge sends frame numbers +48 (own address and port, 1 s)", fi.MisnumberingEdge,
             message="numbered ahead"),
    Scenario("second-edge", "second edge with camera index 1 (1 s)", fi.SecondEdge, message="second sender"),
    Scenario("restart", "edge SIGKILLed, new edge 0.6 s later", fi.EdgeRestart, message="edge restarted",
             lost_ok=True),
    Scenario("edge-stop", "edge SIGSTOP 0.3 s, SIGCONT", fi.SignalEdge, {"hold_s": 0.3},
             "camera 1.*(late|silent)"),
    Scenario("edge-gone", "camera gone 1 s and back (edge SIGSTOP/SIGCONT)", fi.SignalEdge, {"hold_s": 1.0},
             "camera 1 (silent|is sending again)"),
    Scenario("flood", "25k garbage + random-index datagrams in 1 s", fi.GarbageFlood,
             message="malformed|not in the rig", lost_ok=True),
    Scenario("host-stop", "host process SIGSTOP 1.5 s, SIGCONT", fi.HostStop, message="stalled|behind real time",
             trigger="auto", seconds=4.0),
    Scenario("host-kill", "host SIGKILLed mid-run, then `recording recover`", fi.NoFault, message="recovered",
             kill_host_after_s=2.0, seconds=6.0),
    Scenario("trigger-pause", "trigger pauses 0.5 s, host on fixed-rate clock (--no-trigger)", fi.TriggerPause,
             message="re-anchored", trigger="auto", fixed_clock=True, seconds=4.0),
]
BY_NAME = {s.name: s for s in SCENARIOS}


def run_one(name: str, out: Path, seconds: float | None = None) -> dict[str, Any]:
    """Run one scenario in this process (it forks the simulated cameras: call it in a fresh one);
    `seconds`: its run this long instead of the scenario's own length."""
    from flytrack_host.sim.faults.measure import measure
    from flytrack_host.sim.run import PREROLL_FRAMES, DemoConfig, run_demo

    sc = BY_NAME[name]
    fault = sc.fault(**sc.params)
    row: dict[str, Any] = {"name": sc.name, "fault": sc.label}
    if fault.needs_root and os.geteuid() != 0:
        row["skipped"] = "needs root (raw socket to send from the edge's own port)"
        return row
    # 320 x 240 frames: a quarter of the rendering and extraction, so three runs at once fit a busy machine.
    # CPUs shared: with several runs at once, a split would put every run's host on the same CPUs.
    seconds = sc.seconds if seconds is None else seconds
    cfg = DemoConfig(cameras=3, animals=2, fps=100.0, seconds=seconds, seed=3, out=out, progress=False,
                     width=320, height=240, cpus="share",
                     trigger=sc.trigger, fault=fault, host_fixed_clock=sc.fixed_clock)
    rep = run_demo(cfg)
    row.update(measure(rep.recording, fault, PREROLL_FRAMES, rep.frames_rendered, cfg.cameras, sc.message))
    hs = rep.host_summary
    row.update({
        "trigger": rep.trigger, "mota": rep.scores.mota, "frames_in_time": rep.frames_in_time,
        "frames_rendered": rep.frames_rendered, "latency_p99_ms": (hs.get("latency") or {}).get("total_p99_ms"),
        "latency_p50_ms": (hs.get("latency") or {}).get("total_p50_ms"),
        "fault_error": fault.error, "fault_info": fault.info, "fault_s": fault.t_end - fault.t_start,
        "lost_ok": sc.lost_ok, "wall_s": rep.wall_s,
        "receiver": {k: v for k, v in (hs.get("receiver") or {}).items() if k != "cameras"},
        "receiver_cam1": (hs.get("receiver") or {}).get("cameras", {}).get("1"),
        "receiver_lost": sum(c.get("lost", 0) for c in (hs.get("receiver") or {}).get("cameras", {}).values()),
        "sync_cam1": (hs.get("sync") or {}).get("1"),
        "host": {k: hs.get(k) for k in ("wall_clock_steps", "stalls", "behind_skipped", "range_errors",
                                         "untracked", "log_counts")},
    })
    return row


def _run_killed(sc: Scenario, out: Path, timeout_s: float, more: list[str]) -> dict[str, Any]:
    """The host process SIGKILLed during its recording (with everything it started: its process group),
    then `flytrack recording recover`: what was received up to the kill must be there."""
    import signal

    from flytrack_host.recording import load_recording
    from flytrack_host.recording.parts import recording_started
    from flytrack_host.sim.run import PREROLL_FRAMES
    from flytrack_host.util import hostclock

    row: dict[str, Any] = {"name": sc.name, "fault": sc.label, "lost_ok": sc.lost_ok}
    cmd = [sys.executable, "-m", "flytrack_host.sim.faults", "one", sc.name, "--out", str(out), *more]
    p = children.popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    folder = out / "recording.flytrack"
    end = time.monotonic() + timeout_s
    while not recording_started(folder) and p.poll() is None and time.monotonic() < end:
        time.sleep(0.05)
    if not recording_started(folder):
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
        return {**row, "error": "the run never started recording"}
    time.sleep(sc.kill_host_after_s or 0.0)
    os.killpg(p.pid, signal.SIGKILL)  # the host, its edges, simulated cameras and trigger: all at once
    t_kill = hostclock.now()
    p.wait()
    r = children.run([sys.executable, "-m", "flytrack_host.cli", "recording", "recover", str(folder)],
                     capture_output=True, text=True, timeout=120)
    said = (r.stdout + r.stderr).strip().splitlines()
    d = load_recording(folder).table("data2d_distorted")
    d = d[d["camera_frame"] >= PREROLL_FRAMES]
    got = {(int(c), int(f)) for c, f in zip(d["camera_index"], d["camera_frame"], strict=True)}
    t = d["cam_received_timestamp"]
    # Frames a camera delivered before the kill: from its first to its last recorded one, none missing.
    missing = 0
    for c in {k[0] for k in got}:
        fs = sorted(f for cc, f in got if cc == c)
        missing += (fs[-1] - fs[0] + 1) - len(fs)
    row.update({"frames_lost": missing, "frames_misnumbered": int(np.sum(
        d["trigger_frame"].astype(np.int64) != d["camera_frame"].astype(np.int64) - PREROLL_FRAMES)),
        "recovery_s": 0.0, "rogue_tracked": 0, "mota": None, "message_count": 1,
        "message": (f"`flytrack recording recover`: exit {r.returncode}, {len(got)} camera frames back, the last "
                    f"{t_kill - np.nanmax(t):.2f} s before the kill" if len(t) and r.returncode == 0
                    else f"recover: exit {r.returncode}: {said[-1] if said else '(nothing said)'}"),
        "recover_exit": r.returncode, "frames_recovered": len(got),
        "last_row_before_kill_s": float(t_kill - np.nanmax(t)) if len(t) else None, "fault_error": None})
    return row


def _run_child(name: str, root: Path, timeout_s: float, seconds: float | None = None) -> dict[str, Any]:
    out = root / name
    out.mkdir(parents=True, exist_ok=True)
    more = [] if seconds is None else ["--seconds", repr(float(seconds))]
    if BY_NAME[name].kill_host_after_s is not None:
        return _run_killed(BY_NAME[name], out, timeout_s, more)
    cmd = [sys.executable, "-m", "flytrack_host.sim.faults", "one", name, "--out", str(out), *more]
    t0 = time.monotonic()
    try:
        # util.children: the scenario's process (and so its edges, cameras, trigger) ends with this one.
        p = children.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {"name": name, "fault": BY_NAME[name].label, "error": f"timed out after {timeout_s:.0f} s"}
    for line in p.stdout.splitlines()[::-1]:
        if line.startswith(RESULT_TAG):
            row = json.loads(line[len(RESULT_TAG):])
            row["process_s"] = time.monotonic() - t0
            return row
    return {"name": name, "fault": BY_NAME[name].label,
            "error": f"exit {p.returncode}: {(p.stderr or p.stdout)[-1500:]}"}


def run_suite(names: list[str] | None = None, jobs: int = 3, root: Path | None = None,
              timeout_s: float = 150.0, seconds: float | None = None) -> list[dict[str, Any]]:
    """Every scenario (or `names`) in its own process, `jobs` at a time; rows in scenario order.
    `seconds`: every run this long instead of its scenario's length (each then may take 4 s a second)."""
    if seconds is not None:
        timeout_s = max(timeout_s, 4 * seconds + 60)
    names = names or [s.name for s in SCENARIOS]
    root = Path(root or tempfile.mkdtemp(prefix="flytrack-faults-"))
    rows: dict[str, dict[str, Any]] = {}
    todo = list(names)
    lock = threading.Lock()

    def worker() -> None:
        while True:
            with lock:
                if not todo:
                    return
                n = todo.pop(0)
            r = _run_child(n, root, timeout_s, seconds)
            with lock:
                rows[n] = r

    threads = [threading.Thread(target=worker) for _ in range(max(1, jobs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return [rows[n] for n in names]


def _cell(v: Any, fmt: str = "{}") -> str:
    return "-" if v is None else fmt.format(v)


def format_table(rows: list[dict[str, Any]]) -> str:
    lines = ["| fault | frames lost | frames misnumbered | s until numbering right | MOTA | the message the user saw |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        if "skipped" in r or "error" in r:
            why = r.get("skipped") or (r.get("error") or "").strip().splitlines()[-1]
            lines.append(f"| {r['fault']} | - | - | - | - | {why} |")
            continue
        msg = r["message"].replace("|", "/")
        if len(msg) > 150:
            msg = msg[:147] + "..."
        count = f" ({r['message_count']} lines)" if r["message_count"] != 1 else ""
        lines.append(f"| {r['fault']} | {_cell(r['frames_lost'])} | {_cell(r['frames_misnumbered'])} | "
                     f"{_cell(r['recovery_s'], '{:.2f}')} | {_cell(r['mota'], '{:.3f}')} | {msg}{count} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m flytrack_host.sim.faults", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd")
    one = sub.add_parser("one", help="run one scenario in this process")
    one.add_argument("name", choices=list(BY_NAME))
    one.add_argument("--out", type=Path, required=True)
    one.add_argument("--seconds", type=float, help="the run this long (default: the scenario's own)")
    ap.add_argument("--jobs", type=int, default=3, help="scenarios run at the same time")
    ap.add_argument("--json", type=Path, help="write every row as JSON here")
    ap.add_argument("--only", nargs="*", help="scenario names (default: all)")
    ap.add_argument("--seconds", type=float, help="every run this long (default: each scenario's own, 3-6 s)")
    a = ap.parse_args(argv)
    if a.cmd == "one":
        row = run_one(a.name, a.out, a.seconds)
        print(RESULT_TAG + json.dumps(row, default=str), flush=True)
        return 0
    t0 = time.monotonic()
    root = Path(tempfile.mkdtemp(prefix="flytrack-faults-"))
    rows = run_suite(a.only, jobs=a.jobs, root=root, seconds=a.seconds)
    print(format_table(rows))
    print(f"\n{len(rows)} scenarios in {time.monotonic() - t0:.0f} s; each run's rig, logs and recording in {root}")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1, default=str))
    return 1 if any("error" in r for r in rows) else 0
