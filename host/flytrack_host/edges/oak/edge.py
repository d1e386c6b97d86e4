"""`OakEdge`: frames from a `FrameSource` -> the C feature extractor -> FEATURES and STATUS over UDP.

The same datagrams as `flytrack-edge` (protocol/SPEC.md): one FEATURES per frame (SPLIT above 32
points, or TRUNCATED with `truncate`), a STATUS heartbeat every `status_interval` s and a last one on
stop. camera_frame is the device's sequence number; after a reconnect the device counts from 0 again,
so the edge adds an offset that keeps camera_frame increasing for the host.
"""

from __future__ import annotations

import logging
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from flytrack_host.edges.features.extractor import ExtractorParams, FeatureError, FeatureExtractor
from flytrack_host.edges.oak.source import BadFrame, DeviceLost, FrameSource, OakFrame, frame_from_imgframe
from flytrack_host.protocol import CameraState, EdgeStatus, FeatureFrame, PixelFormat, encode
from flytrack_host.protocol.udp import encode_features, make_points

log = logging.getLogger(__name__)

# last_error_code values, as flytrack-edge's (edge_main.c): 30 extraction failed, 40 source failed.
ERR_EXTRACT = 30
ERR_SOURCE = 40
ERR_BAD_FRAME = 41


@dataclass
class OakEdgeConfig:
    host: str = "127.0.0.1"
    port: int = 9000
    camera_index: int = 0
    camera_name: str = "oak"
    width: int = 640
    height: int = 400
    params: ExtractorParams = field(default_factory=ExtractorParams)
    truncate: bool = False
    status_interval: float = 1.0
    reconnect_tries: int = 5  # consecutive failed opens before giving up; 0 = never reconnect
    reconnect_delay: float = 1.0  # s between attempts, doubled each failure up to 8 s
    max_frames: int = 0  # 0 = run until stopped


def wire_points(pts: np.ndarray) -> np.ndarray:
    """Extractor points (f64) as the wire's f32 records, clamped to +-3e38 (NaN kept) as the C daemon's
    clamp_f32 does, so a huge value never becomes an infinity the codec rejects."""
    out = make_points(len(pts))
    for name in _F32_FIELDS:
        v = np.asarray(pts[name], np.float64)
        out[name] = np.where(np.isnan(v), v, np.clip(v, -3.0e38, 3.0e38))
    out["cur_val"] = pts["cur_val"]
    return out


_F32_FIELDS = ("x_dist", "y_dist", "x_undist", "y_undist", "area", "peak_diff", "orientation", "eccentricity",
               "mean_val", "sumsq_val")


class OakEdgeError(RuntimeError):
    """The edge gave up (device gone for good): one clear line for the user."""


def _now_ns() -> int:
    return time.time_ns()  # edge_recv_ns / edge_done_ns are CLOCK_REALTIME, as in the C daemon


