"""Collection of LED detections from the live rig: FEATURES datagrams over UDP -> calibration points.

A frame of a camera is kept only when that camera reports exactly one feature point (the LED): zero
means it did not see it, two or more mean a reflection or another light, which would poison the
calibration. The trigger frame number (or the camera frame when the trigger is unknown) links views.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from flytrack_host.calibration.observations import Observations

__all__ = ["Collector", "collect_udp"]


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
