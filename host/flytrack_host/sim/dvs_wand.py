"""A blinking LED wand waved through the volume, seen by frame cameras and by simulated DVS cameras:
the ground truth for calibrating event cameras together with frame cameras.

The LED follows the calibration simulation's path (calibration.synthetic.led_path) and the frame
cameras see it as that simulation does (calibration.synthetic.observe: one 2D point per trigger frame,
pixel noise, drop-outs, a few gross outliers; the LED blinks far faster than a frame's exposure, so
it is lit in every frame). Each DVS camera renders, with sim/dvs.py's sensor model (DvsRenderer.fire:
contrast threshold, refractory period, background activity), a scene of
- the LED: a bright spot (the lens PSF) switched on and off as a square wave at `led_hz`; every switch
  is a step of light, so the pixels it covers fire ON events at switch-on and OFF at switch-off, a
  burst of up to a few events each (one per refractory period), first ones within `latency_us`;
- a distractor: a dark ball that moves through the volume and does not blink (a hand, a moth);
- background-activity noise at `noise_hz_per_px`.
The sensor clock has its own epoch and runs `clock_ppm` fast against the trigger, and a sync event
(EVT 2.0 EXT_TRIGGER, rising edge) is written at every trigger pulse, as the DVS bridge records the
trigger firmware's frame output: the sync events are the only tie between event times and frames.
Each DVS camera's stream is a Prophesee EVT 2.0 file the event readers open (events.EventReader).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from flytrack_host.calibration.observations import Observations
from flytrack_host.calibration.synthetic import led_path, make_rig, observe
from flytrack_host.geometry.camera import Camera
from flytrack_host.sim.dvs import DVS_SIZES, DvsParams, DvsRenderer, Evt2Encoder, _pack, evt2_header

__all__ = ["WandParams", "WandScene", "simulate_wand", "dvs_cameras"]


@dataclass(frozen=True)
class WandParams:
    led_hz: float = 500.0  # square-wave blink frequency of the LED
    duty: float = 0.5  # fraction of each period the LED is on
    led_gain: float = 20.0  # LED light over the background at the spot's centre (linear)
    latency_us: float = 100.0  # a pixel's first event after a switch comes within this (less if brighter)
    led_substeps: int = 2  # the moving LED is drawn this many times per on (or off) phase
    wave_s: float = 20.0  # the calibration path's pattern spans this long (the wand's speed: 1 m/s median)
    hidden: float = 0.15  # fraction of the time the LED is turned away from each DVS (spells of ~0.3 s)
    distractor_m: float = 0.1  # diameter of the dark non-blinking ball (a hand); 0: none
    distractor_contrast: float = 0.7  # fraction of the light the ball blocks at its centre
    noise_hz_per_px: float = 1.0  # background activity of the DVS, events per pixel per second
    clock_ppm: float = 40.0  # the DVS clock runs this much fast against the trigger
    frame_noise_px: float = 0.3  # frame cameras' detection noise
    frame_missing: float = 0.2  # fraction of frame-camera views without a detection
    frame_outliers: float = 0.01  # fraction of frame-camera detections that are gross outliers

    def __post_init__(self) -> None:
        if not (1.0 <= self.led_hz <= 20_000.0):
            raise ValueError(f"LED frequency must be 1..20000 Hz, got {self.led_hz}")
        if not (0.05 <= self.duty <= 0.95):
            raise ValueError(f"duty must be 0.05..0.95, got {self.duty}")


@dataclass
class WandScene:
    frame_cameras: dict[str, Camera]
    dvs_cameras: dict[str, Camera]
    t: NDArray[np.float64]  # (F,) trigger times, seconds (trigger clock)
    led: NDArray[np.float64]  # (F, 3) true LED position at each trigger frame
    frame_obs: Observations  # the frame cameras' 2D points, frame = trigger frame number
    dvs_files: dict[str, Path] = field(default_factory=dict)  # EVT 2.0 file per DVS camera
    dvs_events: dict[str, int] = field(default_factory=dict)  # events written per DVS camera
    dvs_syncs: dict[str, int] = field(default_factory=dict)  # sync events written per DVS camera
    dvs_hidden: dict[str, NDArray[np.bool_]] = field(default_factory=dict)  # (F,) LED turned away at frame
    params: WandParams = field(default_factory=WandParams)


def dvs_cameras(n: int, arena: float, seed: int, sensor: str = "davis346") -> dict[str, Camera]:
    """DVS cameras around the calibration arena, placed as calibration.synthetic places frame cameras
    (another seed), without lens distortion, named dvs1, dvs2, ..."""
    if sensor not in DVS_SIZES:
        raise ValueError(f"unknown DVS sensor {sensor!r}; one of {', '.join(DVS_SIZES)}")
    w, h = DVS_SIZES[sensor]
    cams = make_rig(n, arena=arena, seed=seed + 50_000, width=w, height=h, dist_k1=0.0, dist_k2=0.0,
                    principal_offset_px=0.0)
    return {f"dvs{i + 1}": Camera(f"dvs{i + 1}", c.width, c.height, c.K, c.R, c.t, c.dist)
            for i, c in enumerate(cams.values())}


class _SensorClock(DvsRenderer):
    """The renderer with a sensor clock that runs `ppm` fast against the trigger's."""

    def __init__(self, camera: Camera, params: DvsParams, seed: int, t0_us: int, ppm: float) -> None:
        super().__init__(camera, params, seed=seed, t0_us=t0_us)
        self.scale = 1.0 + ppm * 1e-6

    def to_us(self, t):  # type: ignore[no-untyped-def]
        return super().to_us(np.asarray(t) * self.scale if np.ndim(t) else float(t) * self.scale)


