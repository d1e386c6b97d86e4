"""`FeatureExtractor`: the edge's C feature extractor (libflytrack_features), called from Python.

Frames in, feature points out, through the very code `flytrack-edge` runs, so an offline re-extraction
gives the same points as the live system did.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass, field, fields

import numpy as np
from numpy.typing import NDArray

from flytrack_host.edges.features import _lib
from flytrack_host.geometry.camera import Camera

PIXEL_FORMATS = {"mono8": 0, "mono16": 1, "yuyv": 2}
POLARITIES = {"both": 0, "bright": 1, "dark": 2}

# Result flags (features.h FT_FX_RES_*).
BACKGROUND_TAKEN = 0x1
BG_UPDATED = 0x2
CAND_OVERFLOW = 0x4
TRUNCATED = 0x8

# One extracted point, laid out exactly as the C struct ft_fx_point.
POINT_DTYPE = np.dtype(
    [
        ("x_dist", "<f8"),
        ("y_dist", "<f8"),
        ("x_undist", "<f8"),
        ("y_undist", "<f8"),
        ("area", "<f8"),
        ("peak_diff", "<f8"),
        ("orientation", "<f8"),
        ("eccentricity", "<f8"),
        ("mean_val", "<f8"),
        ("sumsq_val", "<f8"),
        ("cur_val", "<u4"),
        ("peak_x", "<u4"),
        ("peak_y", "<u4"),
        ("n_candidates", "<u4"),
    ]
)
assert POINT_DTYPE.itemsize == ctypes.sizeof(_lib.Point)


class FeatureError(ValueError):
    """Bad parameters or a bad frame, with the C library's message."""


@dataclass
class ExtractorParams:
    """Detector parameters (Braid's defaults). See features.h for each one's meaning."""

    alpha: float = 0.01
    n_sigma: float = 7.0
    diff_threshold: float = 30.0
    bg_update_interval: int = 200
    polarity: str = "both"
    clear_fraction: float = 0.3
    despeckle_threshold: float = 5.0
    min_area: int = 1
    subtract_cut: bool = True
    max_points: int = 100
    max_candidates: int = 65536
    extra: dict[str, float] = field(default_factory=dict)


@dataclass
class FrameFeatures:
    """What one frame gave."""

    frame_index: int
    points: NDArray[np.void]  # POINT_DTYPE, strongest first
    total_points: int
    n_candidates: int
    flags: int

    @property
    def background_taken(self) -> bool:
        return bool(self.flags & BACKGROUND_TAKEN)

    @property
    def truncated(self) -> bool:
        return bool(self.flags & TRUNCATED)


def _check(rc: int, what: str) -> None:
    if rc != 0:
        msg = _lib.load().ft_fx_strerror(rc).decode()
        raise FeatureError(f"{what}: {msg}")


