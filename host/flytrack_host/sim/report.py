"""A simulated rig run's report: the tracks scored against ground truth, latency and its parts, the
host's frame numbering checked, what the world did, the figure, the braidz export, the JSON summary."""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.geometry.camera import Camera
from flytrack_host.sim.demo_config import DemoConfig
from flytrack_host.sim.flight import GroundTruth
from flytrack_host.sim.goals import check_goals
from flytrack_host.sim.metrics import latency_percentiles_ms
from flytrack_host.tracking.evaluation import FrameTracks, TrackingScores, score_tracks


@dataclass
class HostResult:
    frame: int
    t_result: float
    ids: np.ndarray
    pos: np.ndarray


@dataclass
class DemoReport:
    config: dict[str, Any]
    trigger: str
    trigger_note: str
    scores: TrackingScores | None  # None when the run was not scored (DemoConfig.score False: the soak)
    latency: dict[str, float]  # hand-over to 3D estimate (exposure and transfer are simulated)
    latency_parts_p50_ms: dict[str, float]
    trigger_time_bias_ms: float  # host's trigger time (clock model) minus when the pulse happened
    latency_host: dict[str, float]  # the host's own figure: trigger time (clock model) -> estimate
    frames_triggered: int
    frames_rendered: int
    frames_tracked: int
    frames_in_time: int
    packets_lost: int
    packets_late: int
    frames_misnumbered: int  # camera frames the host's synchroniser gave a wrong trigger frame
    camera_frames_sent: int  # frames handed to the edges (pre-roll excluded)
    camera_frames_received: int  # FEATURES frames the host's receiver took in before it stopped
    exposure_lateness: dict[str, float]  # hand-over vs an ideal clock: how faithful the simulated timing was
    clock_model: dict[str, Any]  # the host's trigger session summary (rate, clock model fit, samples)
    sim_priority_raised: bool
    world: dict[str, Any]  # what the flight model did: saccades, landings, close passes
    live_frames: int
    render_realtime_factor: float
    host_kept_up: bool
    recording: str | None
    braidz: str | None
    figure: str | None
    rig_file: str
    calibration: str | None
    wall_s: float
    notes: list[str] = field(default_factory=list)
    host_summary: dict[str, Any] = field(default_factory=dict)
    cpu_seconds: dict[str, float] = field(default_factory=dict)  # per part of the simulated rig
    # CPUs of the host and of the simulated hardware when split (sim/placement.py); None: shared
    cpu_placement: dict[str, list[int]] | None = None
    actuation: dict[str, Any] = field(default_factory=dict)  # closed loop vs ground truth (with --rules)
    dvs: list[dict[str, Any]] = field(default_factory=list)  # per DVS camera: events sent and received
    # the same bundles tracked with and without the DVS cameras' points (eventcam.comparison)
    dvs_comparison: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["scores"] = self.scores.as_dict() if self.scores is not None else None
        return d

def _scored_mask(gt: GroundTruth, cams: list[Camera]) -> np.ndarray:
    """An animal counts in a frame when at least two cameras see it (else nobody can place it)."""
    seen = np.zeros(gt.landed.shape, dtype=np.int32)
    flat = gt.pos.reshape(-1, 3)
    for c in cams:
        seen += c.in_view(flat, margin=2.0).reshape(gt.landed.shape)
    return seen >= 2