def _interp(t_path: NDArray[np.float64], path: NDArray[np.float64], t: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.column_stack([np.interp(t, t_path, path[:, a]) for a in range(3)])


def _window(uvs: NDArray[np.float64], r: float, w: int, h: int) -> tuple[int, int, int, int] | None:
    """Pixel window [y0:y1, x0:x1] around the given (u, v) points plus r pixels, clipped; None if empty."""
    uvs = uvs[np.all(np.isfinite(uvs), axis=1)]
    if not len(uvs):
        return None
    rr = math.ceil(r)
    x0, x1 = max(0, int(uvs[:, 0].min()) - rr), min(w, int(uvs[:, 0].max()) + rr + 2)
    y0, y1 = max(0, int(uvs[:, 1].min()) - rr), min(h, int(uvs[:, 1].max()) + rr + 2)
    if x0 >= x1 or y0 >= y1:
        return None
    return y0, y1, x0, x1


def _render_dvs(cam: Camera, p: WandParams, dvs: DvsParams, t_frames: NDArray[np.float64],
                t_path: NDArray[np.float64], led: NDArray[np.float64], ball: NDArray[np.float64],
                phase: float, seed: int, t0_us: int, out: Path) -> tuple[int, int, NDArray[np.bool_]]:
    """Writes one DVS camera's EVT 2.0 file; returns (events, sync events) written and at which
    frames the LED was turned away from this camera."""
    r = _SensorClock(cam, dvs, seed=seed, t0_us=t0_us, ppm=p.clock_ppm)
    w, h = cam.width, cam.height
    period = 1.0 / p.led_hz
    sig_led = dvs.psf_sigma_px
    # Switch times of the whole run: on at phase + k T, off at phase + (k + duty) T; between switches
    # the LED is drawn again every so often (it moves while lit: its leading edge brightens, its
    # trailing edge darkens).
    k = np.arange(math.floor((t_frames[0] - phase) / period) - 1, math.ceil((t_frames[-1] - phase) / period) + 1)
    sw_t = np.concatenate([phase + k * period, phase + (k + p.duty) * period])
    sw_on = np.concatenate([np.ones(len(k), bool), np.zeros(len(k), bool)])
    o = np.argsort(sw_t, kind="stable")
    sw_t, sw_on = sw_t[o], sw_on[o]
    m = p.led_substeps
    rng = np.random.default_rng(seed + 99)
    gap = np.diff(sw_t, append=sw_t[-1] + period / 2)
    sw_is_switch = np.tile(np.arange(m) == 0, len(sw_t))
    # (at random times inside the phase: the light of a moving spot changes continuously, so these
    # events are not locked to the switches)
    frac = np.column_stack([np.zeros(len(sw_t)), np.sort(rng.uniform(0.1, 0.9, (len(sw_t), m - 1)), axis=1)])
    sw_t = (sw_t[:, None] + gap[:, None] * frac).ravel()
    sw_on = np.repeat(sw_on, m)
    # Spells with the LED turned away from this camera (dark for it: its events stop).
    hid_t = np.zeros(0)
    if p.hidden > 0:
        span = float(t_frames[-1] - t_frames[0])
        n_sp = rng.poisson(p.hidden * span / 0.3) if span > 0 else 0
        starts = rng.uniform(t_frames[0], t_frames[-1], n_sp)
        hid_t = np.column_stack([starts, starts + rng.uniform(0.15, 0.45, n_sp)])

    def hidden_at(t: NDArray[np.float64]) -> NDArray[np.bool_]:
        if not len(hid_t):
            return np.zeros(len(t), bool)
        return np.any((t[:, None] >= hid_t[None, :, 0]) & (t[:, None] < hid_t[None, :, 1]), axis=1)
    sw_on &= ~hidden_at(sw_t)
    hidden_frames = hidden_at(t_frames)
    steps = dvs.substeps
    enc = Evt2Encoder()
    n_ev = 0
    n_sync = 0
    log_bg = math.log(dvs.background)
    # Everything projected at once: the LED at each switch (and half a period before), the ball at
    # each substep (the scene between two samples is drawn as at the last one).
    sw_uv = cam.project(_interp(t_path, led, sw_t))
    sw_uv_prev = np.vstack([sw_uv[:1], sw_uv[:-1]])  # where it was at the sample before
    sub_t = (t_frames[:-1, None] + np.diff(t_frames)[:, None] * (np.arange(steps + 1) / steps)[None, :]).ravel()
    if p.distractor_m > 0:
        ball_b, ball_ok = r._blobs(_interp(t_path, ball, sub_t), p.distractor_m, p.distractor_m)
    else:
        ball_b, ball_ok = np.zeros((len(sub_t), 3)), np.zeros(len(sub_t), bool)

    def scene(i_sw: int, i_sub: int, win: tuple[int, int, int, int]) -> NDArray[np.float32]:
        """Log intensity over the window with the LED as after switch i_sw and the ball at substep i_sub."""
        y0, y1, x0, x1 = win
        yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float64)
        light = np.ones(yy.shape)
        if ball_ok[i_sub]:
            u, v, sb = ball_b[i_sub]
            light *= 1.0 - p.distractor_contrast * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sb * sb))
        if i_sw >= 0 and sw_on[i_sw] and np.all(np.isfinite(sw_uv[i_sw])):
            u, v = sw_uv[i_sw]
            light += p.led_gain * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sig_led**2))
        return (log_bg + np.log(light)).astype(np.float32)

    with out.open("wb") as fh:
        fh.write(evt2_header(w, h))
        fh.write(enc.encode(_pack(*(np.zeros(0, np.int64),) * 4), sync_us=r.to_us(float(t_frames[0]))))
        n_sync += 1
        for n in range(1, len(t_frames)):
            ta, tb = float(t_frames[n - 1]), float(t_frames[n])
            parts: list[tuple[np.ndarray, ...]] = []
            # Samples of the scene in time order: the LED's switches (the LED's pixels) and the
            # renderer's substeps (the moving ball's pixels); each window is fired until the next
            # sample of its kind, the whole scene (LED and ball) drawn in it.
            sel = (sw_t >= ta) & (sw_t < tb)
            jobs = [(float(sw_t[i]), "led", int(i)) for i in np.nonzero(sel)[0]]
            if p.distractor_m > 0:
                jobs += [(float(sub_t[(n - 1) * (steps + 1) + i]), "ball", (n - 1) * (steps + 1) + i)
                         for i in range(steps)]
            jobs.sort(key=lambda j: j[0])
            i_sub = (n - 1) * (steps + 1)
            for t, kind, i in jobs:
                if kind == "led":
                    i_sw = i
                    t_next = min(float(sw_t[i + 1]) if i + 1 < len(sw_t) else tb, tb)
                    win = _window(np.vstack([sw_uv[i], sw_uv_prev[i]]), 4 * sig_led, w, h)
                    if win is None:
                        continue
                    got = r.fire(scene(i_sw, i_sub, win), win[0], win[2], t, t_next - t,
                                 latency=p.latency_us * 1e-6 if sw_is_switch[i] else None)
                else:
                    i_sub = i
                    i_sw = int(np.searchsorted(sw_t, t, side="right")) - 1  # the last switch at or before t
                    dt = (tb - ta) / steps
                    both = ball_ok[i:i + 2]
                    if not np.any(both):
                        continue
                    win = _window(ball_b[i:i + 2, :2][both], 4 * float(ball_b[i:i + 2, 2][both].max()), w, h)
                    if win is None:
                        continue
                    got = r.fire(scene(i_sw, i_sub, win), win[0], win[2], t, dt)
                if got is not None:
                    parts.append(got)
            noise = r.noise(ta, tb)
            if noise is not None:
                parts.append(noise)
            if parts:
                ev = _pack(*(np.concatenate([q[i] for q in parts]) for i in range(4)))
                ev = ev[np.argsort(ev["t"], kind="stable")]
            else:
                ev = _pack(*(np.zeros(0, np.int64),) * 4)
            sync = r.to_us(tb)
            ev = ev[ev["t"] <= sync]  # (the burst of a switch just before the pulse ends at the pulse)
            fh.write(enc.encode(ev, sync_us=sync))
            n_ev += len(ev)
            n_sync += 1
    return n_ev, n_sync, hidden_frames


