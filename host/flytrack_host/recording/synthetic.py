"""Recordings of synthetic scenarios (tracking.synthetic): 2D points of known flights in a calibrated
rig, written as a FlyTrack recording with its calibration, for offline tools' tests and benchmarks."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from flytrack_host.recording.schema import CAM_INFO, FLAG_TRACKED
from flytrack_host.recording.writer import Recorder


def write_synthetic_recording(path: Path, n_cameras: int = 4, n_targets: int = 2, duration_s: float = 2.0,
                              fps: float = 100.0, seed: int = 0) -> Path:
    """Write a finalised recording of 2D data only (no 3D estimates) to `path`; returns its recording.h5."""
    from flytrack_host.calibration.formats import save_flydra_xml
    from flytrack_host.pipeline import data2d_rows
    from flytrack_host.sync import CameraFrame
    from flytrack_host.tracking.params import TrackingParams
    from flytrack_host.tracking.synthetic import make_scenario

    sc = make_scenario(n_cameras=n_cameras, n_targets=n_targets, duration_s=duration_s, fps=fps,
                       close_pass_m=None, enter_exit=False, false_positives_per_camera=0.0, seed=seed)
    names = {i: f"cam{i}" for i in sc.cameras}
    rec = Recorder(path, 1.0, on_full="block", meta={"rig_name": f"synthetic seed {seed}", "fps": fps,
                                                     "tracking_params": TrackingParams().model_dump()})
    rec.start()
    with tempfile.TemporaryDirectory() as d:
        cal = Path(d) / "calibration.xml"
        save_flydra_xml({names[i]: c for i, c in sc.cameras.items()}, cal)
        rec.attach("calibration.xml", cal.read_bytes())
    ci = np.zeros(len(names), dtype=CAM_INFO)
    for k, (i, n) in enumerate(names.items()):
        ci[k] = (i, n.encode(), b"127.0.0.1", n.encode())
    rec.append("cam_info", ci)
    rec.log(f"MainBrain running at {fps:g} fps")
    rows = []
    for b in sc.bundles:
        t = 1000.0 + b.trigger_frame / fps
        for cam, pts in b.detections.items():
            fr = CameraFrame(cam, b.trigger_frame, -1, pts, t + 0.002)
            rows.append(data2d_rows(fr, b.trigger_frame, t, FLAG_TRACKED))
    rec.append("data2d_distorted", np.concatenate(rows))
    return rec.stop(finalize=True)
