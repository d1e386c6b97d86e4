"""What the live page shows, gathered on the server's publisher thread (never the tracking thread).

`LiveState.add_frame` keeps the live tracks' trails from each tracked frame; `snapshot` reads the rest
from the pipeline (receiver and synchroniser counts, the last bundle's points, the latency histogram,
the recorder, the trigger's status line, the log) and returns one JSON-ready dict. The pipeline's
counters are plain ints written by other threads: reading them without a lock gives a value at most
one frame old, which is what a live view needs.
"""

from __future__ import annotations

import math
import shutil
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.tracking.types import FrameResult
from flytrack_host.util import hostclock

TRAIL_SECONDS = 3.0
TRAIL_POINTS = 60  # per track: one point every TRAIL_SECONDS / TRAIL_POINTS
MAX_POINTS_PER_CAMERA = 50
LOG_LINES = 30
RULE_LINES = 30


def _r(v: float, nd: int = 4) -> float | None:
    return round(v, nd) if math.isfinite(v) else None


class LiveState:
    def __init__(self, pipeline: Any = None, rule_sources: list[Callable[[], list[str]]] | None = None):
        self.pipe = pipeline
        self.thumbs: Any = None  # web.thumbs.ThumbnailAssembler, set by the server
        self.trails: dict[int, deque[tuple[float, float, float]]] = {}
        self.last_point_time: dict[int, float] = {}
        self.last_seen: dict[int, float] = {}
        self.live_ids: list[int] = []
        self.velocity: dict[int, tuple[float, float, float]] = {}
        self.frames = 0
        self.last_frame = -1
        self.last_trigger_time = math.nan
        self.last_estimate_time = math.nan
        self.births = 0
        self.deaths = 0
        self.rule_firings: deque[str] = deque(maxlen=RULE_LINES)
        self.rule_sources = list(rule_sources or [])
        self._rx_prev: dict[int, tuple[float, int]] = {}
        self._fps: dict[int, float] = {}
        self._disk: tuple[float, dict[str, Any]] = (0.0, {})

    # --- fed per frame (publisher thread) ---------------------------------------------------------
    def add_frame(self, result: FrameResult, trigger_time: float, estimate_time: float = math.nan) -> None:
        now = time.monotonic()
        step = TRAIL_SECONDS / TRAIL_POINTS
        self.frames += 1
        self.last_frame = int(result.trigger_frame)
        self.last_trigger_time = trigger_time
        self.last_estimate_time = estimate_time
        self.births += len(result.born)
        self.deaths += len(result.died)
        ids = []
        for e in result.estimates:
            i = int(e.obj_id)
            ids.append(i)
            s = e.state
            self.last_seen[i] = now
            self.velocity[i] = (float(s[3]), float(s[4]), float(s[5]))
            if now - self.last_point_time.get(i, -1e9) >= step:
                self.last_point_time[i] = now
                tr = self.trails.get(i)
                if tr is None:
                    tr = self.trails[i] = deque(maxlen=TRAIL_POINTS)
                tr.append((float(s[0]), float(s[1]), float(s[2])))
        self.live_ids = ids
        for i in result.died:
            self._forget(int(i))
        # Tracks that vanished without a Death (tracker restarted) fade out after the trail length.
        for i in [i for i, t in self.last_seen.items() if now - t > TRAIL_SECONDS]:
            self._forget(i)

    def _forget(self, i: int) -> None:
        for d in (self.trails, self.last_point_time, self.last_seen, self.velocity):
            d.pop(i, None)

    def add_rule_firing(self, text: str) -> None:
        self.rule_firings.append(f"{time.strftime('%H:%M:%S')} {text}")

    # --- snapshot (publisher thread, ~20 Hz) ------------------------------------------------------
    def snapshot(self, server_stats: dict[str, Any] | None = None, final: bool = False) -> dict[str, Any]:
        now = hostclock.now()
        live = set(self.live_ids)
        tracks = [{"id": i, "live": i in live, "trail": [[_r(a), _r(b), _r(c)] for a, b, c in tr],
                   "vel": [_r(v, 3) for v in self.velocity.get(i, (math.nan,) * 3)]}
                  for i, tr in sorted(self.trails.items())]
        snap: dict[str, Any] = {
            "time": now,
            # host time -> the browser's wall clock, for the page's estimate-to-page delay
            "wall_offset": hostclock.wall() - now,
            "final": final,
            "frame": self.last_frame,
            "frames_published": self.frames,
            "trigger_time": self.last_trigger_time if math.isfinite(self.last_trigger_time) else None,
            # when the newest frame shown was estimated: the page's delay is its own clock minus this
            "last_estimate_time": self.last_estimate_time if math.isfinite(self.last_estimate_time) else None,
            "objects": len(self.live_ids),
            "births": self.births,
            "deaths": self.deaths,
            "tracks": tracks,
            "rules": list(self.rule_firings) + [s for f in self.rule_sources for s in _safe(f)],
            "rules_fired": [],
            "server": server_stats or {},
        }
        if self.pipe is not None:
            snap.update(self._pipeline_part())
        return snap

    def _pipeline_part(self) -> dict[str, Any]:
        p = self.pipe
        out: dict[str, Any] = {"rig": p.rig.name, "fps": p.fps, "frames_tracked": p.frames_tracked,
                               "tracker_errors": p.tracker_errors, "loop_errors": p.loop_errors,
                               "sink_errors": getattr(p, "sink_errors", 0)}
        out["cameras"] = self._cameras(p)
        counts, edges = p.latency.histogram()
        c = counts.tolist()
        total = sum(c)
        # Show up to a little past the P99.5 bin (the last bin also holds everything beyond the
        # histogram's range); what is cut off is one "beyond" count.
        n_show = 10
        if total:
            cum = np.cumsum(c)
            k = int(np.searchsorted(cum, 0.995 * total))
            n_show = max(10, int(k * 1.25) + 2)
        out["latency"] = {"bin_ms": float(edges[1] - edges[0]) if len(edges) > 1 else 0.0,
                          "counts": c[:n_show], "beyond": int(sum(c[n_show:])), **_lat_summary(p.latency)}
        out["recording"] = self._recording(p)
        out["trigger"] = [s for f in p.status_sources for s in _safe(lambda f=f: [f()])]
        out["log"] = list(p.events)[-LOG_LINES:]
        fired = _actuation_firings(p)
        if fired:
            out["rules_fired"] = fired
        return out

    def _cameras(self, p: Any) -> list[dict[str, Any]]:
        rx = p.receiver.stats.cameras if p.receiver is not None else {}
        sync = p.sync.stats() if p.sync is not None else {}
        syncs = p.sync.cams if p.sync is not None else {}
        last = getattr(p, "last_synced", None)
        frames = last.frames if last is not None else {}
        ttime = last.bundle.timestamp if last is not None else math.nan
        mono = time.monotonic()
        cams = []
        for c in p.rig.cameras:
            r = rx.get(c.index)
            s = sync.get(c.index)
            n_rx = int(r.frames) if r is not None else 0
            prev = self._rx_prev.get(c.index)
            if prev is None or mono - prev[0] >= 1.0:
                if prev is not None:
                    self._fps[c.index] = (n_rx - prev[1]) / (mono - prev[0])
                self._rx_prev[c.index] = (mono, n_rx)
            fr = frames.get(c.index)
            cam = p.cameras.get(c.index) if p.cameras else None
            pts: list[list[float | None]] = []
            lat_ms = None
            if fr is not None:
                a = fr.points
                k = min(len(a), MAX_POINTS_PER_CAMERA)
                if k:
                    xs, ys = a["x_dist"][:k].tolist(), a["y_dist"][:k].tolist()
                    pts = [[_r(x, 1), _r(y, 1)] for x, y in zip(xs, ys, strict=True)]
                if math.isfinite(ttime):
                    lat_ms = _r((fr.recv_time - ttime) * 1e3, 2)
            centre = None
            if cam is not None:
                try:
                    centre = [_r(float(v), 3) for v in cam.center]
                except (AttributeError, TypeError, ValueError):
                    centre = None
            cams.append({
                "index": c.index, "name": c.name, "centre": centre,
                "width": int(getattr(cam, "width", 0) or 0), "height": int(getattr(cam, "height", 0) or 0),
                "rx": n_rx,
                "lost": int(r.lost) if r is not None else 0,
                "malformed": int(r.malformed) if r is not None else 0,
                "late": int(getattr(s, "late", 0)) if s is not None else 0,
                "alive": bool(syncs[c.index].alive) if c.index in syncs else False,
                "fps": _r(self._fps.get(c.index, math.nan), 1),
                "latency_ms": lat_ms,
                "points": pts,
                "n_points": len(fr.points) if fr is not None else 0,
                "thumbnail": self._thumb(c.index),
            })
        return cams

    def _thumb(self, index: int) -> dict[str, Any] | None:
        t = self.thumbs.latest.get(index) if self.thumbs is not None else None
        if t is None:
            return None
        return {"id": t.image_id, "camera_frame": t.camera_frame, "age_s": round(time.monotonic() - t.time, 1)}

    def _recording(self, p: Any) -> dict[str, Any]:
        rec: dict[str, Any] = {"on": p.recorder is not None, "path": str(p.recording_path) if p.record else None}
        if p.recorder is not None:
            rec["status"] = _safe1(p.recorder_status)
        mono = time.monotonic()
        if mono - self._disk[0] > 2.0:  # statvfs at most every 2 s
            d: dict[str, Any] = {}
            try:
                target = Path(p.recording_path)
                while not target.exists() and target != target.parent:
                    target = target.parent
                u = shutil.disk_usage(target)
                d = {"free_gb": round(u.free / 1e9, 2), "total_gb": round(u.total / 1e9, 2)}
            except OSError as exc:
                d = {"error": str(exc)}
            self._disk = (mono, d)
        rec["disk"] = self._disk[1]
        return rec


