"""The extended Kalman filter on a sinusoid of seed 002 (part II, section 3.2, eqs 9-15), with the two
improvements the seed proposes: a Fourier series of several harmonics, and averaging a few events per
update.

State: x = (a, b1, [b2, c2, ..., bK, cK], xi, omega); the edge's angle is

    h(x) = a + b1 sin(xi) + sum_{k=2..K} (b_k sin(k xi) + c_k cos(k xi))

which for K = 1 is the seed's h = a + M sin(xi) (eq. 9). The transition only advances the phase,
xi += omega dt (eq. 10), with dt the time since the last update taken from the events' own times; events
with the same time are updated without a prediction (the seed's choice). Process noise is given per
second (Q dt), so the filter behaves the same at any event rate. The measurement Jacobian is
dh/dx = (1, sin xi, ..., b1 cos xi + sum k (b_k cos k xi - c_k sin k xi), 0): the phase carries the time,
so h depends on omega only through xi, and omega is corrected by its covariance with xi (the seed's eq.
14 prints "a sin(xi)" and "M t cos(xi)" there, which do not match its own eqs 9-10). Updates use the
optimal-gain form (P - K H P, symmetrised); an event whose innovation is beyond `gate_sigma` standard
deviations is not used (noise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from flytrack_host.dvs.wingbeat.wra import BeatSeries, EdgeTrack

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class EkfParams:
    harmonics: int = 2  # K; 1 is the seed's plain sinusoid
    events_per_update: int = 4  # events averaged per update (the seed's speed-up); 1 = every event
    measurement_std_rad: float = 0.06  # one event's angle about its edge (pixel grid, timing jitter)
    q_centre: float = 0.05  # rad^2/s: the wing's mean position
    q_shape: float = 1.0  # rad^2/s: amplitude and harmonics
    q_phase: float = 2.0  # rad^2/s
    q_omega: float = 4e3  # (rad/s)^2/s: lets the frequency follow a manoeuvre
    gate_sigma: float = 4.0
    initial_phase_std: float = np.pi
    initial_freq_std_hz: float = 5.0


def _n_shape(k: int) -> int:
    return 2 * k  # a, b1, then (b_k, c_k) for k = 2..K


def shape_value(x: NDArray[np.float64], xi: NDArray[np.float64] | float, k: int) -> NDArray[np.float64]:
    """h for the shape part of state x at phases xi."""
    xi = np.asarray(xi, dtype=np.float64)
    h = x[0] + x[1] * np.sin(xi)
    for j in range(2, k + 1):
        h = h + x[2 * j - 2] * np.sin(j * xi) + x[2 * j - 1] * np.cos(j * xi)
    return h


def shape_amplitude(x: NDArray[np.float64], k: int) -> float:
    """Half the range of h over one beat (for K = 1 it is |b1|)."""
    if k == 1:
        return float(abs(x[1]))
    h = shape_value(x, np.linspace(0.0, TWO_PI, 96, endpoint=False), k)
    return float(0.5 * (h.max() - h.min()))


def ekf_track(t_us: NDArray, z: NDArray, centre: float, amplitude: float, freq_hz: float,
              params: EkfParams = EkfParams()) -> EdgeTrack:
    """Track one edge from its events' times (us) and angles (rad): a starting guess of its centre,
    amplitude and frequency (from the initialisation) is enough."""
    k = params.harmonics
    if k < 1:
        raise ValueError("harmonics must be at least 1")
    ns = _n_shape(k)
    n = ns + 2
    ixi, iom = ns, ns + 1
    t = np.asarray(t_us, dtype=np.float64) * 1e-6
    zz = np.asarray(z, dtype=np.float64)
    m = max(1, int(params.events_per_update))
    if m > 1 and len(zz) >= m:  # average consecutive events: one update per group
        g = len(zz) // m
        t = t[: g * m].reshape(g, m).mean(axis=1)
        zz = zz[: g * m].reshape(g, m).mean(axis=1)
    r = params.measurement_std_rad ** 2 / m
    q = np.zeros(n)
    q[0] = params.q_centre
    q[1:ns] = params.q_shape
    q[ixi] = params.q_phase
    q[iom] = params.q_omega
    x = np.zeros(n)
    x[0], x[1], x[iom] = centre, amplitude, TWO_PI * freq_hz
    if len(zz):
        x[ixi] = np.arcsin(np.clip((zz[0] - centre) / max(amplitude, 1e-6), -1.0, 1.0))
    p = np.diag(np.r_[0.1 ** 2, np.full(ns - 1, 0.3 ** 2), params.initial_phase_std ** 2,
                      (TWO_PI * params.initial_freq_std_hz) ** 2])
    hvec = np.zeros(n)
    hvec[0] = 1.0
    pos = np.empty(len(zz))
    keep = np.zeros(len(zz), dtype=bool)
    beats_t, beats_f, beats_a = [], [], []
    t_last = t[0] if len(t) else 0.0
    cycle = math.floor(x[ixi] / TWO_PI)
    gated = 0
    gate2 = params.gate_sigma ** 2
    diag = np.diag_indices(n)
    sin, cos = math.sin, math.cos
    for i in range(len(zz)):
        dt = t[i] - t_last
        if dt > 0.0:
            # Predict (eq. 10): F = I with F[xi, omega] = dt.  F P F^T + Q dt, written out.
            x[ixi] += x[iom] * dt
            p[ixi, :] += dt * p[iom, :]
            p[:, ixi] += dt * p[:, iom]
            p[diag] += q * dt
            t_last = t[i]
            c = math.floor(x[ixi] / TWO_PI)
            if c != cycle:  # a beat ended: report it
                cycle = c
                beats_t.append(t[i] * 1e6)
                beats_f.append(x[iom] / TWO_PI)
                beats_a.append(shape_amplitude(x, k))
        xi = float(x[ixi])
        sx, cx = sin(xi), cos(xi)
        hvec[1] = sx
        h = x[0] + x[1] * sx
        dxi = x[1] * cx
        for j in range(2, k + 1):
            s, co = sin(j * xi), cos(j * xi)
            hvec[2 * j - 2], hvec[2 * j - 1] = s, co
            bj, cj = x[2 * j - 2], x[2 * j - 1]
            h += bj * s + cj * co
            dxi += j * (bj * co - cj * s)
        hvec[ixi] = dxi
        y = zz[i] - h
        ph = p @ hvec
        s_var = float(hvec @ ph) + r
        if y * y > gate2 * s_var:
            gated += 1
            continue
        gain = ph / s_var
        x += gain * y
        # The optimal-gain update P - K H P (what the Joseph form reduces to for this gain), kept
        # symmetric; the 6x6 Joseph product costs twice as much per event for nothing more here.
        p -= np.outer(gain, ph)
        p = 0.5 * (p + p.T)
        pos[i] = h + float(hvec @ (gain * y))  # first-order h at the updated state
        keep[i] = True
    return EdgeTrack(t_us=t[keep] * 1e6, position=pos[keep],
                     beats=BeatSeries(np.array(beats_t), np.array(beats_f), np.array(beats_a)),
                     used=int(keep.sum()) * m, gated=gated * m)
