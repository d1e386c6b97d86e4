"""A simulated DVS (event camera) in the rig: events from the flight model, as an EVT 2.0 stream.

Each pixel fires when its log intensity has moved by the contrast threshold since its last event
(ON brighter, OFF darker), at most once per refractory period; background-activity noise events come
at a set rate per pixel; times are microseconds on the sensor's own clock; and a sync (external
trigger) event is written at every trigger pulse, as the DVS bridge records the trigger firmware's
frame output (firmware/dvs_usb). The scene is the frame renderer's: a uniform background with each
animal a dark Gaussian blob, blurred at least by the optics' PSF.

The stream is Prophesee EVT 2.0 (32-bit words: CD events, TIME_HIGH, EXT_TRIGGER), which
`flytrack-edge --source events --input -` reads from its stdin and counts sync events from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from flytrack_host.geometry.camera import Camera

# EVT 2.0 word types (bits 31..28)
EVT2_CD_OFF = 0x0
EVT2_CD_ON = 0x1
EVT2_TIME_HIGH = 0x8
EVT2_EXT_TRIGGER = 0xA

DVS_SIZES = {"dvs128": (128, 128), "davis346": (346, 260)}


@dataclass(frozen=True)
class DvsParams:
    contrast_threshold: float = 0.15  # log-intensity step per event (DVS128 default biases: ~0.15-0.3)
    refractory_us: int = 500  # a pixel's dead time after an event
    noise_hz_per_px: float = 0.05  # background activity, events per pixel per second
    substeps: int = 5  # intensity samples per trigger period (events get times inside them)
    contrast: float = 0.55  # the animal blocks this fraction of the light at its centre
    psf_sigma_px: float = 1.5  # a low-resolution sensor's lens blur (the frame renderer's floor is 0.9)
    background: float = 170.0  # relative illumination (only its log changes matter)

    def __post_init__(self) -> None:
        if not (0.01 <= self.contrast_threshold <= 2.0):
            raise ValueError(f"contrast threshold must be 0.01..2, got {self.contrast_threshold}")
        if self.refractory_us < 0 or self.substeps < 1 or not (0 <= self.noise_hz_per_px <= 1e4):
            raise ValueError("refractory_us >= 0, substeps >= 1 and noise 0..1e4 Hz per pixel are needed")
        if not (0.0 < self.contrast < 1.0):
            raise ValueError(f"contrast must be in (0, 1), got {self.contrast}")


class DvsRenderer:
    """Events of one DVS camera, one trigger period at a time (call `period` for frames 0, 1, ...)."""

    def __init__(self, camera: Camera, params: DvsParams | None = None, seed: int = 0,
                 t0_us: int = 1_000_000) -> None:
        self.camera = camera
        self.p = params or DvsParams()
        self.rng = np.random.default_rng(seed)
        h, w = camera.height, camera.width
        self.log_bg = math.log(self.p.background)
        self.ref = np.full((h, w), self.log_bg, np.float32)  # log intensity at each pixel's last event
        self.last_us = np.full((h, w), -(1 << 40), np.int64)
        self.t0_us = int(t0_us)  # the sensor clock at flight time 0 (its own epoch, not the host's)
        self.events_made = 0
        self.syncs_made = 0
        self._prev: tuple[float, NDArray[np.float64], NDArray[np.float64]] | None = None

    def to_us(self, t):  # float or array of seconds -> sensor microseconds
        if np.ndim(t):
            return self.t0_us + np.rint(np.asarray(t) * 1e6).astype(np.int64)
        return self.t0_us + int(round(float(t) * 1e6))

    def _blobs(self, pos: NDArray[np.float64], length: float, width: float) -> tuple[np.ndarray, np.ndarray]:
        """(u, v, sigma) of each visible animal, (k, 3)."""
        cam = self.camera
        if pos.shape[0] == 0:
            return np.zeros((0, 3)), np.zeros(0, bool)
        # (a simplification as in render.py: no occlusion between animals)
        uv = cam.project(pos)
        depth = cam.to_camera(pos)[:, 2]
        f = float(cam.K[0, 0])
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.sqrt((f * 0.5 * (length + width) / np.maximum(depth, 1e-6) / 3.0) ** 2 + self.p.psf_sigma_px**2)
            ok = (depth > 0) & np.all(np.isfinite(uv), axis=1) & (uv[:, 0] > -10) & (uv[:, 0] < cam.width + 10) \
                & (uv[:, 1] > -10) & (uv[:, 1] < cam.height + 10)
        return np.column_stack([uv, s]), ok

    def _log_image(self, blobs: np.ndarray, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float32)
        out = np.full(yy.shape, self.log_bg, np.float32)
        for u, v, s in blobs:
            g = np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * s * s))
            out += np.log1p(-self.p.contrast * g).astype(np.float32)
        return out

    def fire(self, L: np.ndarray, y0: int, x0: int, t_base: float, dt: float,
             k: int = 1, latency: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """The sensor model on one window: L is the log intensity now over pixels [y0:, x0:]; each pixel
        that has moved by the contrast threshold since its last event fires, its first event inside
        substep k of length dt after t_base (seconds; sooner for a larger step; within `latency` of the
        substep's start when given, as for a sudden step of light), more one refractory period apart
        while the substep lasts. Updates the pixels' reference and last event time.
        (t us, x, y, p) arrays, or None when nothing fired."""
        p = self.p
        y1, x1 = y0 + L.shape[0], x0 + L.shape[1]
        ref = self.ref[y0:y1, x0:x1]
        d = L - ref
        fire = np.abs(d) >= p.contrast_threshold
        if not np.any(fire):
            return None
        yy, xx = np.nonzero(fire)
        # A step of several thresholds fires several events, one per refractory period at most.
        n_th = np.floor(np.abs(d[yy, xx]) / p.contrast_threshold).astype(np.int64)
        if latency is None:
            t_first = self.to_us(t_base + (k - 1 + self.rng.random(yy.size) / n_th) * dt)
        else:
            t_first = self.to_us(t_base + (k - 1) * dt + self.rng.random(yy.size) / n_th * latency)
        t_first = np.maximum(t_first, self.last_us[yy + y0, xx + x0] + p.refractory_us)
        step_us = max(p.refractory_us, 1)
        t_stop = self.to_us(t_base + k * dt)
        room = np.where(t_first <= t_stop, 1 + (t_stop - t_first) // step_us, 0)
        m = np.minimum(n_th, room)
        if not np.any(m):
            return None
        rep_i = np.repeat(np.arange(yy.size), m)
        j = np.arange(rep_i.size) - np.repeat(np.cumsum(m) - m, m)
        t_ev = t_first[rep_i] + j * step_us
        gy, gx = yy[rep_i] + y0, xx[rep_i] + x0
        sign = np.sign(d[yy, xx])
        pol = (sign[rep_i] > 0).astype(np.int64)
        ref[yy, xx] += (sign * m * p.contrast_threshold).astype(np.float32)
        last = np.full(yy.size, -(1 << 40), np.int64)
        has = m > 0
        last[has] = t_first[has] + (m[has] - 1) * step_us
        self.last_us[yy[has] + y0, xx[has] + x0] = last[has]
        return t_ev, gx, gy, pol

    def noise(self, t_start: float, t_end: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """Background activity from t_start to t_end (seconds): Poisson in time, uniform over the
        pixels, either polarity; (t us, x, y, p) arrays (not time-ordered), or None."""
        p = self.p
        h, w = self.camera.height, self.camera.width
        n_noise = int(self.rng.poisson(p.noise_hz_per_px * h * w * (t_end - t_start)))
        if not n_noise:
            return None
        return (self.to_us(t_start) + self.rng.integers(1, max(2, self.to_us(t_end) - self.to_us(t_start)), n_noise),
                self.rng.integers(0, w, n_noise), self.rng.integers(0, h, n_noise), self.rng.integers(0, 2, n_noise))

    def period(self, t_end: float, pos: NDArray[np.float64], length: float, width: float) -> np.ndarray:
        """Events from the previous call's time to t_end (animals at `pos` (n,3) then), as a structured
        array (t us, x, y, p), time-ordered. The first call only sets the start."""
        ev_t: list[np.ndarray] = []
        ev_x: list[np.ndarray] = []
        ev_y: list[np.ndarray] = []
        ev_p: list[np.ndarray] = []
        prev = self._prev
        self._prev = (t_end, pos.copy(), np.zeros(0))
        if prev is None:
            return _pack(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
        t_start, pos0 = prev[0], prev[1]
        p = self.p
        cam = self.camera
        h, w = cam.height, cam.width
        steps = p.substeps
        dt = (t_end - t_start) / steps
        n = pos.shape[0]
        if pos0.shape != pos.shape:
            pos0 = pos
        # Every animal at every substep boundary, projected at once: (steps + 1, n, 3).
        a = np.linspace(0.0, 1.0, steps + 1)[:, None, None]
        P = ((1 - a) * pos0[None] + a * pos[None]).reshape(-1, 3)
        blobs_all, ok_all = self._blobs(P, length, width)
        blobs_all = blobs_all.reshape(steps + 1, max(n, 0), 3)
        ok_all = ok_all.reshape(steps + 1, max(n, 0))
        for k in range(1, steps + 1):
            blobs = blobs_all[k][ok_all[k]]
            both = ok_all[k] | ok_all[k - 1]
            if not np.any(both):
                continue
            # A window per animal over where it is and where it was a substep ago (pixels it left
            # change too); overlapping windows are fine, a pixel fires once per refractory period.
            for i in np.nonzero(both)[0]:
                pts = np.stack([blobs_all[k][i], blobs_all[k - 1][i]])
                pts = pts[np.all(np.isfinite(pts), axis=1)]
                rr = math.ceil(4 * float(pts[:, 2].max()))
                x0, x1 = max(0, int(pts[:, 0].min()) - rr), min(w, int(pts[:, 0].max()) + rr + 2)
                y0, y1 = max(0, int(pts[:, 1].min()) - rr), min(h, int(pts[:, 1].max()) + rr + 2)
                if x0 >= x1 or y0 >= y1:
                    continue
                L = self._log_image(blobs, y0, y1, x0, x1)
                got = self.fire(L, y0, x0, t_start, dt, k)
                if got is None:
                    continue
                ev_t.append(got[0])
                ev_x.append(got[1])
                ev_y.append(got[2])
                ev_p.append(got[3])
        noise = self.noise(t_start, t_end)
        if noise is not None:
            ev_t.append(noise[0])
            ev_x.append(noise[1])
            ev_y.append(noise[2])
            ev_p.append(noise[3])
        if not ev_t:
            return _pack(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
        out = _pack(np.concatenate(ev_t), np.concatenate(ev_x), np.concatenate(ev_y), np.concatenate(ev_p))
        out = out[np.argsort(out["t"], kind="stable")]
        self.events_made += len(out)
        return out


EV_DTYPE = np.dtype([("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])


def _pack(t: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray) -> np.ndarray:
    out = np.empty(len(t), EV_DTYPE)
    out["t"], out["x"], out["y"], out["p"] = t, x, y, p
    return out


def evt2_header(width: int, height: int) -> bytes:
    return (f"% evt 2.0\n% format EVT2;width={width};height={height}\n% geometry {width}x{height}\n"
            "% generated by flytrack_host.sim.dvs\n% end\n").encode()


class Evt2Encoder:
    """Events and sync events to EVT 2.0 words; keeps the last TIME_HIGH across calls (a stream)."""

    def __init__(self) -> None:
        self.t_high = -1

    def encode(self, events: np.ndarray, sync_us: int | None = None) -> bytes:
        """Time-ordered events, then (if given) one rising-edge EXT_TRIGGER at sync_us (>= their times)."""
        t = events["t"].astype(np.int64)
        typ = np.where(events["p"] != 0, EVT2_CD_ON, EVT2_CD_OFF).astype(np.uint32)
        words = (typ << 28) | ((t & 0x3F).astype(np.uint32) << 22) | (events["x"].astype(np.uint32) << 11) \
            | events["y"].astype(np.uint32)
        if sync_us is not None:
            t = np.append(t, sync_us)
            # EXT_TRIGGER: bits 27..22 time low, 12..8 channel id (0), bit 0 edge value (1 rising)
            words = np.append(words, np.uint32((EVT2_EXT_TRIGGER << 28) | ((sync_us & 0x3F) << 22) | 1))
        if t.size and np.any(np.diff(t) < 0):
            raise ValueError("events must come in non-decreasing time")
        hi = t >> 6
        prev = np.concatenate([[self.t_high], hi[:-1]]) if hi.size else hi
        new = hi != prev
        if hi.size:
            self.t_high = int(hi[-1])
        n_new = int(new.sum())
        out = np.empty(words.size + n_new, np.uint32)
        # Each event whose high time differs from the word before gets a TIME_HIGH word ahead of it.
        pos = np.arange(words.size) + np.cumsum(new)
        out[pos] = words
        th_pos = pos[new] - 1
        out[th_pos] = (np.uint32(EVT2_TIME_HIGH) << 28) | (hi[new] & 0x0FFFFFFF).astype(np.uint32)
        return out.astype("<u4").tobytes()


def make_dvs_cameras(n: int, arena, seed: int, sensor: str = "dvs128") -> list[Camera]:
    """N calibrated DVS cameras around the arena (placed as the frame cameras are, other seeds)."""
    from flytrack_host.sim.rig import make_cameras

    if sensor not in DVS_SIZES:
        raise ValueError(f"unknown DVS sensor {sensor!r}; one of {', '.join(DVS_SIZES)}")
    w, h = DVS_SIZES[sensor]
    cams = make_cameras(n, arena, seed=seed + 50_000, width=w, height=h, distortion=False)
    # Focal lengths drawn for 640 px images: scale to the sensor so the arena fills it.
    return [Camera(f"dvs{i + 1}", c.width, c.height, c.K, c.R, c.t, c.dist) for i, c in enumerate(cams)]


def render_stream(renderer: DvsRenderer, gt, warmup_frames: int = 0) -> list[tuple[bytes, int]]:
    """Per trigger frame n: the EVT 2.0 words of the events up to pulse n and its sync event, and how
    many events they hold. The flight is known in advance, so the whole run is rendered before the
    trigger starts and a pulse costs only a write (as the frame cameras' frames are rendered ahead)."""
    enc = Evt2Encoder()
    none = np.zeros((0, 3))
    out: list[tuple[bytes, int]] = []
    for n in range(gt.n_frames):
        pos = gt.pos[n] if n >= warmup_frames else none
        ev = renderer.period(float(gt.t[n]), pos, gt.body_length_m, gt.body_width_m)
        out.append((enc.encode(ev, sync_us=renderer.to_us(float(gt.t[n]))), len(ev)))
    return out