def _actuation_firings(p: Any) -> list[str]:
    """The last firings of the actuation rules, read from any sink that keeps a `firings` log of rows
    (flytrack_host.actuation's FiringLog: FIRINGS rows) - duck-typed, so the page needs no actuation."""
    lines: list[str] = []
    for sink in list(getattr(p, "sinks", [])):
        log = getattr(sink, "firings", None)
        rows = getattr(log, "rows", None)
        if not isinstance(rows, list | deque):
            continue
        try:
            rows = list(rows)  # one C-level copy under the GIL: the workers append to it meanwhile
        except RuntimeError:  # mutated during the copy: next tick
            continue
        lines.append(f"{getattr(log, 'count', len(rows))} actions fired, {getattr(log, 'failed', 0)} failed")
        for r in rows[-RULE_LINES:]:
            try:
                r0 = r[0]
                lat = (float(r0["time_ack"]) - float(r0["frame_time"])) * 1e3
                err = r0["error"].decode(errors="replace")
                lines.append(f"{r0['rule'].decode(errors='replace')} obj {int(r0['obj_id'])} -> "
                             f"{r0['output'].decode(errors='replace')} frame {int(r0['scheduled_frame'])}"
                             + (f" {lat:.1f} ms" if math.isfinite(lat) else "") + (f" ({err})" if err else ""))
            except (IndexError, KeyError, TypeError, ValueError):
                lines.append("(a firing row this page cannot read)")
    return lines


def _lat_summary(lat: Any) -> dict[str, float | None]:
    out: dict[str, float | None] = {}
    for q in (50, 99):
        v = lat.percentile("total", q)
        out[f"p{q}_ms"] = _r(v, 3)
    out["n"] = int(lat.n)
    return out


def _safe(f: Callable[[], list[str]]) -> list[str]:
    try:
        return [str(s) for s in f()]
    except Exception as exc:  # a status source's bug shows on the page, it does not stop it
        return [f"(status source failed: {exc!r})"]


def _safe1(f: Callable[[], Any]) -> Any:
    try:
        return f()
    except Exception as exc:
        return f"(failed: {exc!r})"