class OakEdge:
    def __init__(self, source: FrameSource, cfg: OakEdgeConfig,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.source = source
        self.cfg = cfg
        self._sleep = sleep
        self.extractor = FeatureExtractor(cfg.width, cfg.height, "mono8", cfg.params)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.addr = (cfg.host, cfg.port)
        self.seq = 0
        self.state = CameraState.IDLE
        self.last_error_code = 0
        self.last_error = ""
        self.frames_seen = 0
        self.frames_dropped = 0
        self.reconnects = 0
        self.send_errors = 0
        self._frame_offset = 0  # added to the device's sequence numbers after a reconnect
        self._last_frame = -1
        self._last_seq_num = -1
        self._win_start = time.monotonic()
        self._win_frames = 0
        self._win_proc_sum = 0.0
        self._win_proc_max = 0.0
        self._fps = self._proc_mean = self._proc_max = 0.0
        self._stop = False

    # ------------------------------------------------------------ sending
    def _send(self, data: bytes) -> None:
        try:
            self.sock.sendto(data, self.addr)
        except OSError as exc:  # the host being away must not stop the edge: counted, logged once
            if self.send_errors == 0:
                log.warning("sendto %s:%d: %s (counted, going on)", *self.addr, exc)
            self.send_errors += 1
        self.seq = (self.seq + 1) & 0xFFFFFFFF

    def send_status(self) -> None:
        self._send(encode(EdgeStatus(
            camera_index=self.cfg.camera_index, width=self.cfg.width, height=self.cfg.height,
            pixel_format=int(PixelFormat.MONO8), state=int(self.state), seq=self.seq,
            last_error_code=self.last_error_code, frames_seen=self.frames_seen,
            frames_dropped=self.frames_dropped, fps=self._fps, proc_us_mean=self._proc_mean,
            proc_us_max=self._proc_max, camera_name=self.cfg.camera_name[:32],
            last_error=self.last_error[:64],
        )))

    def _set_error(self, code: int, text: str) -> None:
        self.last_error_code, self.last_error = code, text
        log.error("%s", text)

    # ------------------------------------------------------------ frames
    def process(self, frame: OakFrame, recv_ns: int) -> None:
        """Extract and send one frame."""
        if frame.image.shape != (self.cfg.height, self.cfg.width):
            raise BadFrame(f"frame {frame.sequence_num} is {frame.image.shape[1]}x{frame.image.shape[0]}, "
                           f"the edge was set up for {self.cfg.width}x{self.cfg.height}")
        camera_frame = self._frame_offset + frame.sequence_num
        t0 = time.perf_counter()
        ff = self.extractor.process(frame.image)
        us = (time.perf_counter() - t0) * 1e6
        self._win_frames += 1
        self._win_proc_sum += us
        self._win_proc_max = max(self._win_proc_max, us)
        self.frames_seen += 1
        self._last_frame = camera_frame
        msg = FeatureFrame(camera_index=self.cfg.camera_index, seq=self.seq, camera_frame=camera_frame,
                           trigger_frame=-1, device_timestamp_ns=frame.device_timestamp_ns,
                           edge_recv_ns=recv_ns, edge_done_ns=_now_ns(), total_points=ff.total_points,
                           points=wire_points(ff.points))
        for dgram in encode_features(msg, truncate=self.cfg.truncate):
            self._send(dgram)

    def _tick(self, force: bool = False) -> None:
        now = time.monotonic()
        dt = now - self._win_start
        if dt >= 1.0:
            self._fps = self._win_frames / dt
            self._proc_mean = self._win_proc_sum / self._win_frames if self._win_frames else 0.0
            self._proc_max = self._win_proc_max
            self._win_start, self._win_frames, self._win_proc_sum, self._win_proc_max = now, 0, 0.0, 0.0
        if force or now - self._last_status >= self.cfg.status_interval:
            self.send_status()
            self._last_status = now

    # ------------------------------------------------------------ lifecycle
    def _connect(self) -> None:
        """Opens the source, retrying with backoff; raises OakEdgeError after reconnect_tries failures."""
        delay = self.cfg.reconnect_delay
        tries = 0
        while True:
            try:
                self.source.open()
            except DeviceLost as exc:
                tries += 1
                self.state = CameraState.ERROR
                self._set_error(ERR_SOURCE, f"OAK open failed: {exc}")
                self._tick(force=True)
                if tries > self.cfg.reconnect_tries:
                    raise OakEdgeError(f"OAK device not available after {tries} attempts: {exc}") from exc
                self._sleep(delay)
                delay = min(delay * 2, 8.0)
                continue
            self.state = CameraState.RUNNING
            if self.last_error_code == ERR_SOURCE:
                self.last_error_code, self.last_error = 0, ""
            return

    def stop(self) -> None:
        self._stop = True

    def run(self) -> int:
        """Runs until stopped, max_frames, or the device is gone for good (OakEdgeError). Returns the
        number of frames processed."""
        self._last_status = time.monotonic()
        processed = 0
        try:
            self._connect()
            self._tick(force=True)
            while not self._stop:
                try:
                    img = self.source.get(timeout=0.05)
                except DeviceLost as exc:
                    # Say so at once (STATUS ERROR with the reason), then reconnect; frames of the new
                    # session continue after the last camera_frame sent.
                    self.state = CameraState.ERROR
                    self._set_error(ERR_SOURCE, f"OAK device lost after frame {self._last_frame}: {exc}")
                    self._tick(force=True)
                    self.source.close()
                    if self.cfg.reconnect_tries <= 0:
                        raise OakEdgeError(self.last_error) from exc
                    self._sleep(self.cfg.reconnect_delay)
                    self._connect()
                    self.reconnects += 1
                    self._frame_offset = self._last_frame + 1
                    self._last_seq_num = -1
                    self._tick(force=True)
                    continue
                if img is not None:
                    recv_ns = _now_ns()
                    # The device drops frames when the host is slow: its sequence numbers show how many.
                    seqn = int(img.getSequenceNum())
                    if self._last_seq_num >= 0 and seqn > self._last_seq_num + 1:
                        self.frames_dropped += seqn - self._last_seq_num - 1
                    self._last_seq_num = seqn
                    try:
                        self.process(frame_from_imgframe(img), recv_ns)
                    except BadFrame as exc:
                        self.frames_dropped += 1
                        self._set_error(ERR_BAD_FRAME, str(exc))
                    except FeatureError as exc:
                        self.frames_dropped += 1
                        self._set_error(ERR_EXTRACT, str(exc))
                    processed += 1
                    if self.cfg.max_frames and processed >= self.cfg.max_frames:
                        break
                self._tick()
        finally:
            if self.state != CameraState.ERROR:
                self.state = CameraState.STOPPED
            self._tick(force=True)  # the last word: why we stopped
            self.source.close()
        return processed

    def close(self) -> None:
        self.sock.close()
        self.extractor.close()