def simulate_wand(out_dir: str | Path | None, n_frame_cameras: int = 4, n_dvs: int = 2, seconds: float = 10.0,
                  fps: float = 100.0, arena: float = 1.0, sensor: str = "davis346", seed: int = 0,
                  params: WandParams | None = None, dvs_params: DvsParams | None = None) -> WandScene:
    """Frame cameras' points and one EVT 2.0 file per DVS camera (`<out_dir>/dvsN.raw`; none when
    out_dir is None) of an LED wand waved through a cubic arena for `seconds` at `fps` trigger frames."""
    p = params or WandParams()
    dvs = dvs_params or DvsParams(noise_hz_per_px=p.noise_hz_per_px)
    n_frames = int(round(seconds * fps))
    if n_frames < 10:
        raise ValueError(f"{seconds} s at {fps} fps is fewer than 10 frames")
    over = 10  # path samples per frame; the DVS sees the LED between frames, interpolated linearly
    t_path = np.arange((n_frames - 1) * over + 1) / (fps * over)
    # The pattern of led_path over wave_s (a shorter run takes its start): the speed of a waved wand
    n_path = max(len(t_path), int(round(p.wave_s * fps * over)) + 1)
    led = led_path(n_path, arena=arena, seed=seed)[: len(t_path)]
    ball = led_path(n_path, arena=arena, seed=seed + 777)[: len(t_path)]
    t_frames = t_path[::over]
    frame_cams = make_rig(n_frame_cameras, arena=arena, seed=seed)
    obs, _ = observe(frame_cams, led[::over], noise_px=p.frame_noise_px, missing=p.frame_missing,
                     outliers=p.frame_outliers, seed=seed)
    scene = WandScene(frame_cams, dvs_cameras(n_dvs, arena, seed, sensor), t_frames, led[::over], obs, params=p)
    if out_dir is None:
        return scene
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed + 4242)
    for i, (name, cam) in enumerate(scene.dvs_cameras.items()):
        path = out / f"{name}.raw"
        scene.dvs_events[name], scene.dvs_syncs[name], scene.dvs_hidden[name] = _render_dvs(
            cam, p, dvs, t_frames, t_path, led, ball, phase=float(rng.uniform(0, 1 / p.led_hz)),
            seed=seed * 1000 + 17 + i, t0_us=3_000_000 * (i + 1) + 4321, out=path)
        scene.dvs_files[name] = path
    return scene
