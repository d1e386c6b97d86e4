"""Iterated extended Kalman filter (seed 004 §2.1, used in §3.2 for the cross-section sizes).

One measurement z = h(x) + n, n ~ N(0, R), prior x ~ N(x0, P0). The iterated update re-linearises h about
the latest estimate until the step is negligible (the seed stops on the norm of the covariance; with a
fixed measurement both come to rest together). The Jacobian is taken by finite differences, all columns
in one call of h, which takes a batch of states (B, n) -> (B, m).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass
class IEKFResult:
    x: F64
    P: F64
    iterations: int
    converged: bool


def jacobian(h: Callable[[F64], F64], x: F64, eps: F64 | float = 1e-6) -> tuple[F64, F64]:
    n = x.size
    e = np.broadcast_to(np.asarray(eps, float), (n,))
    X = np.vstack([x, x + np.diag(e)])
    Y = h(X)
    return Y[0], ((Y[1:] - Y[0]) / e[:, None]).T


def iekf_update(h: Callable[[F64], F64], z: F64, R: F64, x0: F64, P0: F64, max_iter: int = 20,
                tol: float = 1e-9, eps: F64 | float = 1e-6) -> IEKFResult:
    """The iterated EKF measurement update (Gauss-Newton on the MAP cost)."""
    x = x0.astype(float).copy()
    P = P0
    converged = False
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (it is reported)
        hx, H = jacobian(h, x, eps)
        S = H @ P0 @ H.T + R
        K = np.linalg.solve(S, H @ P0).T
        x_new = x0 + K @ (z - hx - H @ (x0 - x))
        P = (np.eye(x.size) - K @ H) @ P0
        step = np.linalg.norm(x_new - x)
        x = x_new
        if step <= tol * (1.0 + np.linalg.norm(x)):
            converged = True
            break
    return IEKFResult(x, P, it, converged)
