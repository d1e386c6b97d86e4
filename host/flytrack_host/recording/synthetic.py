"""Recordings of synthetic scenarios (tracking.synthetic): 2D points of known flights in a calibrated
rig, written as a FlyTrack recording with its calibration, for offline tools' tests and benchmarks."""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.recording.parts import PartPolicy
from flytrack_host.recording.schema import CAM_INFO, FLAG_TRACKED
from flytrack_host.recording.writer import Recorder


def start_synthetic_recording(path: Path, scenario: Any, fps: float, *, flush_s: float = 0.2, on_full: str = "drop",
                              rig_name: str = "synthetic", parts: PartPolicy | None = None) -> Recorder:
    """A started Recorder holding the scenario's rig: calibration.xml, cam_info (cameras named camN) and
    the textlog's frame-rate line, as a live run writes them before its first frame. `parts`: record in
    parts (recording/parts.py)."""
    from flytrack_host.geometry.formats import save_flydra_xml
    from flytrack_host.tracking.params import TrackingParams

    names = {i: f"cam{i}" for i in scenario.cameras}
    meta = {"rig_name": rig_name, "fps": fps, "tracking_params": TrackingParams().model_dump()}
    rec = Recorder(path, flush_s, meta=meta, on_full=on_full, parts=parts)
    rec.start()
    with tempfile.TemporaryDirectory() as d:
        cal = Path(d) / "calibration.xml"
        save_flydra_xml({names[i]: c for i, c in scenario.cameras.items()}, cal)
        rec.attach("calibration.xml", cal.read_bytes())
    ci = np.zeros(len(names), dtype=CAM_INFO)
    for k, (i, n) in enumerate(names.items()):
        ci[k] = (i, n.encode(), b"127.0.0.1", n.encode())
    rec.append("cam_info", ci)
    rec.log(f"MainBrain running at {fps:g} fps")
    return rec


def write_scenario_frames(rec: Recorder, scenario: Any, fps: float, *, track: bool, t0: float = 1000.0,
                          camera_frame_offset: int = 0,
                          on_frame: Callable[[int, Any], None] | None = None) -> None:
    """Append every bundle's 2D rows (trigger time t0 + frame / fps, arrival 2 ms later) and, with `track`,
    the real tracker's kalman_estimates and data_association rows, a frame's rows queued as one item as the
    pipeline queues them (so a recording in parts never splits a frame). Each camera frame is numbered
    trigger frame + `camera_frame_offset`; `on_frame(n, bundle)` runs after each bundle."""
    from flytrack_host.intake.sync import CameraFrame
    from flytrack_host.recording.rows import data2d_rows, result_rows
    from flytrack_host.tracking.params import TrackingParams
    from flytrack_host.tracking.tracker import Tracker

    tracker = Tracker(scenario.cameras, TrackingParams(), 1 / fps) if track else None
    for n, b in enumerate(scenario.bundles):
        b.timestamp = t0 + b.trigger_frame / fps
        cam_frame = b.trigger_frame + camera_frame_offset
        rows = [data2d_rows(CameraFrame(cam, cam_frame, -1, pts, b.timestamp + 0.002), b.trigger_frame,
                            b.timestamp, FLAG_TRACKED) for cam, pts in b.detections.items()]
        items = [("data2d_distorted", np.concatenate(rows))] if rows else []
        if tracker is not None:
            k, a = result_rows(tracker.process(b), b.timestamp)
            items += [("kalman_estimates", k), ("data_association", a)]
        rec.append_many(items)
        if on_frame is not None:
            on_frame(n, b)


def write_synthetic_recording(path: Path, n_cameras: int = 4, n_targets: int = 2, duration_s: float = 2.0,
                              fps: float = 100.0, seed: int = 0) -> Path:
    """Write a finalised recording of 2D data only (no 3D estimates) to `path`; returns its recording.h5."""
    from flytrack_host.tracking.synthetic import make_scenario

    sc = make_scenario(n_cameras=n_cameras, n_targets=n_targets, duration_s=duration_s, fps=fps,
                       close_pass_m=None, enter_exit=False, false_positives_per_camera=0.0, seed=seed)
    rec = start_synthetic_recording(path, sc, fps, flush_s=1.0, on_full="block",
                                    rig_name=f"synthetic seed {seed}")
    write_scenario_frames(rec, sc, fps, track=False)
    return rec.stop(finalize=True)
