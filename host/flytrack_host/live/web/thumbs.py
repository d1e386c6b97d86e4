"""Camera thumbnails for the live page, from the edges' IMAGE messages (protocol/SPEC.md 1.5).

The receiver hands every IMAGE chunk to `add` (on the tracking thread: a bounded append, nothing
else). The publisher thread calls `assemble`: chunks are put together by (camera, kind, image_id) as
the SPEC says, and each complete full frame becomes a PNG at most `max_width` pixels wide (16-bit
frames scaled to 8 bits), kept as the camera's latest thumbnail. Regions are left out. Incomplete
images are forgotten after `timeout_s`; at most `max_pending` are put together at once.

An edge sends a full frame when asked (CONTROL SEND_FULL_IMAGE); `Requester` asks each camera's edge
every few seconds on the rig's control port, when the live server is told to.
"""

from __future__ import annotations

import contextlib
import socket
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from flytrack_host.protocol import Command, Control, ImageChunk, encode

FULL_FRAME = 0


@dataclass
class Thumbnail:
    camera_index: int
    image_id: int
    camera_frame: int
    width: int  # of the original frame
    height: int
    png: bytes
    time: float


@dataclass
class _Pending:
    buf: bytearray
    got: set[int]
    filled: int
    started: float
    first: ImageChunk


class ThumbnailAssembler:
    def __init__(self, max_width: int = 160, max_chunks: int = 8192, max_pending: int = 16, timeout_s: float = 2.0):
        self.max_width = max_width
        self.timeout_s = timeout_s
        self.max_pending = max_pending
        self.chunks: deque[ImageChunk] = deque(maxlen=max_chunks)  # bounded: old chunks fall out
        self.latest: dict[int, Thumbnail] = {}
        self.pending: dict[tuple[int, int, int], _Pending] = {}
        self.images = 0
        self.dropped_incomplete = 0
        self.bad = 0

    def add(self, chunk: ImageChunk) -> None:
        """Tracking thread: keep the chunk for the publisher."""
        self.chunks.append(chunk)

    def assemble(self, now: float | None = None) -> int:
        """Publisher thread: put chunks together; returns the thumbnails made."""
        now = time.monotonic() if now is None else now
        made = 0
        while self.chunks:
            c = self.chunks.popleft()
            if c.kind != FULL_FRAME:
                continue
            key = (c.camera_index, c.kind, c.image_id)
            p = self.pending.get(key)
            if p is None:
                if len(self.pending) >= self.max_pending:
                    oldest = min(self.pending, key=lambda k: self.pending[k].started)
                    del self.pending[oldest]
                    self.dropped_incomplete += 1
                p = self.pending[key] = _Pending(bytearray(c.total_bytes), set(), 0, now, c)
            f = p.first
            if (c.total_bytes, c.width, c.height, c.bytes_per_pixel) != (f.total_bytes, f.width, f.height,
                                                                          f.bytes_per_pixel):
                self.bad += 1  # chunks of one image that disagree: the image is dropped
                del self.pending[key]
                continue
            if c.offset not in p.got:
                p.buf[c.offset:c.offset + len(c.data)] = c.data
                p.got.add(c.offset)
                p.filled += len(c.data)
            if p.filled >= f.total_bytes:
                del self.pending[key]
                try:
                    self.latest[c.camera_index] = self._thumbnail(f, bytes(p.buf), now)
                    self.images += 1
                    made += 1
                except (ValueError, ImportError):
                    self.bad += 1
        for k in [k for k, p in self.pending.items() if now - p.started > self.timeout_s]:
            del self.pending[k]
            self.dropped_incomplete += 1
        return made

    def _thumbnail(self, c: ImageChunk, data: bytes, now: float) -> Thumbnail:
        import cv2

        dtype = np.uint16 if c.bytes_per_pixel == 2 else np.uint8
        img = np.frombuffer(data, dtype=dtype).reshape(c.height, c.width)
        if dtype == np.uint16:
            img = (img >> 8).astype(np.uint8)
        if c.width > self.max_width:
            h = max(1, round(c.height * self.max_width / c.width))
            img = cv2.resize(img, (self.max_width, h), interpolation=cv2.INTER_AREA)
        ok, png = cv2.imencode(".png", img)
        if not ok:
            raise ValueError("PNG encoding failed")
        return Thumbnail(c.camera_index, c.image_id, c.camera_frame, c.width, c.height, png.tobytes(), now)


class Requester:
    """Asks each camera's edge for a full frame every `every_s` seconds (CONTROL SEND_FULL_IMAGE)."""

    def __init__(self, edges: dict[int, tuple[str, int]], every_s: float):
        self.edges = edges
        self.every_s = every_s
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.request_id = 1
        self.next_t = 0.0
        self.sent = 0
        self.errors = 0

    def tick(self, now: float) -> None:
        if self.every_s <= 0 or now < self.next_t:
            return
        self.next_t = now + self.every_s
        # Drain the acknowledgements: nothing to do with them but not let them pile up.
        with contextlib.suppress(OSError):
            while self.sock.recv(2048):
                pass
        for cam, addr in self.edges.items():
            msg = encode(Control(request_id=self.request_id & 0xFFFFFFFF, camera_index=cam,
                                 command=Command.SEND_FULL_IMAGE))
            self.request_id += 1
            try:
                self.sock.sendto(msg, addr)
                self.sent += 1
            except OSError:
                self.errors += 1

    def close(self) -> None:
        self.sock.close()
