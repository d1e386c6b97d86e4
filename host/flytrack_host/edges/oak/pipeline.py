"""The depthai pipeline an OAK edge runs on the device: one camera node -> XLinkOut.

depthai 2.x is pinned: its `Pipeline` is a plain description that can be built (and checked in tests)
without a device, whereas the 3.x API refuses to create device nodes in a pipeline with no device
("Pipeline is host only, cannot create device node", measured with depthai 3.12.0).
"""

from __future__ import annotations

from dataclasses import dataclass

import depthai as dai

STREAM = "flytrack_frames"

MONO_RESOLUTIONS = {
    "400p": (dai.MonoCameraProperties.SensorResolution.THE_400_P, 640, 400),
    "480p": (dai.MonoCameraProperties.SensorResolution.THE_480_P, 640, 480),
    "720p": (dai.MonoCameraProperties.SensorResolution.THE_720_P, 1280, 720),
    "800p": (dai.MonoCameraProperties.SensorResolution.THE_800_P, 1280, 800),
}
COLOR_RESOLUTIONS = {
    "1080p": (dai.ColorCameraProperties.SensorResolution.THE_1080_P, 1920, 1080),
    "720p": (dai.ColorCameraProperties.SensorResolution.THE_720_P, 1280, 720),
    "800p": (dai.ColorCameraProperties.SensorResolution.THE_800_P, 1280, 800),
}
SOCKETS = ("CAM_A", "CAM_B", "CAM_C", "CAM_D")


class OakConfigError(ValueError):
    """A camera setting the OAK pipeline cannot have."""


@dataclass(frozen=True)
class CameraSpec:
    """What to ask the device for. `kind` mono: GRAY8 frames; color: NV12 `video`, its luma is used."""

    kind: str = "mono"
    socket: str = "CAM_B"
    resolution: str = "400p"
    fps: float = 60.0

    def size(self) -> tuple[int, int]:
        table = MONO_RESOLUTIONS if self.kind == "mono" else COLOR_RESOLUTIONS
        return table[self.resolution][1], table[self.resolution][2]

    def check(self) -> None:
        if self.kind not in ("mono", "color"):
            raise OakConfigError(f"camera kind {self.kind!r}: one of mono, color")
        table = MONO_RESOLUTIONS if self.kind == "mono" else COLOR_RESOLUTIONS
        if self.resolution not in table:
            raise OakConfigError(f"{self.kind} resolution {self.resolution!r}: one of {sorted(table)}")
        if self.socket not in SOCKETS:
            raise OakConfigError(f"socket {self.socket!r}: one of {', '.join(SOCKETS)}")
        if not (0.0 < self.fps <= 240.0):  # also rejects NaN
            raise OakConfigError(f"fps {self.fps!r} must be in (0, 240]")


def build_pipeline(spec: CameraSpec) -> dai.Pipeline:
    """The device pipeline: the camera's frames to the host on the XLink stream `STREAM`."""
    spec.check()
    p = dai.Pipeline()
    socket = getattr(dai.CameraBoardSocket, spec.socket)
    xout = p.create(dai.node.XLinkOut)
    xout.setStreamName(STREAM)
    # Blocking off, small queue: a slow host drops frames on the device (the sequence numbers show the
    # gap) instead of stalling the sensor.
    xout.input.setBlocking(False)
    xout.input.setQueueSize(4)
    if spec.kind == "mono":
        cam = p.create(dai.node.MonoCamera)
        cam.setBoardSocket(socket)
        cam.setResolution(MONO_RESOLUTIONS[spec.resolution][0])
        cam.setFps(spec.fps)
        cam.out.link(xout.input)
    else:
        cam = p.create(dai.node.ColorCamera)
        cam.setBoardSocket(socket)
        cam.setResolution(COLOR_RESOLUTIONS[spec.resolution][0])
        cam.setFps(spec.fps)
        cam.video.link(xout.input)  # NV12: the Y plane comes first, the extractor reads it as mono8
    return p
