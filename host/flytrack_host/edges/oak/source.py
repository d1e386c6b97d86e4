"""Where an OAK edge gets its frames: the `FrameSource` seam, and the real depthai device behind it.

There is no OAK device on the development machine: tests drive `OakEdge` through a `FrameSource` that
hands over real `depthai.ImgFrame` objects built on the host, and `DepthaiSource` (the device link) is
the only part they cannot run.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Protocol

import depthai as dai
import numpy as np
from numpy.typing import NDArray

from flytrack_host.edges.oak.pipeline import STREAM, CameraSpec, build_pipeline


class DeviceLost(RuntimeError):
    """The device went away (unplugged, rebooted, XLink error): the edge reports it and reconnects."""


class BadFrame(ValueError):
    """A frame the extractor cannot take (wrong type or size): counted as dropped, never processed."""


@dataclass(frozen=True)
class OakFrame:
    """One frame as the edge uses it: the device's sequence number and clock, and the luma plane."""

    sequence_num: int
    device_timestamp_ns: int
    image: NDArray[np.uint8]  # (height, width) mono8


_MONO_TYPES = {dai.ImgFrame.Type.GRAY8, dai.ImgFrame.Type.RAW8, dai.ImgFrame.Type.YUV400p}
_LUMA_FIRST = {dai.ImgFrame.Type.NV12, dai.ImgFrame.Type.NV21, dai.ImgFrame.Type.YUV420p}


def frame_from_imgframe(img: dai.ImgFrame) -> OakFrame:
    """The luma plane, sequence number and device timestamp of a depthai frame."""
    w, h, kind = int(img.getWidth()), int(img.getHeight()), img.getType()
    if kind not in _MONO_TYPES and kind not in _LUMA_FIRST:
        raise BadFrame(f"frame {img.getSequenceNum()}: type {kind.name} has no 8-bit luma plane")
    data = np.asarray(img.getData(), dtype=np.uint8)
    if w <= 0 or h <= 0 or data.size < w * h:
        raise BadFrame(f"frame {img.getSequenceNum()}: {data.size} bytes for a {w}x{h} {kind.name} image")
    # The device clock (monotonic since device boot), not the host-synced getTimestamp().
    td = img.getTimestampDevice()
    ts_ns = (td.days * 86400 + td.seconds) * 1_000_000_000 + td.microseconds * 1000
    return OakFrame(int(img.getSequenceNum()), ts_ns, data[: w * h].reshape(h, w))


class FrameSource(Protocol):
    """The device link. `get` returns the next frame, None after `timeout` s without one, and raises
    `DeviceLost` when the device is gone; `open` (re)connects and may raise `DeviceLost` too."""

    def open(self) -> None: ...

    def get(self, timeout: float) -> dai.ImgFrame | None: ...

    def close(self) -> None: ...


class DepthaiSource:
    """A real OAK device over XLink (USB or PoE). Not exercised in tests: no device here."""

    def __init__(self, spec: CameraSpec, device_id: str = "") -> None:
        self.spec = spec
        self.device_id = device_id
        self._device: dai.Device | None = None
        self._queue: dai.DataOutputQueue | None = None

    def open(self) -> None:
        self.close()
        try:
            if self.device_id:
                info = dai.DeviceInfo(self.device_id)
                self._device = dai.Device(build_pipeline(self.spec), info)
            else:
                self._device = dai.Device(build_pipeline(self.spec))
            self._queue = self._device.getOutputQueue(STREAM, maxSize=4, blocking=False)
        except RuntimeError as exc:
            self.close()
            raise DeviceLost(f"cannot open OAK device {self.device_id or '(first found)'}: {exc}") from exc

    def get(self, timeout: float) -> dai.ImgFrame | None:
        if self._queue is None or self._device is None:
            raise DeviceLost("OAK device not open")
        # depthai 2.x's Python queue has no timed get: poll tryGet (1 ms steps) so the edge stays
        # responsive to status ticks and shutdown.
        end = time.monotonic() + timeout
        try:
            while True:
                msg = self._queue.tryGet()
                if msg is not None:
                    return msg
                if self._device.isClosed():
                    raise DeviceLost("OAK device closed")
                if time.monotonic() >= end:
                    return None
                time.sleep(0.001)
        except RuntimeError as exc:  # XLink errors come as RuntimeError ("Communication exception ...")
            raise DeviceLost(str(exc)) from exc

    def close(self) -> None:
        if self._device is not None:
            try:
                self._device.close()
            except RuntimeError:
                pass
        self._device = None
        self._queue = None


def available_devices() -> list[str]:
    """The ids (MxId) of the OAK devices depthai can see now."""
    return [d.getMxId() for d in dai.Device.getAllAvailableDevices()]
