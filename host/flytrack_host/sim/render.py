"""Fast 8-bit frames of a simulated near-IR camera looking at the arena.

Each frame is: a fixed background (smooth illumination structure x cos^4 vignetting, precomputed once
per illumination level), scaled by a slow illumination drift, plus sensor noise, plus every animal the
camera sees as a small Gaussian blob elongated along the projection of its body axis, plus now and
then a false blob (dust, a reflection).

What makes it fast enough for several cameras at 100 fps on one core:
- the backgrounds for the few illumination levels the drift visits are computed once and cached;
- noise is not generated per frame: a bank of pre-generated noise, a few frames long, is sampled at a
  random offset, and added with one saturating uint8 add (OpenCV), which also does the clipping;
- blobs are drawn only inside small windows around each animal.

A simplification, on purpose: a blob's peak contrast does not shrink when the animal is smaller than a
pixel (the optics' blur sets a floor on its size). A real 2.5 mm fly 2 m from a 640 px camera would be
nearly invisible; labs put cameras closer or use more pixels, which we stand in for this way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from flytrack_host.geometry.camera import Camera

U8 = NDArray[np.uint8]


@dataclass(frozen=True)
class RenderParams:
    background_level: float = 170.0  # grey level at the image centre
    texture: float = 0.05  # relative amplitude of the smooth background structure
    vignetting: bool = True  # cos^4 fall-off with the camera's own focal length
    drift_amplitude: float = 0.03  # relative, slow illumination drift
    drift_period_s: float = 20.0
    noise_sigma: float = 2.0  # sensor noise, grey levels
    psf_sigma_px: float = 0.9  # optical blur: the smallest blob
    contrast: float = 0.55  # dark animal: the fraction of light it blocks at its centre
    bright_fraction: float = 0.0  # fraction of animals drawn bright instead of dark
    false_blob_rate: float = 0.01  # false blobs per frame per camera
    false_blob_frames: tuple[int, int] = (1, 4)  # how long one lasts
    noise_bank_frames: int = 3

    def __post_init__(self) -> None:
        if not (0.0 <= self.noise_sigma <= 40.0):
            raise ValueError(f"noise sigma must be 0..40 grey levels, got {self.noise_sigma}")
        if not (0.0 < self.contrast <= 1.0):
            raise ValueError(f"contrast must be in (0, 1], got {self.contrast}")
        if not (0.0 <= self.bright_fraction <= 1.0):
            raise ValueError(f"bright fraction must be in [0, 1], got {self.bright_fraction}")
        if not (1.0 <= self.background_level <= 250.0):
            raise ValueError(f"background level must be 1..250, got {self.background_level}")


def _stamp(out: U8, u: float, v: float, s_maj: float, s_min: float, ang: float, gain: float, add: float) -> None:
    """out <- out * (1 + (gain - 1) g) + add g in a small window, g an elongated Gaussian at (u, v)
    with standard deviations s_maj along `ang` and s_min across; rounded, clipped to 0..255."""
    h, w = out.shape
    r = int(math.ceil(3.5 * s_maj)) + 1
    iu, iv = int(u), int(v)
    x0, x1 = max(0, iu - r), min(w, iu + r + 2)
    y0, y1 = max(0, iv - r), min(h, iv + r + 2)
    if x0 >= x1 or y0 >= y1:
        return
    ca, sa = math.cos(ang), math.sin(ang)
    i_maj, i_min = 1.0 / (s_maj * s_maj), 1.0 / (s_min * s_min)
    # Quadratic form of the inverse covariance, so the exponent is three broadcast terms.
    qa = ca * ca * i_maj + sa * sa * i_min
    qc = sa * sa * i_maj + ca * ca * i_min
    qb = 2.0 * ca * sa * (i_maj - i_min)
    dx = np.arange(x0 - u, x1 - u, dtype=np.float32)[: x1 - x0]
    dy = np.arange(y0 - v, y1 - v, dtype=np.float32)[: y1 - y0, None]
    g = np.exp(-0.5 * (qa * dx * dx + qc * dy * dy + qb * dy * dx))
    win = out[y0:y1, x0:x1]
    val = win * (1.0 + (gain - 1.0) * g)
    if add:
        val += add * g
    np.clip(val + 0.5, 0, 255, out=val)
    win[...] = val


def _stamp_many(out: U8, u: np.ndarray, v: np.ndarray, s_maj: np.ndarray, s_min: np.ndarray, ang: np.ndarray,
                gain: np.ndarray) -> None:
    """Several multiplicative blobs (as `_stamp` with add = 0): their Gaussians are computed in one
    batch over equal windows, then applied one window at a time (so overlapping blobs compose)."""
    h, w = out.shape
    r = int(math.ceil(3.5 * float(s_maj.max()))) + 1
    size = 2 * r + 2
    iu, iv = u.astype(np.int64), v.astype(np.int64)
    x0, y0 = iu - r, iv - r
    ca, sa = np.cos(ang), np.sin(ang)
    i_maj, i_min = 1.0 / (s_maj * s_maj), 1.0 / (s_min * s_min)
    qa = (ca * ca * i_maj + sa * sa * i_min)[:, None, None]
    qc = (sa * sa * i_maj + ca * ca * i_min)[:, None, None]
    qb = (2.0 * ca * sa * (i_maj - i_min))[:, None, None]
    steps = np.arange(size, dtype=np.float64)
    dx = (x0[:, None] + steps[None, :] - u[:, None])[:, None, :]
    dy = (y0[:, None] + steps[None, :] - v[:, None])[:, :, None]
    g = np.exp(-0.5 * (qa * dx * dx + qc * dy * dy + qb * dy * dx))
    f = (1.0 + (gain - 1.0)[:, None, None] * g).astype(np.float32)
    darker = (gain <= 1.0).tolist()
    for i in range(u.size):
        xa, ya = int(x0[i]), int(y0[i])
        xs, ys = max(0, xa), max(0, ya)
        xe, ye = min(w, xa + size), min(h, ya + size)
        if xs >= xe or ys >= ye:
            continue
        win = out[ys:ye, xs:xe]
        val = win * f[i, ys - ya : ye - ya, xs - xa : xe - xa]
        val += 0.5  # round on the cast below
        if not darker[i]:  # a darker pixel cannot leave 0..255; a brighter one can
            np.minimum(val, 255.0, out=val)
        win[...] = val


@dataclass
class _FalseBlob:
    u: float
    v: float
    sigma: float
    amplitude: float  # signed grey levels
    frames_left: int


@dataclass
class DrawnBlob:
    """What was drawn, for tests and for checking the edge's detections."""

    animal: int  # -1 for a false blob
    u: float
    v: float


