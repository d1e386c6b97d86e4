"""The soak's samples (sim/soak.py): what one sample of a running rig reads, and the sampler that takes them.

Resident memory, open files and threads of every process of the rig, from /proc; the UDP socket's kernel
queue and drops; the trigger -> estimate latency of the frames tracked since the last sample (the growth
of the host's histogram); the Braid and pose clients' process (sim/soak_clients.py) and the live page in
Chromium; and `Sampler`, attached to a demo run, which writes one JSON line per sample to samples.jsonl
as the run goes (nothing is kept in the host process, whose memory is under test).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.sim.demo_config import DemoContext, DemoError
from flytrack_host.util import children

MB = 1e6


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
    """Percentile (ms) of a sparse latency histogram (bin index -> count, bins of `bin_ms`, the host's
    BIN_MS) and the exact values past its end: recording.latency's on the dense histogram."""
    from flytrack_host.recording.latency import BIN_MS, histogram_percentile

    assert bin_ms == BIN_MS, "the soak's windows are the host's latency bins"
    dense = np.zeros(max(bins, default=-1) + 1, dtype=np.int64)
    np.add.at(dense, np.asarray(bins, dtype=np.int64), np.asarray(counts, dtype=np.int64))
    return histogram_percentile(dense, over_ms, q)


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


# --- the sampler, attached to a run ----------------------------------------------------------------
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


def load_samples(path: Path) -> list[dict[str, Any]]:
    try:
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    except OSError:
        return []
