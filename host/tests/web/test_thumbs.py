"""Putting IMAGE chunks together: order, duplicates, 16-bit, regions, bad and incomplete images."""

from __future__ import annotations

import cv2
import numpy as np

from flytrack_host.live.web.thumbs import ThumbnailAssembler
from flytrack_host.protocol import ImageChunk


def chunks(img: np.ndarray, image_id: int = 1, cam: int = 0, size: int = 1000, kind: int = 0) -> list[ImageChunk]:
    data = img.tobytes()
    h, w = img.shape
    return [ImageChunk(camera_index=cam, kind=kind, bytes_per_pixel=img.itemsize, image_id=image_id, camera_frame=9,
                       x0=0, y0=0, width=w, height=h, offset=o, total_bytes=len(data), data=data[o:o + size])
            for o in range(0, len(data), size)]


def test_chunks_in_any_order_with_duplicates_make_the_frame():
    img = np.random.default_rng(0).integers(0, 255, (60, 80), dtype=np.uint8)
    a = ThumbnailAssembler(max_width=160)
    cs = chunks(img)
    for c in cs[::-1] + cs[:2]:  # reversed, two repeated
        a.add(c)
    assert a.assemble() == 1
    t = a.latest[0]
    assert (t.width, t.height, t.camera_frame, t.image_id) == (80, 60, 9, 1)
    assert np.array_equal(cv2.imdecode(np.frombuffer(t.png, np.uint8), cv2.IMREAD_UNCHANGED), img)


def test_16_bit_frames_scaled_down_and_regions_left_out():
    img = (np.arange(100 * 400, dtype=np.uint16).reshape(100, 400) * 3)
    a = ThumbnailAssembler(max_width=100)
    for c in chunks(img, image_id=2) + chunks(img[:10, :10].copy(), image_id=3, kind=1):
        a.add(c)
    assert a.assemble() == 1 and list(a.latest) == [0]
    out = cv2.imdecode(np.frombuffer(a.latest[0].png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert out.shape == (25, 100) and out.dtype == np.uint8
    assert np.array_equal(out, cv2.resize((img >> 8).astype(np.uint8), (100, 25), interpolation=cv2.INTER_AREA))


def test_incomplete_and_inconsistent_images_are_dropped_and_counted():
    img = np.zeros((50, 50), np.uint8)
    a = ThumbnailAssembler(max_pending=2, timeout_s=1.0)
    cs = chunks(img, image_id=1)
    a.add(cs[0])  # never completed
    a.assemble(now=0.0)
    assert a.assemble(now=5.0) == 0 and a.dropped_incomplete == 1 and not a.pending
    bad = chunks(np.zeros((25, 100), np.uint8), image_id=4)  # same id, other shape
    a.add(chunks(img, image_id=4)[0])
    a.add(bad[1])
    a.assemble(now=6.0)
    assert a.bad == 1 and not a.latest
    for i in range(5, 9):  # more images under way than max_pending: the oldest go
        a.add(chunks(img, image_id=i)[0])
        a.assemble(now=7.0 + 0.01 * i)
    assert len(a.pending) == 2 and a.dropped_incomplete == 3
    a.chunks.extend([cs[0]] * 10_000)  # the tracking thread's side is bounded
    assert len(a.chunks) == a.chunks.maxlen