class FeatureExtractor:
    """One camera's extractor. Not thread-safe; use one per camera (or per thread)."""

    def __init__(
        self,
        width: int,
        height: int,
        pixel_format: str = "mono8",
        params: ExtractorParams | None = None,
        camera: Camera | None = None,
        mask: NDArray[np.uint8] | None = None,
    ) -> None:
        self._lib = _lib.load()
        self._h: ctypes.c_void_p | None = None
        if pixel_format not in PIXEL_FORMATS:
            raise FeatureError(f"unknown pixel format {pixel_format!r}: one of {sorted(PIXEL_FORMATS)}")
        params = params or ExtractorParams()
        if params.polarity not in POLARITIES:
            raise FeatureError(f"unknown polarity {params.polarity!r}: one of {sorted(POLARITIES)}")
        if width <= 0 or height <= 0:
            raise FeatureError(f"bad frame size {width}x{height}")
        p = _lib.Params()
        self._lib.ft_fx_params_default(ctypes.byref(p), width, height, PIXEL_FORMATS[pixel_format])
        for f in fields(ExtractorParams):
            if f.name in ("polarity", "extra"):
                continue
            setattr(p, f.name, int(getattr(params, f.name)) if f.name in
                    ("bg_update_interval", "min_area", "subtract_cut", "max_points", "max_candidates")
                    else float(getattr(params, f.name)))
        p.polarity = POLARITIES[params.polarity]
        if camera is not None:
            if (camera.width, camera.height) != (width, height):
                raise FeatureError(
                    f"camera {camera.name} is {camera.width}x{camera.height}, frames are {width}x{height}"
                )
            K = camera.Kd  # the distortion's K: the undistorted pixels come out in P's frame
            p.fx, p.skew, p.cx = float(K[0, 0]), float(K[0, 1]), float(K[0, 2])
            p.fy, p.cy = float(K[1, 1]), float(K[1, 2])
            p.k1, p.k2, p.p1, p.p2, p.k3 = (float(v) for v in camera.dist)
        msg = ctypes.create_string_buffer(128)
        rc = self._lib.ft_fx_params_check(ctypes.byref(p), msg, len(msg))
        if rc != 0:
            raise FeatureError(f"bad extractor parameters: {msg.value.decode()}")
        h = ctypes.c_void_p()
        _check(self._lib.ft_fx_create(ctypes.byref(p), ctypes.sizeof(p), ctypes.byref(h)), "create")
        self._h = h
        self._p = p
        self.width, self.height, self.pixel_format = width, height, pixel_format
        self._frame_bytes = int(self._lib.ft_fx_frame_bytes(ctypes.byref(p)))
        self._res = _lib.Result()
        for name, value in params.extra.items():
            self.set_param(name, value)
        if mask is not None:
            self.set_mask(mask)

    def __del__(self) -> None:
        self.close()

    def close(self) -> None:
        if getattr(self, "_h", None):
            self._lib.ft_fx_destroy(self._h)
            self._h = None

    def __enter__(self) -> FeatureExtractor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def frame_bytes(self) -> int:
        return self._frame_bytes

    def _frame_ptr(self, frame: NDArray | bytes | bytearray | memoryview) -> tuple[object, int]:
        if isinstance(frame, np.ndarray):
            want = np.uint16 if self.pixel_format == "mono16" else np.uint8
            if frame.dtype != want:
                raise FeatureError(f"{self.pixel_format} frames must be {np.dtype(want)}, got {frame.dtype}")
            if not frame.flags.c_contiguous:
                frame = np.ascontiguousarray(frame)
            if frame.nbytes != self._frame_bytes:
                raise FeatureError(
                    f"frame has {frame.nbytes} bytes, {self.width}x{self.height} {self.pixel_format} "
                    f"needs {self._frame_bytes}"
                )
            return frame, frame.ctypes.data
        buf = bytes(frame)
        if len(buf) != self._frame_bytes:
            raise FeatureError(f"frame has {len(buf)} bytes, expected {self._frame_bytes}")
        return buf, ctypes.cast(ctypes.c_char_p(buf), ctypes.c_void_p).value or 0

    def process_raw(self, frame: NDArray | bytes) -> int:
        """Processes a frame and returns the number of points, without copying them out (for benchmarks)."""
        keep, ptr = self._frame_ptr(frame)
        _check(self._lib.ft_fx_process(self._h, ptr, self._frame_bytes, ctypes.byref(self._res)), "process")
        del keep
        return int(self._res.n_points)

    def process(self, frame: NDArray | bytes) -> FrameFeatures:
        """Feeds one frame; returns its points (a copy), strongest first."""
        self.process_raw(frame)
        r = self._res
        n = int(r.n_points)
        if n:
            raw = ctypes.string_at(ctypes.cast(r.points, ctypes.c_void_p), n * POINT_DTYPE.itemsize)
            pts = np.frombuffer(raw, dtype=POINT_DTYPE).copy()
        else:
            pts = np.zeros(0, dtype=POINT_DTYPE)
        return FrameFeatures(int(r.frame_index), pts, int(r.total_points), int(r.n_candidates), int(r.flags))

    def take_background(self) -> None:
        """The next frame becomes the background."""
        self._lib.ft_fx_take_background(self._h)

    def set_mask(self, mask: NDArray | None) -> None:
        """Nonzero = pixel used. None removes the mask."""
        if mask is None:
            _check(self._lib.ft_fx_set_mask(self._h, None), "set_mask")
            return
        m = np.ascontiguousarray(mask, dtype=np.uint8)
        if m.shape != (self.height, self.width):
            raise FeatureError(f"mask shape {m.shape} differs from the frame's {(self.height, self.width)}")
        _check(self._lib.ft_fx_set_mask(self._h, m.ctypes.data), "set_mask")

    def set_param(self, name: str, value: float) -> None:
        if name == "polarity" and isinstance(value, str):
            value = POLARITIES.get(value, -1)
        _check(self._lib.ft_fx_set_param(self._h, name.encode(), float(value)), f"set_param {name}")

    def get_param(self, name: str) -> float:
        out = ctypes.c_double()
        _check(self._lib.ft_fx_get_param(self._h, name.encode(), ctypes.byref(out)), f"get_param {name}")
        return out.value

    def background(self) -> tuple[NDArray[np.float32], NDArray[np.float32]] | None:
        """(mean, mean of squares) as (height, width) float32 copies, None before the first frame."""
        m = self._lib.ft_fx_background_mean(self._h)
        s = self._lib.ft_fx_background_sumsq(self._h)
        if not m:
            return None
        n = self.width * self.height
        shape = (self.height, self.width)
        return (
            np.ctypeslib.as_array(m, shape=(n,)).reshape(shape).copy(),
            np.ctypeslib.as_array(s, shape=(n,)).reshape(shape).copy(),
        )

    def undistort(self, u: float, v: float) -> tuple[float, float]:
        """The library's lens-distortion correction of one distorted pixel."""
        uo, vo = ctypes.c_double(), ctypes.c_double()
        self._lib.ft_fx_undistort(ctypes.byref(self._p), u, v, ctypes.byref(uo), ctypes.byref(vo))
        return uo.value, vo.value
