"""Smoothing of the per-frame fits (seed 004 §4.3, eqs 4.3-4.4): the velocity and the heading are random
walks (d r_dot = d w_r, d h = d w_h), the length p1 a random walk and the bend p2..p5 decays to straight
at rate lambda (d p_i = -lambda p_i dt + d w_p,i). A forward Kalman filter gives the prediction the next
frame's fit starts from; a Rauch-Tung-Striebel pass over the whole track gives the smoothed output.

Filter state (14): r (3), r_dot (3), h (3), p (5); measurement: the fitted r, h, p (11).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
N = 14
H = np.zeros((11, N))
H[0:3, 0:3] = np.eye(3)
H[3:6, 6:9] = np.eye(3)
H[6:11, 9:14] = np.eye(5)


@dataclass
class SmootherConfig:
    lam: float = 5.0  # Table 2: decay of the midline parameters p2..p5 (1/s)
    # per-frame process noise standard deviations (white-noise intensities of eqs 4.3-4.4 times dt)
    sd_vel: float = 0.03  # m/s per frame (fast starts accelerate to ~0.4 m/s in ~10 frames)
    sd_head: float = 0.06  # per frame (unit heading; a C-start turns ~90 degrees in ~20 frames)
    sd_p1: float = 0.0003  # m per frame
    sd_bend: float = 0.004  # m per frame
    # measurement noise of one fit
    sd_r: float = 0.0004
    sd_h: float = 0.02
    sd_p: tuple[float, ...] = (0.001, 0.0015, 0.0015, 0.002, 0.002)


def _F(dt: float, lam: float) -> F64:
    F = np.eye(N)
    F[0:3, 3:6] = dt * np.eye(3)
    F[10:14, 10:14] = np.exp(-lam * dt) * np.eye(4)  # p2..p5 (state indices 10..13)
    return F


def _Q(cfg: SmootherConfig) -> F64:
    q = np.zeros(N)
    q[3:6] = cfg.sd_vel**2
    q[6:9] = cfg.sd_head**2
    q[9] = cfg.sd_p1**2
    q[10:14] = cfg.sd_bend**2
    return np.diag(q)


def _R(cfg: SmootherConfig) -> F64:
    return np.diag(np.concatenate([np.full(3, cfg.sd_r**2), np.full(3, cfg.sd_h**2), np.asarray(cfg.sd_p) ** 2]))


@dataclass
class TrackFilter:
    """Forward filter of one fish; keeps what the RTS pass needs."""

    dt: float
    cfg: SmootherConfig = field(default_factory=SmootherConfig)
    x: F64 = field(default_factory=lambda: np.zeros(N))
    P: F64 = field(default_factory=lambda: np.eye(N))
    xs_pred: list[F64] = field(default_factory=list)
    Ps_pred: list[F64] = field(default_factory=list)
    xs: list[F64] = field(default_factory=list)
    Ps: list[F64] = field(default_factory=list)

    def start(self, X: F64, vel: F64 | None = None) -> None:
        self.x = np.concatenate([X[0:3], np.zeros(3) if vel is None else vel, X[3:6], X[6:11]])
        self.P = np.diag(np.concatenate([np.full(3, 1e-6), np.full(3, 0.05**2), np.full(3, 1e-3),
                                         np.full(5, 1e-6)]))
        self.xs, self.Ps = [self.x.copy()], [self.P.copy()]
        self.xs_pred, self.Ps_pred = [self.x.copy()], [self.P.copy()]

    def predict(self) -> F64:
        """The predicted state X (11) for the next frame (the fit's starting point)."""
        F = _F(self.dt, self.cfg.lam)
        self.x_pred = F @ self.x
        self.P_pred = F @ self.P @ F.T + _Q(self.cfg)
        return self.x_pred[[0, 1, 2, 6, 7, 8, 9, 10, 11, 12, 13]]

    def update(self, X: F64 | None) -> None:
        """Fold in the fitted state X (11), or None for a frame without a measurement."""
        x, P = self.x_pred, self.P_pred
        self.xs_pred.append(x.copy())
        self.Ps_pred.append(P.copy())
        if X is not None and np.all(np.isfinite(X)):
            R = _R(self.cfg)
            y = X - H @ x
            S = H @ P @ H.T + R
            K = np.linalg.solve(S, H @ P).T
            x = x + K @ y
            P = (np.eye(N) - K @ H) @ P
            x[6:9] /= np.linalg.norm(x[6:9])
        self.x, self.P = x, P
        self.xs.append(x.copy())
        self.Ps.append(P.copy())

    def smoothed(self) -> tuple[F64, F64]:
        """RTS pass: smoothed states (T, 11) and their covariances (T, 11, 11) in the measurement layout."""
        F = _F(self.dt, self.cfg.lam)
        T = len(self.xs)
        xs = [None] * T
        Ps = [None] * T
        xs[-1], Ps[-1] = self.xs[-1], self.Ps[-1]
        for k in range(T - 2, -1, -1):
            Pp = self.Ps_pred[k + 1]
            C = np.linalg.solve(Pp.T, (self.Ps[k] @ F.T).T).T
            xs[k] = self.xs[k] + C @ (xs[k + 1] - self.xs_pred[k + 1])
            Ps[k] = self.Ps[k] + C @ (Ps[k + 1] - Pp) @ C.T
        X = np.array([H @ x for x in xs])
        X[:, 3:6] /= np.linalg.norm(X[:, 3:6], axis=1, keepdims=True)
        Pm = np.array([H @ P @ H.T for P in Ps])
        return X, Pm

    def filtered(self) -> tuple[F64, F64]:
        X = np.array([H @ x for x in self.xs])
        return X, np.array([H @ P @ H.T for P in self.Ps])
