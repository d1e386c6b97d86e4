"""EKF updates from 2D observations that bring their own measurement covariance (event cameras).

Frame cameras' points share one noise, R = measurement_noise_px^2 I, and go through the tracker's
association and joint update. An event camera's edge sends each cluster with the covariance of its
Kalman filter (protocol/SPEC.md 1.6), so its points are worth what that covariance says: here each
one updates the target it is gated to with R = its own 2x2 covariance (px^2). The update runs after
the frame cameras' one, camera by camera (sequential updates with independent noises are the joint
update; the Jacobian is taken again at the updated state). Gating is on the innovation covariance
S = J P J^T + R (chi-square, 2 degrees of freedom), one point per target and one target per point,
closest first. These points never start a target: event clusters lag, merge and split, so two
event cameras' strays could triangulate into a phantom.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from flytrack_host.tracking.ekf import joseph_update
from flytrack_host.tracking.observation import CameraArray

F64 = NDArray[np.float64]

# chi-square with 2 degrees of freedom: P(d2 > 13.82) = 0.1 % for a point of the target.
GATE_CHI2 = 13.82


def covariance_matrices(cov: np.ndarray) -> F64:
    """(n, 3) var_x, var_y, cov_xy -> (n, 2, 2)."""
    c = np.asarray(cov, dtype=np.float64).reshape(-1, 3)
    R = np.empty((len(c), 2, 2))
    R[:, 0, 0], R[:, 1, 1] = c[:, 0], c[:, 1]
    R[:, 0, 1] = R[:, 1, 0] = c[:, 2]
    return R


def usable_covariance(cov: np.ndarray) -> NDArray[np.bool_]:
    """Rows that are finite positive-definite 2x2 covariances."""
    c = np.asarray(cov, dtype=np.float64).reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        return np.isfinite(c).all(axis=1) & (c[:, 0] > 0) & (c[:, 1] > 0) & (c[:, 2] ** 2 < c[:, 0] * c[:, 1])


def gate_and_pick(d2: F64, gate: float) -> list[tuple[int, int]]:
    """Pairs (target, point) with d2 <= gate, closest first, each target and point used once."""
    T, N = d2.shape
    ok = np.isfinite(d2) & (d2 <= gate)
    if not ok.any():
        return []
    ts, ns = np.nonzero(ok)
    order = np.argsort(d2[ts, ns], kind="stable")
    used_t, used_n = np.zeros(T, bool), np.zeros(N, bool)
    out: list[tuple[int, int]] = []
    for k in order.tolist():
        t, n = int(ts[k]), int(ns[k])
        if not (used_t[t] or used_n[n]):
            used_t[t] = used_n[n] = True
            out.append((t, n))
    return out


def own_covariance_update(
    x: F64, P: F64, cams: CameraArray, detections: Mapping[int, np.ndarray], covariances: Mapping[int, np.ndarray],
    gate: float = GATE_CHI2, scale: float = 1.0,
) -> tuple[list[tuple[int, int, int]], dict[str, int]]:
    """Updates x (T, 6) and P (T, 6, 6) in place with the points of the cameras in `covariances`
    (camera index -> (n, 3) var_x, var_y, cov_xy of detections[camera] in distorted pixels); each
    point's R is `scale` x its covariance (TrackingParams.own_cov_scale), for the gate and the update.

    Returns the pairs used, (target row, camera index, point index), and counts: `points` offered,
    `bad_covariance` (not a finite positive-definite covariance: not used), `gated_out`, `used`,
    `rejected` (updates whose posterior was not usable: the target kept its prior)."""
    stats = {"points": 0, "bad_covariance": 0, "gated_out": 0, "used": 0, "rejected": 0}
    pairs: list[tuple[int, int, int]] = []
    T = x.shape[0]
    for ci in sorted(covariances):
        pts = detections.get(ci)
        s = cams.slot_of.get(ci)
        if pts is None or s is None or len(pts) == 0:
            continue
        cov = np.asarray(covariances[ci], dtype=np.float64).reshape(-1, 3)
        if len(cov) != len(pts):
            raise ValueError(f"camera {ci}: {len(pts)} points but {len(cov)} covariances")
        n = len(pts)
        stats["points"] += n
        z = np.column_stack([pts["x_dist"], pts["y_dist"]]).astype(np.float64)
        good = usable_covariance(cov) & np.isfinite(z).all(axis=1)
        stats["bad_covariance"] += int((~good).sum())
        if T == 0 or not good.any():
            stats["gated_out"] += int(good.sum())
            continue
        R = covariance_matrices(cov) * float(scale)
        R[~good] = np.eye(2)  # placeholders, never used (their d2 is inf)
        uv_all, J_all, front_all = cams.project_jacobian(x[:, :3])
        uv, J, front = uv_all[s], J_all[s], front_all[s]  # (T, 2), (T, 2, 3), (T,)
        JPJ = J @ P[:, :3, :3] @ np.swapaxes(J, -1, -2)  # (T, 2, 2)
        S = JPJ[:, None] + R[None]  # (T, n, 2, 2)
        r = z[None] - uv[:, None]  # (T, n, 2)
        det = S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]
        with np.errstate(invalid="ignore", divide="ignore"):
            d2 = (S[..., 1, 1] * r[..., 0] ** 2 - 2 * S[..., 0, 1] * r[..., 0] * r[..., 1]
                  + S[..., 0, 0] * r[..., 1] ** 2) / det  # fmt: skip
        d2[~(np.isfinite(d2) & (det > 0))] = np.inf
        d2[~front] = np.inf
        d2[:, ~good] = np.inf
        chosen = gate_and_pick(d2, gate)
        stats["gated_out"] += int(good.sum()) - len(chosen)
        if not chosen:
            continue
        rows = np.array([t for t, _ in chosen], dtype=np.intp)
        cols = np.array([k for _, k in chosen], dtype=np.intp)
        H = np.zeros((rows.size, 2, 6))
        H[:, :, :3] = J[rows]
        xp, Pp, ok = joseph_update(x[rows], P[rows], z[cols], uv[rows], H, R[cols])
        x[rows[ok]] = xp[ok]
        P[rows[ok]] = Pp[ok]
        stats["used"] += int(ok.sum())
        stats["rejected"] += int((~ok).sum())
        pairs.extend((int(t), int(ci), int(k)) for t, k, a in zip(rows, cols, ok, strict=True) if a)
    return pairs, stats
