"""Points with their own covariance (event cameras, SPEC 1.6) update targets with that covariance as
R: a tight point pulls the estimate, a loose one barely; a point outside its gate is not used; such
points never start a target. Both tracker paths (NumPy and the C kernel) do the same."""

from __future__ import annotations

import numpy as np
import pytest

from flytrack_host.protocol import POINT_DTYPE
from flytrack_host.tracking import kernel as ckernel
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.synthetic import arena_cameras
from flytrack_host.tracking.tracker import Tracker
from flytrack_host.tracking.types import FrameBundle

FPS = 100.0
DVS = 3  # the fourth camera plays the event camera


def _points(cam, X: np.ndarray, du: float = 0.0) -> np.ndarray:
    uv = cam.project(X[None])[0]
    p = np.zeros(1, POINT_DTYPE)
    p["x_dist"], p["y_dist"] = uv[0] + du, uv[1]
    u = cam.undistort(np.array([[uv[0] + du, uv[1]]]))[0] if cam.has_distortion else (uv[0] + du, uv[1])
    p["x_undist"], p["y_undist"] = u[0], u[1]
    p["area"] = 20.0
    p["orientation"] = np.nan
    p["eccentricity"] = np.nan
    return p


def _run(kernel: str, dvs_var: float | None, du: float = 1.0, frames: int = 30) -> tuple[np.ndarray, Tracker]:
    """A target on a straight path seen by three frame cameras; at the last frame the 'event camera'
    adds a point du px off with covariance dvs_var I (None: no such point). Returns the estimate."""
    cams = arena_cameras(4, seed=3)
    tr = Tracker(cams, TrackingParams(kernel=kernel, own_cov_scale=1.0), 1.0 / FPS)
    X0, v = np.array([0.4, 0.15, 0.12]), np.array([0.2, 0.05, 0.0])
    est = None
    for f in range(frames):
        X = X0 + v * f / FPS
        det = {c: _points(cams[c], X) for c in range(3)}
        b = FrameBundle(f, f / FPS, det)
        if f == frames - 1 and dvs_var is not None:
            b.detections[DVS] = _points(cams[DVS], X, du)
            b.point_cov[DVS] = np.array([[dvs_var, dvs_var, 0.0]])
        res = tr.process(b)
        if res.estimates:
            est = res.estimates[0].state[:3].copy()
    assert est is not None
    return est, tr


KERNELS = ["numpy"] + (["c"] if ckernel.unavailable_reason() is None else [])


@pytest.mark.parametrize("kernel", KERNELS)
def test_the_points_covariance_is_their_measurement_noise(kernel: str) -> None:
    base, _ = _run(kernel, None)
    tight, tr_t = _run(kernel, 0.01)
    loose, tr_l = _run(kernel, 100.0)
    assert tr_t.stats["own_cov_used"] == 1 and tr_l.stats["own_cov_used"] == 1
    pull_tight = np.linalg.norm(tight - base)
    pull_loose = np.linalg.norm(loose - base)
    # 0.01 px^2 against the frame cameras' 1 px^2: the event point moves the estimate most of the way
    # towards its ray; at 100 px^2 hardly at all. (A tracker that gave it the frame cameras' R would
    # move both by the same amount.)
    assert pull_tight > 20 * pull_loose, (pull_tight, pull_loose)
    assert pull_tight > 1e-4  # metres: 1 px at this range is about a millimetre
    # the associations report the event camera's point, so recordings and summaries can count it
    last = tr_t.process(FrameBundle(30, 0.3, {}))  # (an empty frame: nothing more to associate)
    assert not last.associations


@pytest.mark.parametrize("kernel", KERNELS)
def test_a_point_outside_its_gate_is_not_used_and_never_starts_a_target(kernel: str) -> None:
    _, tr = _run(kernel, 0.01, du=60.0)  # 60 px off with a 0.1 px std: far outside the chi-square gate
    assert tr.stats["own_cov_used"] == 0 and tr.stats["own_cov_gated_out"] == 1
    cams = arena_cameras(4, seed=3)
    tr2 = Tracker(cams, TrackingParams(kernel=kernel), 1.0 / FPS)
    X = np.array([0.5, 0.1, 0.1])
    for f in range(20):  # only 'event camera' points, from two cameras: they never make a target
        det = {c: _points(cams[c], X) for c in (2, 3)}
        tr2.process(FrameBundle(f, f / FPS, det, point_cov={c: np.array([[0.5, 0.5, 0.0]]) for c in (2, 3)}))
    assert tr2.n_targets == 0 and tr2.stats["births"] == 0 and tr2.stats["own_cov_points"] == 40


def test_bad_covariances_are_counted_and_not_used() -> None:
    for bad in ([np.nan, 1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 2.0]):
        cams = arena_cameras(4, seed=3)
        tr = Tracker(cams, TrackingParams(kernel="numpy"), 1.0 / FPS)
        X0 = np.array([0.4, 0.15, 0.12])
        for f in range(12):
            b = FrameBundle(f, f / FPS, {c: _points(cams[c], X0) for c in range(3)})
            b.detections[DVS] = _points(cams[DVS], X0)
            b.point_cov[DVS] = np.array([bad])
            tr.process(b)
        assert tr.stats["own_cov_bad"] == 12 and tr.stats["own_cov_used"] == 0, bad
