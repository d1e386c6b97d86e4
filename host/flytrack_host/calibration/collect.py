"""Collection of LED detections -> calibration points: live (FEATURES datagrams over UDP) or from a recording.

A frame of a camera is kept only when that camera reports exactly one feature point (the LED): zero
means it did not see it, two or more mean a reflection or another light, which would poison the
calibration. Live, the trigger frame number (or the camera frame when the trigger is unknown) links views;
in a recording, only frames mapped to the trigger count are used (others cannot be matched across cameras).
"""

from __future__ import annotations

import socket
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flytrack_host.calibration.observations import Observations

__all__ = ["Collector", "RecordingPoints", "collect_udp", "points_from_recording"]


@dataclass
class Collector:
    camera_names: list[str]  # index in FEATURES camera_index -> name
    sizes: list[tuple[int, int]]
    frames: list[int] = field(default_factory=list)
    cams: list[int] = field(default_factory=list)
    uvs: list[tuple[float, float]] = field(default_factory=list)
    rejected_multi: int = 0
    bad_datagrams: int = 0
    unknown_camera: int = 0
    _seen: set[tuple[int, int]] = field(default_factory=set)

    def add_datagram(self, data: bytes) -> None:
        from flytrack_host.protocol import FeatureFrame, ProtocolError, decode_datagram

        try:
            msg = decode_datagram(data)
        except ProtocolError:
            self.bad_datagrams += 1  # counted and dropped: a bad packet must not stop the collection
            return
        if not isinstance(msg, FeatureFrame):
            return
        ci = int(msg.camera_index)
        if ci >= len(self.camera_names):
            self.unknown_camera += 1
            return
        if msg.part_count > 1 or msg.total_points != 1 or len(msg.points) != 1:
            if msg.total_points > 1 or len(msg.points) > 1:
                self.rejected_multi += 1
            return
        frame = int(msg.trigger_frame) if msg.trigger_frame >= 0 else int(msg.camera_frame)
        if (frame, ci) in self._seen:
            return
        self._seen.add((frame, ci))
        p = msg.points[0]
        self.frames.append(frame)
        self.cams.append(ci)
        self.uvs.append((float(p["x_dist"]), float(p["y_dist"])))

    def counts(self) -> np.ndarray:
        return np.bincount(np.asarray(self.cams, dtype=np.int64), minlength=len(self.camera_names))

    def coverage(self) -> list[float]:
        """Fraction of a 4x4 grid of image cells that hold points, per camera."""
        out = []
        uv = np.asarray(self.uvs, dtype=float).reshape(-1, 2)
        cams = np.asarray(self.cams, dtype=np.int64)
        for c, (w, h) in enumerate(self.sizes):
            s = uv[cams == c]
            cells = {(int(min(3, max(0, u / w * 4))), int(min(3, max(0, v / h * 4)))) for u, v in s}
            out.append(len(cells) / 16.0)
        return out

    def observations(self) -> Observations:
        return Observations(np.asarray(self.frames, dtype=np.int64), np.asarray(self.cams, dtype=np.int32),
                            np.asarray(self.uvs, dtype=np.float64).reshape(-1, 2), list(self.camera_names),
                            list(self.sizes))