def _report(cfg: DemoConfig, gt: GroundTruth, rig_path: Path, calib_path: Path | None, trig: Any, fs: Any,
            results: list[HostResult], host_summary: dict[str, Any], live_frames: int, out: Path,
            notes: list[str], wall0: float, cams: list[Camera], warmup: int,
            trigger_summary: dict[str, Any], preroll: int, result_times: np.ndarray | None = None) -> DemoReport:
    """`result_times` (per trigger frame, when its 3D result came; NaN: none) instead of `results` for a run
    that is not scored (DemoConfig.score False)."""
    from flytrack_host.sim.plot import plot_tracks

    hyps = [FrameTracks(r.frame, r.ids, r.pos) for r in results if 0 <= r.frame < gt.n_frames]
    scores = None
    if result_times is None:
        scored = _scored_mask(gt, cams)
        scored[:warmup] = False  # animals not drawn yet: the edges were taking their background
        scores = score_tracks(gt.pos, hyps, scored=scored, close=gt.close_frames(cfg.close_distance_m),
                              match_threshold_m=cfg.match_threshold_m, close_window=int(round(0.1 * cfg.fps)))
    recording = host_summary.get("recording")
    # The clock model's bias is judged against when each pulse happened (paced simavr states it);
    # with the software trigger, against when the cameras read it.
    truth_edges = fs.edge_true_time if np.any(np.isfinite(fs.edge_true_time)) else fs.edge_time
    numbering = _frame_numbering(recording, fs.written_time, preroll, truth_edges)
    if numbering["misnumbered"]:
        notes.append(f"the host's synchroniser gave {numbering['misnumbered']} of {numbering['camera_frames']} "
                     "camera frames a wrong trigger frame number (scores use the host's numbers)")
    if host_summary.get("behind_skipped"):  # the bounded backlog of an overloaded host (issue 16)
        notes.append(f"the host fell more than 1 s behind real time: {host_summary['behind_skipped']} frames were "
                     "recorded but not tracked, so that it caught up")
    # Latency from the hand-over of the frames a bundle was made of to its estimate: independent of
    # the numbering, so a misnumbered frame still gets its true processing time.
    lat = []
    if result_times is None:
        for r in results:
            t0 = numbering["bundle_handoff"].get(r.frame, math.nan)
            if math.isfinite(t0):
                lat.append(r.t_result - t0)
        res_t = np.full(gt.n_frames, np.nan)
        for r in results:
            if 0 <= r.frame < gt.n_frames:
                res_t[r.frame] = r.t_result
    else:
        res_t = result_times
        for f, t0 in numbering["bundle_handoff"].items():
            if 0 <= f < res_t.size and math.isfinite(t0) and math.isfinite(res_t[f]):
                lat.append(res_t[f] - t0)
    lat_a = np.asarray(lat)
    # Per-frame timing and the ground truth, for whoever wants to look closer than the summary.
    np.savez(out / "frame_timing.npz", trigger_edge=fs.edge_time, handoff=fs.handoff_time, estimate=res_t)
    if scores is not None:
        np.savez(out / "ground_truth.npz", t=gt.t, pos=gt.pos, vel=gt.vel, axis=gt.axis, landed=gt.landed,
                 fps=gt.fps, warmup_frames=warmup)
    period = 1.0 / cfg.fps
    in_time = int(np.sum(lat_a < period)) if lat_a.size else 0
    recv = host_summary.get("receiver", {}).get("cameras", {})
    sync = host_summary.get("sync", {})
    lost = sum(int(c.get("lost", 0)) for c in recv.values())
    late = sum(int(s.get("late", 0)) for s in sync.values()) if isinstance(sync, dict) else 0
    hl = host_summary.get("latency", {})
    latency_host = {k.removeprefix("total_"): v for k, v in hl.items() if k.startswith("total_")}
    rendered_s = fs.frames_rendered / cfg.fps
    busy = fs.render_s + fs.write_s
    rt = rendered_s / busy if busy > 0 else float("inf")
    braidz = fig = None
    if scores is not None:
        braidz = _export_braidz(recording, out, notes)
        title = (f"{cfg.cameras} cameras, {cfg.animals} animals\n{cfg.fps:g} fps, {cfg.seconds:g} s, "
                 f"seed {cfg.seed}\n\nRMSE {scores.rmse_mm:.2f} mm\nMOTA {scores.mota:.3f}\n"
                 f"IDF1 {scores.idf1:.3f}\nID switches {scores.id_switches}\ntracks {scores.tracks_found}")
        dvs_obs = host_summary.get("dvs", {})
        if dvs_obs:  # which observations came from event cameras
            title += "\n\nDVS points used\n" + "\n".join(
                f"cam {i}: {v.get('points_used', 0)} in {v.get('frames_given', 0)} fr." for i, v in dvs_obs.items())
        fig = plot_tracks(gt, hyps, out / "tracks.png", title=title, latencies_ms=lat_a * 1e3)
    frames_triggered = max(fs.edges, fs.frames_rendered)
    return DemoReport(
        config={f.name: (str(v) if isinstance(v, Path) else v) for f in fields(cfg)
                if f.name not in ("flight", "render", "attach", "fault") for v in [getattr(cfg, f.name)]},
        trigger=trig.kind_label,
        trigger_note=trig.note,
        scores=scores,
        latency=latency_percentiles_ms(lat_a),
        latency_parts_p50_ms=numbering["parts_p50_ms"],
        trigger_time_bias_ms=numbering["trigger_time_bias_ms"],
        latency_host=latency_host,
        frames_triggered=min(frames_triggered, gt.n_frames),
        frames_rendered=fs.frames_rendered,
        frames_tracked=len(hyps) if scores is not None else int(np.isfinite(res_t).sum()),
        frames_in_time=in_time,
        packets_lost=lost,
        packets_late=late,
        frames_misnumbered=numbering["misnumbered"],
        camera_frames_sent=int(np.isfinite(fs.written_time).sum()),
        camera_frames_received=max(0, sum(int(c.get("frames", 0)) for c in recv.values()) - preroll * cfg.cameras),
        exposure_lateness=_lateness(fs.handoff_time, float(trigger_summary.get("fps", cfg.fps))),
        clock_model=_jsonable(trigger_summary),
        sim_priority_raised=bool(fs.priority_raised),
        world=_world(gt, cfg.close_distance_m),
        live_frames=live_frames,
        render_realtime_factor=float(rt),
        host_kept_up=bool(in_time >= 0.99 * min(frames_triggered, gt.n_frames)),
        recording=recording,
        braidz=braidz,
        figure=str(fig) if fig is not None else None,
        rig_file=str(rig_path),
        calibration=str(calib_path) if calib_path else None,
        wall_s=time.monotonic() - wall0,
        notes=[n for n in notes if n],
        host_summary=_jsonable(host_summary),
    )


