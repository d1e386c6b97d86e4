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
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.sim.demo_config import ROOT, DemoConfig, DemoContext, DemoError
from flytrack_host.util import children

MB = 1e6
DEFAULT_RULES = ROOT / "examples" / "closed_loop.toml"
FIT_SKIP_S = 300.0  # memory is fitted after the first 5 minutes ...
SHORT_RUN_FIT_FRACTION = 0.2  # ... or after the first 20 % when 5 minutes is more than that (under 25 min)
GROWTH_GOAL_MB_PER_H = 1.0
LATENCY_WINDOW_S = 600.0  # last 10 minutes against the first 10 ...
LATENCY_WINDOW_FRACTION = 1.0 / 6.0  # ... or a sixth of the run each for a run under an hour
LATENCY_GOAL_CHANGE = 0.10
FPS_LADDER = 0.7  # each probe after a failed one asks this fraction of the rate before
PROJECT_HOURS = (8.0, 24.0)
FINALISE_SPLIT_S = 60.0  # a finalise longer than this: recordings would better be split into parts
SCALING_FRACTIONS = (0.25, 0.5, 1.0)


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


# --- /proc ----------------------------------------------------------------------------------------
def proc_figures(pid: int) -> dict[str, float] | None:
    """Resident memory (RSS, its anonymous part, PSS) in MB, open files and threads of a process; None
    when it is gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    kb: dict[str, int] = {}
    for line in status.splitlines():
        k, _, v = line.partition(":")
        if k == "State" and v.split()[:1] == ["Z"]:
            return None  # exited, not yet reaped
        if k in ("VmRSS", "RssAnon", "Threads"):
            kb[k] = int(v.split()[0])
    if "VmRSS" not in kb:
        return None
    pss = 0
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                pss = int(line.split()[1])
                break
    except OSError:
        pass
    try:
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        fds = -1
    return {"rss_mb": kb.get("VmRSS", 0) * 1024 / MB, "anon_mb": kb.get("RssAnon", 0) * 1024 / MB,
            "pss_mb": pss * 1024 / MB, "fds": fds, "threads": kb.get("Threads", 0)}


def descendants(root: int) -> list[int]:
    """`root` and every process below it (from /proc/*/stat)."""
    children: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            ppid = int(Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(d))
    out, todo = [], [root]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += children.get(p, [])
    return out


def tree_figures(root: int) -> dict[str, float] | None:
    """The figures of a process tree summed (a browser is many processes); `processes` counts them."""
    rows = [f for f in (proc_figures(p) for p in descendants(root)) if f is not None]
    if not rows:
        return None
    out = {k: sum(r[k] for r in rows) for k in rows[0]}
    out["processes"] = len(rows)
    return out


def udp_socket(port: int) -> dict[str, int] | None:
    """The kernel's receive queue (bytes) and drop count of the UDP socket bound to `port`."""
    for path in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = Path(path).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            if len(f) > 12 and int(f[1].rsplit(":", 1)[1], 16) == port:
                return {"rx_queue_bytes": int(f[4].split(":")[1], 16), "drops": int(f[-1])}
    return None


def folder_bytes(path: Path) -> int:
    """The raw files of a recording folder so far (its parts' too; not the HDF5 files the background
    finaliser writes beside them)."""
    from flytrack_host.recording.schema import H5_NAME

    total = 0
    try:
        for e in os.scandir(path):
            if e.is_dir():
                total += folder_bytes(Path(e.path))
            elif e.is_file() and e.name != H5_NAME and not e.name.endswith(".tmp"):
                total += e.stat().st_size
    except OSError:
        pass
    return total


# --- latency windows -------------------------------------------------------------------------------
def hist_percentile(bins: list[int], counts: list[int], over_ms: list[float], q: float, bin_ms: float) -> float:
    """Percentile (ms) of a sparse latency histogram (bin index -> count, bins of `bin_ms`) and the exact
    values past its end, as recording.latency.LatencyStats computes it."""
    in_range = int(sum(counts))
    total = in_range + len(over_ms)
    if total == 0:
        return math.nan
    rank = max(1, math.ceil(q / 100.0 * total))
    if rank > in_range:
        return sorted(over_ms)[rank - in_range - 1]
    order = np.argsort(bins)
    cum = np.cumsum(np.asarray(counts)[order])
    k = int(np.asarray(bins)[order][int(np.searchsorted(cum, rank))])
    return (k + 0.5) * bin_ms


def merge_hists(windows: list[dict[str, Any]]) -> tuple[list[int], list[int], list[float]]:
    acc: dict[int, int] = {}
    over: list[float] = []
    for w in windows:
        for b, c in zip(w["bins"], w["counts"], strict=True):
            acc[b] = acc.get(b, 0) + c
        over += w["over_ms"]
    return list(acc), list(acc.values()), over


class LatencyWindow:
    """Trigger -> estimate latency of the frames tracked since the last `take()`, from the host's running
    histogram (recording/latency.py): its bins' growth, kept sparse."""

    def __init__(self, stats: Any):
        self.stats = stats
        self.prev = stats.counts["total"].copy()
        self.prev_over = len(stats.overflow["total"])

    def take(self) -> dict[str, Any]:
        from flytrack_host.recording.latency import BIN_MS

        c = self.stats.counts["total"].copy()
        d = c - self.prev
        self.prev = c
        kept = self.stats.overflow["total"]
        over = [float(x) for x in kept[self.prev_over:]]
        self.prev_over = len(kept)
        nz = np.nonzero(d)[0]
        bins, counts = nz.tolist(), d[nz].tolist()
        n = int(sum(counts)) + len(over)
        return {"n": n, "bins": bins, "counts": counts, "over_ms": over,
                "p50_ms": hist_percentile(bins, counts, over, 50, BIN_MS),
                "p99_ms": hist_percentile(bins, counts, over, 99, BIN_MS)}


# --- the clients and the page ----------------------------------------------------------------------
class Clients:
    """The Braid and pose clients' process (sim/soak_clients.py)."""

    def __init__(self, status: Path):
        self.status = status
        # Ends with the soak whatever ends it (util.children).
        self.proc = children.popen([sys.executable, "-m", "flytrack_host.sim.soak_clients", str(status)],
                                   stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, close_fds=True)
        line = self.proc.stdout.readline() if self.proc.stdout else ""
        if not line.startswith("pose_port "):
            self.close()
            raise DemoError(f"the soak's clients did not start (said {line!r})")
        self.pose_port = int(line.split()[1])

    def follow(self, url: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(url + "\n")
        self.proc.stdin.flush()

    def counts(self) -> dict[str, Any]:
        try:
            return json.loads(self.status.read_text())
        except (OSError, ValueError):
            return {}

    def close(self) -> dict[str, Any]:
        if self.proc.poll() is None:
            try:
                if self.proc.stdin is not None:
                    self.proc.stdin.close()
                self.proc.wait(5.0)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(5.0)
        return self.counts()


PAGE_JS = ("const f = window.flytrack || {}; const m = performance.memory || {};"
           "return [f.updates || 0, f.drawnSegments || 0, m.usedJSHeapSize || 0, !!f.ended];")


# --- one run ---------------------------------------------------------------------------------------
class Sampler:
    """Attached to a demo run: starts the live outputs, the clients and the browser on the pipeline, then
    samples every `sample_s` from the trigger's start to the last frame, one JSON line each."""

    def __init__(self, out: Path, sample_s: float, browser: bool, clients: bool):
        self.out = out
        self.sample_s = sample_s
        self.want_browser = browser
        self.want_clients = clients
        self.samples_path = out / "samples.jsonl"
        self.samples_path.unlink(missing_ok=True)
        self.pipe: Any = None
        self.ctx: DemoContext | None = None
        self.outputs: Any = None
        self.clients: Clients | None = None
        self.browser: Any = None
        self.browser_error: str | None = None
        self.pids: dict[str, int] = {}
        self.n_samples = 0
        self.sample_errors = 0
        self.last_error = ""
        self.t0 = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lat: LatencyWindow | None = None
        self._last_t = 0.0

    # DemoConfig.attach: the pipeline is built, not started (the frame feeder has forked: threads and
    # processes may start now).
    def attach(self, pipe: Any) -> None:
        from flytrack_host.live.launch import LiveOutputs

        self.pipe = pipe
        if self.want_clients:
            self.clients = Clients(self.out / "clients.json")
        self.outputs = LiveOutputs(http=("127.0.0.1", 0),
                                   pose=("127.0.0.1", self.clients.pose_port) if self.clients else None)
        self.outputs.attach(pipe, echo=lambda s: None)
        url = self.outputs.server.url
        if self.clients is not None:
            self.clients.follow(url)
        if self.want_browser:
            from flytrack_host.live.web import browser as browser_mod

            why = browser_mod.missing()
            if why:
                raise DemoError(f"the soak opens the live page in Chromium: {why}")
            self.browser = browser_mod.Browser()
            self.browser.driver.set_script_timeout(10)
            self.browser.driver.get(url)

    # DemoConfig.on_running: the trigger has started.
    def running(self, ctx: DemoContext) -> None:
        self.ctx = ctx
        self.t0 = time.monotonic()
        for cam, p in zip(ctx.cameras, ctx.edges.procs, strict=False):
            self.pids[f"edge {cam.name}"] = p.pid
        if ctx.feeder.pid:
            self.pids["sim cameras"] = ctx.feeder.pid
        sim = getattr(ctx.trigger, "sim", None)
        if sim is not None and getattr(sim, "proc", None) is not None:
            self.pids["sim trigger"] = sim.proc.pid
        if ctx.lab is not None and ctx.lab.modbus.proc is not None:
            self.pids["modbus server"] = ctx.lab.modbus.proc.pid
        if self.clients is not None:
            self.pids["clients"] = self.clients.proc.pid
        self._lat = LatencyWindow(self.pipe.latency)
        self._thread = threading.Thread(target=self._run, name="soak-sampler", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        with open(self.samples_path, "a") as f:
            next_t = 0.0
            while True:
                self._write(f, self.sample())
                next_t += self.sample_s
                while True:
                    now = time.monotonic() - self.t0
                    if self._stop.is_set() or self.ctx is None or self.ctx.feeder.done:
                        if now - self._last_t > 0.25 * self.sample_s:
                            # The end of the run: its last frames' figures. The edges and the cameras are
                            # exiting now, so its memory figures are left out of the fits.
                            self._write(f, {**self.sample(), "end": True})
                        return
                    if now >= next_t:
                        break
                    self._stop.wait(min(next_t - now, 0.2))

    def _write(self, f: Any, s: dict[str, Any]) -> None:
        f.write(json.dumps(s, allow_nan=True) + "\n")
        f.flush()
        self.n_samples += 1

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(30.0)

    def sample(self) -> dict[str, Any]:
        t = time.monotonic() - self.t0
        s: dict[str, Any] = {"t_s": t, "window_s": t - self._last_t, "wall": time.time()}  # noqa: TID251 - a label
        self._last_t = t
        for part, fn in (("proc", self._procs), ("frames", self._frames), ("queues", self._queues),
                         ("latency", self._latency), ("disk", self._disk), ("clients", self._clients),
                         ("page", self._page), ("closed_loop", self._closed_loop)):
            try:  # a figure that cannot be read is said, and never ends the run
                s[part] = fn()
            except Exception as exc:
                self.sample_errors += 1
                self.last_error = f"{part}: {exc!r}"
                s[part] = {"error": repr(exc)}
        try:
            s["status"] = self.pipe.status_line()
        except Exception as exc:
            s["status"] = f"status error {exc!r}"
        return s

    def _procs(self) -> dict[str, Any]:
        out: dict[str, Any] = {"host": proc_figures(os.getpid())}
        for name, pid in self.pids.items():
            out[name] = proc_figures(pid)
        if self.browser is not None:
            svc = getattr(self.browser.driver, "service", None)
            proc = getattr(svc, "process", None)
            if proc is not None:
                out["browser"] = tree_figures(proc.pid)
        return out

    def _frames(self) -> dict[str, Any]:
        pipe, ctx = self.pipe, self.ctx
        assert ctx is not None
        cams = list(pipe.receiver.stats.cameras.values())
        sync = list(pipe.sync.stats().values())
        n_cams = len(ctx.cameras)
        handed = (ctx.feeder.frames_rendered + ctx.feeder.preroll_frames) * n_cams
        received = sum(c.frames for c in cams)
        return {
            "triggered": ctx.feeder.edges_seen, "handed_to_edges": ctx.feeder.frames_rendered * n_cams,
            "received": received - ctx.feeder.preroll_frames * n_cams,
            # handed to the edges and not (yet) received: in flight, or lost if it grows
            "not_received": handed - received,
            "tracked": pipe.frames_tracked, "lost": sum(c.lost for c in cams), "late": sum(s.late for s in sync),
            "untracked": dict(pipe.untracked), "behind_skipped": pipe.behind_skipped, "stalls": pipe.stalls,
            "loop_errors": pipe.loop_errors, "tracker_errors": pipe.tracker_errors,
        }

    def _queues(self) -> dict[str, Any]:
        pipe = self.pipe
        out: dict[str, Any] = {}
        rec = pipe.recorder
        if rec is not None:
            out["recorder_bytes"] = rec.queue_bytes
            out["recorder_dropped_rows"] = sum(rec.stats.dropped_rows.values())
            out["recorder_write_errors"] = rec.stats.write_errors
        udp = udp_socket(pipe.address[1])
        if udp is not None:
            out["udp_rx_queue_bytes"] = udp["rx_queue_bytes"]
            out["udp_drops"] = udp["drops"]
        srv = self.outputs.server if self.outputs is not None else None
        if srv is not None:
            st = srv.stats()
            out["live_backlog_frames"] = st["backlog_frames"]
            out["live_client_pending_bytes"] = srv.clients.pending_bytes()
            out["live_clients"] = st["clients"]
            out["live_clients_dropped_slow"] = st["clients_dropped_slow"]
            out["live_frames_dropped"] = st["frames_dropped"]
        ps = self.outputs.pose_stream if self.outputs is not None else None
        if ps is not None:
            out["pose_datagrams_sent"] = ps.stats.datagrams
            out["pose_late_ticks"] = ps.stats.late_ticks
        return out

    def _latency(self) -> dict[str, Any]:
        assert self._lat is not None
        return self._lat.take()

    def _disk(self) -> dict[str, Any]:
        return {"recording_bytes": folder_bytes(Path(self.pipe.recording_path)),
                "free_bytes": shutil.disk_usage(self.out).free}

    def _clients(self) -> dict[str, Any]:
        return self.clients.counts() if self.clients is not None else {}

    def _page(self) -> dict[str, Any]:
        if self.browser is None:
            return {}
        updates, drawn, heap, ended = self.browser.js(PAGE_JS)
        return {"updates": updates, "drawn_segments": drawn, "js_heap_mb": heap / MB, "ended": ended}

    def _closed_loop(self) -> dict[str, Any]:
        engine = next((s for s in self.pipe.sinks if type(s).__name__ == "ActuationEngine"), None)
        if engine is None:
            return {}
        out: dict[str, Any] = {"fired": sum(engine.fired.values()), "firings": engine.firings.count,
                               "failed": engine.firings.failed}
        lab = self.ctx.lab if self.ctx is not None else None
        if lab is not None:
            try:
                with open(lab.modbus.log_path, "rb") as f:
                    out["modbus_writes"] = sum(1 for _ in f)
            except OSError:
                pass
        return out

    def close(self) -> dict[str, Any]:
        """After the run: the page's last figures, then the browser and the clients closed."""
        out: dict[str, Any] = {}
        if self.browser is not None:
            try:
                out["page"] = self._page()
            except Exception as exc:
                out["page"] = {"error": repr(exc)}
            self.browser.close()
            self.browser = None
        if self.clients is not None:
            out["clients"] = self.clients.close()
        return out


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


def load_samples(path: Path) -> list[dict[str, Any]]:
    try:
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    except OSError:
        return []


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


# --- after the run ---------------------------------------------------------------------------------
def raw_bytes(recording: str | None) -> int:
    """The raw files of a recording (its folder, or its parts, without the HDF5 files)."""
    if not recording:
        return 0
    p = Path(recording)
    return folder_bytes(p if p.is_dir() else p.parent)


def h5_files(recording: Path) -> list[Path]:
    """The HDF5 files of a finalised recording: its recording.h5, or one per part."""
    from flytrack_host.recording.parts import part_dirs
    from flytrack_host.recording.schema import H5_NAME

    if recording.is_file():
        return [recording]
    return [p / H5_NAME for p in part_dirs(recording) if (p / H5_NAME).exists()]


def drop_cache(path: Path) -> bool:
    """Write the file out and drop it from the page cache, so a read comes from the disk."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        os.fsync(fd)
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        return True
    except (OSError, AttributeError):
        return False
    finally:
        os.close(fd)


def read_back(h5: Path) -> dict[str, Any]:
    """Read the finalised recording whole (every table, the text log, the files), from the disk (page cache
    dropped for the file) and again warm."""
    from flytrack_host.recording import load_recording

    files = h5_files(h5)
    out: dict[str, Any] = {"h5_bytes": sum(f.stat().st_size for f in files),
                           "cache_dropped": bool(files) and all([drop_cache(f) for f in files])}
    t0 = time.monotonic()
    rec = load_recording(h5)
    out["cold_s"] = time.monotonic() - t0
    out["table_bytes"] = int(sum(a.nbytes for a in rec.tables.values()))
    out["rows"] = {k: len(v) for k, v in rec.tables.items() if len(v)}
    out["textlog_lines"] = len(rec.textlog)
    del rec
    t0 = time.monotonic()
    rec = load_recording(h5)
    out["warm_s"] = time.monotonic() - t0
    del rec
    return out


def finalise_scaling(h5: Path, work: Path, fractions: tuple[float, ...] = SCALING_FRACTIONS) -> dict[str, Any]:
    """Finalise the first `fractions` of every raw table's rows again (copies in `work`, removed after):
    time against size, and the exponent of a power law through them (1: linear)."""
    from flytrack_host.recording.finalize import finalize, read_meta
    from flytrack_host.recording.schema import H5_NAME, RAW_SUFFIX, dtype_from_json

    folder = h5.parent if h5.is_file() else h5_files(h5)[0].parent  # in parts: the first part
    meta = read_meta(folder)
    sizes = {name + RAW_SUFFIX: dtype_from_json(d).itemsize for name, d in meta["tables"].items()}
    points = []
    for frac in fractions:
        d = work / f"finalise_{int(round(frac * 100))}pct"
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
        try:
            raw = 0
            for e in os.scandir(folder):
                if not e.is_file() or e.name == H5_NAME or e.name.endswith(".tmp"):
                    continue
                n = e.stat().st_size
                if e.name in sizes:  # whole rows of this fraction of the table
                    item = sizes[e.name]
                    n = int(n * frac) // item * item
                with open(e.path, "rb") as src, open(d / e.name, "wb") as dst:
                    _copy_bytes(src, dst, n)
                raw += n
            os.sync()  # the copies' writing is not the finalise's
            t0 = time.monotonic()
            rep = finalize(d)
            dt = time.monotonic() - t0
            points.append({"fraction": frac, "raw_bytes": raw, "h5_bytes": rep.h5_path.stat().st_size,
                           "finalise_s": dt})
        finally:
            shutil.rmtree(d, ignore_errors=True)
    out: dict[str, Any] = {"points": points}
    if len(points) >= 2 and all(p["finalise_s"] > 0 and p["raw_bytes"] > 0 for p in points):
        x = np.log([p["raw_bytes"] for p in points])
        y = np.log([p["finalise_s"] for p in points])
        out["exponent"] = float(np.polyfit(x, y, 1)[0])
    return out


def _copy_bytes(src: Any, dst: Any, n: int) -> None:
    while n > 0:
        b = src.read(min(n, 8 << 20))
        if not b:
            return
        dst.write(b)
        n -= len(b)


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
    """Latency P99 of the first and the last window (10 minutes; a sixth of a run under an hour), each the
    merged histograms of the samples whose interval lies in it."""
    from flytrack_host.recording.latency import BIN_MS

    scaled = duration_s < 6 * LATENCY_WINDOW_S
    w = duration_s * LATENCY_WINDOW_FRACTION if scaled else LATENCY_WINDOW_S
    lat = [(s["t_s"] - s["window_s"], s["t_s"], s["latency"]) for s in samples
           if isinstance(s.get("latency"), dict) and "bins" in s["latency"]]
    first = [(a, b, x) for a, b, x in lat if b <= w + 1e-6 and b > 0]
    last = [(a, b, x) for a, b, x in lat if a >= duration_s - w - 1e-6]
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


def _closed_loop_summary(act: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, d in (act or {}).get("rules", {}).items():
        out[name] = {k: d.get(k) for k in ("fired", "expected", "missed", "false_fires", "latency_ms_p50",
                                           "latency_ms_p99", "frame_error_max")}
    if act:
        out["modbus_coil_writes"] = act.get("modbus_coil_writes")
        out["can_frames"] = act.get("can_frames")
    return out


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
            out.append(f"closed loop {name}: fired {d['fired']}/{d['expected']}, missed {d['missed']}, false "
                       f"{d['false_fires']}, ack P50/P99 {_fmt(d['latency_ms_p50'])}/{_fmt(d['latency_ms_p99'])} ms; "
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
