"""A pair of recordings of the same synthetic flight, one unparted and one in parts, written from the same
stream of queued items: what a reader gives for the one it must give for the other."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from flytrack_host.intake.sync import CameraFrame
from flytrack_host.recording.parts import PartPolicy
from flytrack_host.recording.rows import data2d_rows
from flytrack_host.recording.schema import CAMERA_STATUS, FLAG_LATE, FLAG_REJECTED, LATENCY, TRIGGER_CLOCK
from flytrack_host.recording.synthetic import start_synthetic_recording, write_scenario_frames
from flytrack_host.tracking.synthetic import make_scenario

FPS = 100.0
PART_BYTES = 90_000  # about a third of a second of this flight: 8 parts


@dataclass
class Pair:
    whole: Path
    parted: Path
    frames: int


def write_pair(d: Path, part_bytes: int = PART_BYTES, seed: int = 7, duration_s: float = 3.0) -> Pair:
    """The same items queued to an unparted recorder and to one in parts: each frame's 2D rows, estimates
    and associations as one item (as the pipeline queues them), its latency row apart, and every third frame
    a camera's frame again, late (FLAG_LATE), six frames later; rows rejected live and rows with no trigger
    frame; camera status and trigger clock rows."""
    sc = make_scenario(n_cameras=4, n_targets=3, duration_s=duration_s, fps=FPS, close_pass_m=None,
                       enter_exit=True, false_positives_per_camera=0.3, seed=seed)
    paths = {}
    for name, parts in (("whole", None), ("parted", PartPolicy(bytes=part_bytes))):
        path = d / f"{name}.flytrack"
        rec = start_synthetic_recording(path, sc, FPS, on_full="block", parts=parts, rig_name="pair")
        late: list = []

        def extra(n: int, b, rec=rec, late=late) -> None:  # noqa: ANN001
            lat = np.zeros(1, LATENCY)
            lat["trigger_frame"], lat["trigger_time"] = b.trigger_frame, b.timestamp
            lat["estimate_time"] = b.timestamp + 0.001 + 0.0001 * (n % 13)
            rec.append("latency", lat)
            if late and late[0][0] <= n:  # a camera frame that came two frames after its own
                _, cam, pts, tf, t = late.pop(0)
                rec.append("data2d_distorted", data2d_rows(CameraFrame(cam, tf + 500, -1, pts, t + 0.06), tf, t,
                                                           FLAG_LATE))
            if n % 3 == 1 and b.detections:
                cam = sorted(b.detections)[n % len(b.detections)]
                late.append((n + 6, cam, b.detections[cam][:1], b.trigger_frame, b.timestamp))
            if n % 50 == 10:
                pts = np.zeros(0, dtype=b.detections[sorted(b.detections)[0]].dtype) if b.detections else None
                if pts is not None:
                    rec.append("data2d_distorted", data2d_rows(CameraFrame(1, 9, -1, pts, b.timestamp), -1, np.nan, 0))
                    rec.append("data2d_distorted", data2d_rows(CameraFrame(2, 3, -1, pts, b.timestamp), 3,
                                                               b.timestamp, FLAG_REJECTED))
                st = np.zeros(1, CAMERA_STATUS)
                st["host_time"], st["camera_index"], st["frames_seen"] = b.timestamp, n % 4, n
                clk = np.zeros(1, TRIGGER_CLOCK)
                clk[0] = (b.timestamp, b.trigger_frame, 0.5, b.timestamp + 0.001)
                rec.append_many([("camera_status", st), ("trigger_clock_info", clk)])

        write_scenario_frames(rec, sc, FPS, track=True, camera_frame_offset=500, on_frame=extra)
        rec.log("the end")
        rec.stop()
        paths[name] = path
    return Pair(paths["whole"], paths["parted"], len(sc.bundles))


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> Pair:
    return write_pair(tmp_path_factory.mktemp("pair"))