@dataclass
class CameraRenderer:
    camera: Camera
    params: RenderParams = field(default_factory=RenderParams)
    seed: int = 0
    bright: NDArray[np.bool_] | None = None  # per animal, set by the caller or drawn from bright_fraction

    def __post_init__(self) -> None:
        cam, p = self.camera, self.params
        self.rng = np.random.default_rng(self.seed)
        h, w = cam.height, cam.width
        # Background: smooth structure (upsampled coarse noise) x vignetting.
        coarse = self.rng.normal(0.0, 1.0, (max(2, h // 48), max(2, w // 48))).astype(np.float32)
        smooth = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
        smooth /= max(1e-6, float(np.abs(smooth).max()))
        bg = p.background_level * (1.0 + p.texture * smooth)
        if p.vignetting:
            yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
            r2 = ((xx - cam.K[0, 2]) ** 2 + (yy - cam.K[1, 2]) ** 2) / float(cam.K[0, 0]) ** 2
            bg *= 1.0 / (1.0 + r2) ** 2  # cos^4 of the field angle
        self._bg = bg.astype(np.float32)
        self._levels: dict[int, U8] = {}
        self._level_step = 1.0 / p.background_level  # about one grey level per cached background
        # Noise bank: values offset by `off` so one saturating uint8 add applies signed noise.
        self._off = int(math.ceil(4 * p.noise_sigma)) if p.noise_sigma > 0 else 0
        n = h * w * max(2, p.noise_bank_frames)
        bank = self.rng.normal(self._off, p.noise_sigma, n) if p.noise_sigma > 0 else np.zeros(n)
        self._bank = np.clip(np.rint(bank), 0, 255).astype(np.uint8)
        self._n_pix = h * w
        self._phase = self.rng.uniform(0, 2 * math.pi, 2)
        self._false: list[_FalseBlob] = []
        self._out = np.empty((h, w), np.uint8)

    # --- background -----------------------------------------------------------------------------
    def gain(self, t: float) -> float:
        p = self.params
        a = p.drift_amplitude
        return 1.0 + a * (
            0.8 * math.sin(2 * math.pi * t / p.drift_period_s + self._phase[0])
            + 0.2 * math.sin(2 * math.pi * t / (p.drift_period_s * 0.31) + self._phase[1])
        )

    def _background(self, g: float) -> U8:
        q = int(round((g - 1.0) / self._level_step))
        base = self._levels.get(q)
        if base is None:
            level = self._bg * (1.0 + q * self._level_step) - self._off
            base = np.clip(np.rint(level), 0, 255).astype(np.uint8)
            self._levels[q] = base
        return base

    # --- frames ---------------------------------------------------------------------------------
    def render(
        self, t: float, pos: NDArray[np.float64], axis: NDArray[np.float64], body_length_m: float,
        body_width_m: float, drawn: list[DrawnBlob] | None = None, fresh: bool = False,
    ) -> U8:
        """The frame at time t for animals at `pos` (n,3) with unit body axes `axis` (n,3).

        Returns a uint8 (height, width) array that the next call reuses, unless `fresh` (a new array,
        for a caller that keeps frames: cheaper than copying)."""
        p = self.params
        out = np.empty_like(self._out) if fresh else self._out
        base = self._background(self.gain(t))
        start = int(self.rng.integers(0, self._bank.size - self._n_pix))
        noise = self._bank[start : start + self._n_pix].reshape(out.shape)
        cv2.add(base, noise, dst=out)
        n = pos.shape[0]
        if self.bright is None or self.bright.shape[0] != n:
            self.bright = self.rng.random(n) < p.bright_fraction
        if n:
            self._draw_animals(out, pos, axis, body_length_m, body_width_m, drawn)
        self._draw_false(out, drawn)
        return out

    def _draw_animals(
        self, out: U8, pos: NDArray[np.float64], axis: NDArray[np.float64], length: float, width: float,
        drawn: list[DrawnBlob] | None,
    ) -> None:
        cam, p = self.camera, self.params
        n = pos.shape[0]
        half = 0.5 * length * axis
        pts = np.concatenate([pos, pos + half, pos - half])
        uv = cam.project(pts)
        depth = cam.to_camera(pos)[:, 2]
        c, head, tail = uv[:n], uv[n : 2 * n], uv[2 * n :]
        # In front of the camera and inside the image (as Camera.in_view, without projecting again).
        m = 2.0
        with np.errstate(invalid="ignore"):
            visible = ((depth > 0) & (c[:, 0] >= -0.5 + m) & (c[:, 0] <= cam.width - 0.5 - m)
                       & (c[:, 1] >= -0.5 + m) & (c[:, 1] <= cam.height - 0.5 - m))
        if not np.any(visible):
            return
        major = head - tail
        f = float(cam.K[0, 0])
        with np.errstate(invalid="ignore", divide="ignore"):
            l_px = np.linalg.norm(major, axis=1)
            w_px = f * width / depth
        s_maj = np.sqrt((l_px / 3.0) ** 2 + p.psf_sigma_px**2)
        s_min = np.sqrt((w_px / 3.0) ** 2 + p.psf_sigma_px**2)
        # Occlusion: a nearer animal whose blob covers this one's centre hides it.
        order = [int(i) for i in np.argsort(depth) if visible[i]]
        if len(order) > 1:
            dist = np.hypot(c[:, None, 0] - c[None, :, 0], c[:, None, 1] - c[None, :, 1]).tolist()
            smaj = s_maj.tolist()
            shown: list[int] = []
            for i in order:
                if not any(dist[i][j] < smaj[j] for j in shown):
                    shown.append(i)
        else:
            shown = order
        if not shown:
            return
        idx = np.asarray(shown)
        ang = np.where(l_px[idx] > 1e-9, np.arctan2(major[idx, 1], major[idx, 0]), 0.0)
        k = p.contrast
        gain = np.where(self.bright[idx], 1.0 + k, 1.0 - k)
        _stamp_many(out, c[idx, 0], c[idx, 1], s_maj[idx], s_min[idx], ang, gain)
        if drawn is not None:
            drawn.extend(DrawnBlob(int(i), float(c[i, 0]), float(c[i, 1])) for i in shown)

    def _draw_false(self, out: U8, drawn: list[DrawnBlob] | None) -> None:
        p = self.params
        h, w = out.shape
        for _ in range(int(self.rng.poisson(p.false_blob_rate))):
            self._false.append(
                _FalseBlob(
                    u=float(self.rng.uniform(0, w - 1)),
                    v=float(self.rng.uniform(0, h - 1)),
                    sigma=float(self.rng.uniform(0.8, 2.0)),
                    amplitude=float(self.rng.uniform(40, 90) * self.rng.choice((-1.0, 1.0))),
                    frames_left=int(self.rng.integers(p.false_blob_frames[0], p.false_blob_frames[1] + 1)),
                )
            )
        keep: list[_FalseBlob] = []
        for fb in self._false:
            _stamp(out, fb.u, fb.v, fb.sigma, fb.sigma, 0.0, 1.0, fb.amplitude)
            if drawn is not None:
                drawn.append(DrawnBlob(-1, fb.u, fb.v))
            fb.frames_left -= 1
            if fb.frames_left > 0:
                keep.append(fb)
        self._false = keep
