"""The DVS (event camera) part of the simulated rig: the edge command lines for event streams, and
after the run the per-camera event counts and the tracking scored with and without the DVS points."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from flytrack_host.geometry.camera import Camera
from flytrack_host.sim.demo_config import DemoConfig
from flytrack_host.sim.flight import GroundTruth
from flytrack_host.sim.report import _scored_mask
from flytrack_host.tracking.evaluation import FrameTracks, score_tracks

# DVS slice length in the demo: 2 slices per 100 fps frame keeps the host's datagram load low (1 ms
# slices are 1000 datagrams/s per DVS camera for the Python receiver).
DVS_SLICE_US = 5000


def dvs_edge_command(edge_bin: Path, cam_index: int, cam: Camera, port: int,
                     slice_us: int = DVS_SLICE_US) -> list[str]:
    """The command line of one edge reading a DVS camera's event stream (EVT 2.0) from stdin."""
    return [
        str(edge_bin), "--source", "events", "--input", "-",
        "--camera-index", str(cam_index), "--camera-name", cam.name,
        "--host", "127.0.0.1", "--port", str(port), "--control-port", "0", "--slice-us", str(slice_us),
        "--realtime", "0",  # the events come as they happen: no pacing by their times on top
    ] + dvs_support_options(cam.width, cam.height)


def dvs_support_options(width: int, height: int) -> list[str]:
    """The edge's noise-filter window and cluster support for a sensor smaller than a DAVIS346 (the
    library defaults' class): an animal crosses s = 346 / side times fewer pixels, so it gives s times
    fewer events (support / s) and each pixel's neighbours fire sparser and later (window x s^2; the
    simulated background activity, 0.05 Hz per pixel, lets 8 x 0.05 Hz x 14.6 ms = 0.6 % of the noise
    through at 128 px). With the defaults a 128 x 128 sensor found 6 clusters in 2 s."""
    side = max(int(width), int(height))
    if side <= 0 or side >= 346:
        return []
    s = 346.0 / side
    return ["--ba-window-us", str(round(2000 * s * s)), "--cluster-min-mass", f"{5.0 / s:.3f}"]

def _dvs_comparison(cfg: DemoConfig, gt: GroundTruth, cams: list[Camera], warmup: int, host: Any,
                    dvs_indices: range) -> dict[str, Any]:
    """The run's bundles tracked again, with and without the DVS cameras' points, scored alike."""
    from flytrack_host.dvs.clusters.comparison import with_and_without

    runs = with_and_without(list(host.dvs_bundles), host.cameras, host.params, 1.0 / cfg.fps, dvs_indices)
    scored = _scored_mask(gt, cams)
    scored[:warmup] = False
    out: dict[str, Any] = {"bundles": len(host.dvs_bundles)}
    for name, run in runs.items():
        hyps = [FrameTracks(f, ids, pos) for f, ids, pos in run.frames if 0 <= f < gt.n_frames]
        sc = score_tracks(gt.pos, hyps, scored=scored, close=gt.close_frames(cfg.close_distance_m),
                          match_threshold_m=cfg.match_threshold_m, close_window=int(round(0.1 * cfg.fps)))
        out[name] = {"rmse_mm": sc.rmse_mm, "mota": sc.mota, "idf1": sc.idf1, "id_switches": sc.id_switches,
                     "false_positives": sc.false_positives, "misses": sc.misses,
                     "dvs_points": int(run.stats.get("own_cov_points", 0)),
                     "dvs_points_used": int(run.stats.get("own_cov_used", 0)),
                     "dvs_points_gated_out": int(run.stats.get("own_cov_gated_out", 0))}
    return out


def _dvs_counts(dvs_cams: list[Camera], first: int, fs: Any, host_summary: dict[str, Any],
                sensor: str) -> list[dict[str, Any]]:
    """Per DVS camera: events (and sync events) the simulated sensor wrote into its edge, and what the
    host heard back: the events the edge read (its last STATUS), its slices and clusters."""
    recv = host_summary.get("receiver", {}).get("cameras", {})
    out = []
    for i, c in enumerate(dvs_cams):
        r = recv.get(first + i, recv.get(str(first + i), {}))
        obs = host_summary.get("dvs", {})
        o = obs.get(first + i, obs.get(str(first + i), {}))
        sent = int(fs.dvs_events_sent[i]) if i < len(fs.dvs_events_sent) else 0
        got = int(r.get("status_frames_seen", 0))
        out.append({
            "name": c.name, "camera_index": first + i, "sensor": sensor, "width": c.width, "height": c.height,
            "events_sent": sent, "sync_events_sent": int(fs.dvs_syncs_sent[i]) if i < len(fs.dvs_syncs_sent) else 0,
            "events_received": got, "events_lost": sent - got,
            "edge_events_dropped": int(r.get("status_frames_dropped", 0)),
            "slices_received": int(r.get("dvs_slices", 0)), "clusters_received": int(r.get("dvs_clusters", 0)),
            "datagrams_lost": int(r.get("lost", 0)),
            # What the 3D tracker got from this camera: trigger frames with its clusters, and points
            "frames_observed": int(o.get("frames_given", 0)), "points_observed": int(o.get("points_given", 0)),
            "points_used": int(o.get("points_used", 0)),
            "sensor_t0_us_estimated": o.get("t0_us"),
        })
    return out