def _world(gt: GroundTruth, close_m: float) -> dict[str, Any]:
    hs = gt.horizontal_speed()[~gt.landed]
    d = gt.pair_distances() if gt.n_animals > 1 else None
    return {
        **{k: v for k, v in gt.meta.items() if k != "step_s"},
        "horizontal_speed_mean_m_s": float(hs.mean()) if hs.size else float("nan"),
        "horizontal_speed_std_m_s": float(hs.std()) if hs.size else float("nan"),
        "landed_fraction": float(gt.landed.mean()),
        "closest_pass_m": float(d.min()) if d is not None else float("nan"),
        "animal_frames_in_close_pass": int(gt.close_frames(close_m).sum()),
    }


def _lateness(handoff: np.ndarray, fps: float) -> dict[str, float]:
    """How late each frame reached the edges compared with a perfect clock at the trigger's rate,
    anchored on the earliest frame: a real camera's is ~0; ours grows when the machine is busy."""
    n = np.arange(handoff.size)
    ok = np.isfinite(handoff)
    if not np.any(ok):
        return latency_percentiles_ms([])
    lag = handoff[ok] - n[ok] / fps
    return latency_percentiles_ms(lag - lag.min())


def _frame_numbering(recording: str | None, written: np.ndarray, preroll: int = 0,
                     edge_time: np.ndarray | None = None) -> dict[str, Any]:
    """Check the host's frame numbering against the truth, from the recording's 2D rows.

    Every edge got `preroll` frames before the trigger started, then every pulse's frame in order from
    the first, so camera frame c is trigger frame c - preroll. `written` (frames, cameras) is when each
    frame was completely in its edge's input: where the measured latency starts (what came before, the
    exposure and the image transfer, is simulated).
    Returns the count of camera frames numbered otherwise, and per host trigger frame the hand-over
    time of the latest camera frame it was built from."""
    out: dict[str, Any] = {"misnumbered": 0, "camera_frames": 0, "bundle_handoff": {}, "parts_p50_ms": {},
                           "trigger_time_bias_ms": math.nan}
    if not recording or not Path(recording).exists():
        return out
    from flytrack_host.recording.schema import FLAG_TRACKED
    from flytrack_host.recording.source import open_source

    src = open_source(recording)  # a recording in parts or not
    if "data2d_distorted" not in src.table_names:
        return out
    d = src.table("data2d_distorted")
    lat = src.table("latency") if "latency" in src.table_names else None
    from flytrack_host.recording.schema import FLAG_DVS

    d = d[(d["camera_frame"] >= preroll) & ((d["flags"] & FLAG_DVS) == 0)]  # frame cameras' rows
    if len(d) == 0:
        return out
    d["camera_frame"] -= preroll
    key = d["camera_index"].astype(np.int64) * (1 << 40) + d["camera_frame"].astype(np.int64)
    _, first = np.unique(key, return_index=True)
    u = d[first]  # one row per camera frame
    out["camera_frames"] = int(len(u))
    out["misnumbered"] = int(np.sum(u["trigger_frame"] != u["camera_frame"]))
    written = np.asarray(written, dtype=np.float64).reshape(written.shape[0], -1)

    def written_at(rows: np.ndarray) -> np.ndarray:
        cf = rows["camera_frame"].astype(np.int64)
        cam = rows["camera_index"].astype(np.int64)
        ok = (cf >= 0) & (cf < written.shape[0]) & (cam >= 0) & (cam < written.shape[1])
        t = np.full(len(rows), np.nan)
        t[ok] = written[cf[ok], cam[ok]]
        return t

    tracked = u[(u["flags"] & FLAG_TRACKED) != 0]
    tf = tracked["trigger_frame"].astype(np.int64)
    t = written_at(tracked)
    bh: dict[int, float] = {}
    for a, b in zip(tf.tolist(), t.tolist(), strict=True):
        if math.isfinite(b) and b > bh.get(a, -math.inf):
            bh[a] = b
    out["bundle_handoff"] = bh
    # Where the time goes (medians, ms): frame to the edge's read, extraction, UDP to the host's
    # receiver, then synchronisation and tracking in the host.
    parts = {
        "edge_read": u["edge_recv_ns"] / 1e9 - written_at(u),
        "extraction": (u["edge_done_ns"].astype(np.int64) - u["edge_recv_ns"].astype(np.int64)) / 1e9,
        "udp_to_host": u["cam_received_timestamp"] - u["edge_done_ns"] / 1e9,
    }
    if lat is not None and len(lat):
        parts["sync_and_track"] = lat["estimate_time"] - lat["last_arrival"]
    if edge_time is not None and edge_time.size:
        # The host's trigger time of each frame (from its clock model) against the moment the
        # simulated cameras saw that pulse in the trigger's edge stream (itself ~0.1 ms after it).
        cf = u["camera_frame"].astype(np.int64)
        ok = (cf >= 0) & (cf < edge_time.size) & (u["trigger_frame"] == u["camera_frame"])
        bias = u["timestamp"][ok] - edge_time[cf[ok]]
        bias = bias[np.isfinite(bias)]
        if bias.size:
            out["trigger_time_bias_ms"] = float(np.median(bias) * 1e3)
    for k, v in parts.items():
        v = np.asarray(v, dtype=float)
        v = v[np.isfinite(v)]
        if v.size:
            out["parts_p50_ms"][k] = float(np.median(v) * 1e3)
    return out


def _export_braidz(recording: str | None, out: Path, notes: list[str]) -> str | None:
    if not recording or not Path(recording).exists():
        notes.append("no finalised recording to export")
        return None
    from flytrack_host.io.braidz import export_braidz

    dest = out / "recording.braidz"
    export_braidz(recording, dest)  # a recording in parts is read part by part
    return str(dest)


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def write_json(report: DemoReport, path: Path) -> None:
    data = report.as_dict()
    data["goals"] = [asdict(g) for g in check_goals(report)]
    Path(path).write_text(json.dumps(_jsonable(data), indent=1))