def collect_udp(collector: Collector, port: int, duration_s: float, host: str = "0.0.0.0",
                progress: Callable[[Collector], None] | None = None, progress_every_s: float = 1.0) -> Collector:
    """Receive FEATURES datagrams for duration_s seconds (or until Ctrl-C) into the collector."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((host, port))
    sock.settimeout(0.1)
    t_end = time.monotonic() + duration_s
    t_next = time.monotonic() + progress_every_s
    try:
        while time.monotonic() < t_end:
            try:
                data = sock.recv(2048)
            except TimeoutError:
                data = b""
            if data:
                collector.add_datagram(data)
            if progress is not None and time.monotonic() >= t_next:
                progress(collector)
                t_next += progress_every_s
    except KeyboardInterrupt:
        pass  # the user stops waving: keep what was collected
    finally:
        sock.close()
    return collector


@dataclass
class RecordingPoints:
    obs: Observations
    frames_multi: int  # camera frames with 2 or more points (skipped)
    frames_unmapped: int  # camera frames with no trigger frame number (skipped)
    rows_rejected: int  # rows the recorder marked rejected (duplicates, future-dated; skipped)


def _recorded_sizes(rec: object) -> dict[str, tuple[int, int]]:
    """Image sizes of the calibration stored in a recording (none when there is none or it is unreadable)."""
    from flytrack_host.geometry.formats import CalibrationFormatError, load_calibration

    cal = rec.calibration  # type: ignore[attr-defined]
    if cal is None:
        return {}
    name, data = cal
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / name
        p.write_bytes(data)
        try:
            cams = load_calibration(p)
        except (CalibrationFormatError, ValueError, OSError):
            return {}
    return {k: (c.width, c.height) for k, c in cams.items()}


def points_from_recording(path: str | Path, sizes: Mapping[str, tuple[int, int]] | None = None) -> RecordingPoints:
    """Single-LED detections of a FlyTrack recording (raw folder or recording.h5) as calibration points.

    Camera names come from the recording's cam_info table (the calibration name when set), image sizes
    from `sizes` or else from the calibration stored in the recording. Raises ValueError (with what to do)
    when the recording cannot be read or a camera's image size is unknown."""
    from flytrack_host.recording import RecordingError, load_recording
    from flytrack_host.recording.schema import FLAG_REJECTED

    try:
        rec = load_recording(path)
    except (RecordingError, OSError) as exc:
        raise ValueError(f"cannot read the recording: {exc}") from None
    rows = rec.table("data2d_distorted")
    if not len(rows):
        raise ValueError(f"{path}: the recording has no 2D points (data2d_distorted is empty).")
    names: dict[int, str] = {}
    for r in rec.table("cam_info"):
        cid = r["calibration_id"].decode(errors="replace")
        names[int(r["camera_index"])] = cid or r["name"].decode(errors="replace")
    for ci in np.unique(rows["camera_index"]):
        names.setdefault(int(ci), f"cam{int(ci)}")
    known = dict(_recorded_sizes(rec))
    known.update(sizes or {})
    order = sorted(names)
    missing = [names[i] for i in order if names[i] not in known]
    if missing:
        raise ValueError(f"image size unknown for camera(s) {', '.join(missing)}: the recording holds no calibration "
                         "with them. Give --camera NAME=WIDTHxHEIGHT for each.")
    rejected = (rows["flags"] & FLAG_REJECTED) != 0
    rows_ok = rows[~rejected]
    # One camera frame: all rows with the same (camera, camera_frame); the LED frames have exactly one point.
    key = rows_ok["camera_index"].astype(np.int64) << 48 | rows_ok["camera_frame"].astype(np.int64)
    _, first, count = np.unique(key, return_index=True, return_counts=True)
    fr = rows_ok[first]
    has_point = np.isfinite(fr["x_dist"]) & np.isfinite(fr["y_dist"])
    single = (count == 1) & (fr["total_points"] <= 1) & has_point
    multi = (count > 1) | (fr["total_points"] > 1)
    mapped = fr["trigger_frame"] >= 0
    use = fr[single & mapped]
    # The same trigger frame twice for one camera cannot be told apart: keep neither.
    k2 = use["camera_index"].astype(np.int64) << 48 | use["trigger_frame"].astype(np.int64)
    _, inv2, c2 = np.unique(k2, return_inverse=True, return_counts=True)
    use = use[c2[inv2] == 1]
    pos = {ci: i for i, ci in enumerate(order)}
    cam = np.array([pos[int(c)] for c in use["camera_index"]], dtype=np.int32)
    srt = np.lexsort((cam, use["trigger_frame"]))
    obs = Observations(use["trigger_frame"][srt].astype(np.int64), cam[srt],
                       np.stack([use["x_dist"], use["y_dist"]], axis=1)[srt].astype(np.float64),
                       [names[i] for i in order], [tuple(known[names[i]]) for i in order])
    return RecordingPoints(obs, int(np.sum(multi)), int(np.sum(single & ~mapped)), int(rejected.sum()))
