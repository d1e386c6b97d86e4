"""Extended Kalman filter maths for a constant-velocity 3D point, batched over targets.

Written in the FilterPy style (x, P, F, Q, H, R, y, S, K), but every function works on a stack of
targets at once: x is (T, 6), P is (T, 6, 6), so one NumPy call serves all targets of a frame.
State order: (x, y, z, vx, vy, vz) in metres and metres per second (seed 000 eq. 3.2).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
_I6 = np.eye(6)


@lru_cache(maxsize=64)
def _cv_matrices(dt: float, motion_noise_scale: float) -> tuple[F64, F64]:
    F = np.eye(6)
    F[0, 3] = F[1, 4] = F[2, 5] = dt
    # Braid's process noise: white acceleration integrated twice (a continuous Wiener velocity model).
    q = motion_noise_scale
    Q = np.zeros((6, 6))
    I3 = np.eye(3)
    Q[:3, :3] = q * dt**3 / 3.0 * I3
    Q[:3, 3:] = Q[3:, :3] = q * dt**2 / 2.0 * I3
    Q[3:, 3:] = q * dt * I3
    F.flags.writeable = False
    Q.flags.writeable = False
    return F, Q


def cv_transition(dt: float) -> F64:
    """State transition F(dt) of the constant-velocity model (read-only, cached)."""
    return _cv_matrices(float(dt), 1.0)[0]


def cv_process_noise(dt: float, motion_noise_scale: float) -> F64:
    """Q(dt) = scale * [[dt^3/3 I, dt^2/2 I], [dt^2/2 I, dt I]] (read-only, cached)."""
    return _cv_matrices(float(dt), float(motion_noise_scale))[1]


def predict(x: F64, P: F64, F: F64, Q: F64) -> tuple[F64, F64]:
    """A priori estimate (seed 000 eqs. A1, A2): x = F x, P = F P F^T + Q, for (T, 6) and (T, 6, 6)."""
    x_prior = x @ F.T
    P_prior = F @ P @ F.T + Q
    return x_prior, P_prior


def joseph_update(
    x: F64, P: F64, z: F64, hx: F64, H: F64, R: F64
) -> tuple[F64, F64, NDArray[np.bool_]]:
    """EKF measurement update with the Joseph-form covariance, batched over targets.

    x (T, 6), P (T, 6, 6): the prior. z (T, m): the observations; hx (T, m): h(x) at the prior;
    H (T, m, 6): the Jacobian of h at the prior; R (m, m) or (T, m, m): observation noise.
    Rows of H that are all zero (with z == hx) carry no information, so targets with different numbers
    of observations can share one padded batch.

    The Joseph form P+ = (I - K H) P (I - K H)^T + K R K^T is a sum of two symmetric positive
    semi-definite terms whatever K is, so round-off in K (an ill-conditioned S, a wild Jacobian) cannot
    make P+ indefinite the way the short form (I - K H) P can. As a last guard, a target whose posterior
    is not finite or not positive definite keeps its prior, and is flagged in the returned mask.

    Returns (x_post, P_post, accepted) where accepted (T,) says which targets took the update.
    """
    y = z - hx  # innovation
    Ht = np.swapaxes(H, -1, -2)
    PHt = P @ Ht  # (T, 6, m)
    S = H @ PHt + R  # innovation covariance (T, m, m)
    try:
        # K = P H^T S^-1, computed as solve(S, (P H^T)^T)^T since S is symmetric.
        K = np.swapaxes(np.linalg.solve(S, np.swapaxes(PHt, -1, -2)), -1, -2)
    except np.linalg.LinAlgError:
        K = np.empty_like(PHt)
        for k in range(S.shape[0]):
            try:
                K[k] = np.linalg.solve(S[k], PHt[k].T).T
            except np.linalg.LinAlgError:
                K[k] = np.nan  # rejected below
    x_post = x + (K @ y[..., None])[..., 0]
    P_post = joseph_covariance(P, K, H, R)
    accepted = _usable(x_post, P_post)
    if not accepted.all():
        x_post[~accepted] = x[~accepted]
        P_post[~accepted] = P[~accepted]
    return x_post, P_post, accepted


def joseph_covariance(P: F64, K: F64, H: F64, R: F64) -> F64:
    """P+ = (I - K H) P (I - K H)^T + K R K^T, symmetrised, for (T, 6, 6) P and (T, 6, m) K.

    Positive semi-definite for any gain K, not only the optimal one: an error in K (round-off in
    solving an ill-conditioned S) costs accuracy, never definiteness."""
    I_KH = _I6 - K @ H
    P_post = (I_KH @ P) @ np.swapaxes(I_KH, -1, -2)
    P_post += (K @ R) @ np.swapaxes(K, -1, -2)
    P_post += np.swapaxes(P_post, -1, -2).copy()
    P_post *= 0.5
    return P_post


def _usable(x: F64, P: F64) -> NDArray[np.bool_]:
    """Which (x, P) pairs are finite with P positive definite (Cholesky succeeds)."""
    if np.isfinite(x).all() and np.isfinite(P).all():  # the usual case, in as few calls as possible
        try:
            np.linalg.cholesky(P)
            return np.ones(x.shape[0], dtype=bool)
        except np.linalg.LinAlgError:
            ok = np.ones(x.shape[0], dtype=bool)
    else:
        ok = np.isfinite(x).all(axis=1) & np.isfinite(P).all(axis=(1, 2))
    for k in np.flatnonzero(ok):
        try:
            np.linalg.cholesky(P[k])
        except np.linalg.LinAlgError:
            ok[k] = False
    return ok


def is_symmetric_positive_definite(P: F64, rtol: float = 1e-9) -> bool:
    """True when P (6, 6) is finite, symmetric to rtol and has a Cholesky factor."""
    if not np.all(np.isfinite(P)):
        return False
    scale = max(float(np.max(np.abs(P))), 1e-300)
    if np.max(np.abs(P - P.T)) > rtol * scale:
        return False
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return False
    return True
