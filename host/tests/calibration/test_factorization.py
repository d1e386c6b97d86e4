"""Projective factorisation and Euclidean upgrade on exact data: projective, then metric, cameras; plot axes."""

from __future__ import annotations

import numpy as np
import pytest

from flytrack_host.calibration.factorization import FactorizationError, projective_factorization
from flytrack_host.calibration.metric_upgrade import MetricUpgradeError, metric_upgrade
from flytrack_host.calibration.synthetic import led_path
from flytrack_host.geometry.camera import Camera


def _cameras(n: int) -> list[Camera]:
    """Distortion-free cameras with square pixels, zero skew and the principal point at the centre."""
    rng = np.random.default_rng(5)
    cams = []
    for i in range(n):
        ang = 2 * np.pi * i / n + rng.uniform(-0.2, 0.2)
        pos = np.array([1.3 * np.cos(ang), 1.3 * np.sin(ang), 0.5 + rng.uniform(-0.6, 0.8)])
        cams.append(Camera.look_at(f"c{i}", pos, rng.normal(0, 0.05, 3) + [0, 0, 0.5], 1280, 1024,
                                   rng.uniform(650, 950)))
    return cams


def _views(cams: list[Camera], X: np.ndarray) -> np.ndarray:
    return np.stack([c.project(X) for c in cams])


def _angles(X: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Angles between the directions X[a]-X[b] of consecutive pairs of point pairs."""
    d = X[pairs[:, 0]] - X[pairs[:, 1]]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.arccos(np.clip(np.sum(d[:-1] * d[1:], axis=1), -1, 1))


def test_factorization_then_upgrade_is_exact_on_complete_noiseless_data() -> None:
    cams = _cameras(5)
    X = led_path(400, seed=3)
    uv = _views(cams, X)
    seen = np.ones(uv.shape[:2], dtype=bool)
    rec = projective_factorization(uv, seen, tol=1e-12, max_iter=2000)
    # Projective: every point reprojects onto its pixels (the cameras are right up to a 4x4 H).
    assert rec.rms_px < 1e-3, rec.rms_px
    assert rec.singular_ratio > 0.1
    # ... yet not metric: the projective points are not a similarity of the true ones.
    Xp = (rec.X[:3] / rec.X[3]).T
    pairs = np.random.default_rng(0).integers(0, len(X), (60, 2))
    assert np.max(np.abs(_angles(Xp, pairs) - _angles(X, pairs))) > 0.05
    mr = metric_upgrade(rec.P, rec.X, [(c.width, c.height) for c in cams], [800.0] * len(cams), seen)
    assert mr.in_front == 1.0
    # Metric: angles between known directions are preserved (a similarity of the truth) ...
    assert np.max(np.abs(_angles(mr.X, pairs) - _angles(X, pairs))) < 2e-3
    for P, truth in zip(mr.P, cams, strict=True):
        got = Camera.from_P(truth.name, P, truth.width, truth.height)
        # ... and the cameras have square pixels, zero skew, the true focal length and principal point.
        assert abs(got.K[1, 1] / got.K[0, 0] - 1) < 1e-3
        assert abs(got.K[0, 1]) < 1e-3 * got.K[0, 0]
        assert abs(got.K[0, 0] / truth.K[0, 0] - 1) < 3e-3
        assert np.allclose(got.K[:2, 2], truth.K[:2, 2], atol=1.0)
        # and each projects the metric points where the true camera projects the true ones.
        assert np.max(np.abs(got.project(mr.X) - truth.project(X))) < 1e-2


def test_factorization_fills_missing_views() -> None:
    cams = _cameras(6)
    X = led_path(600, seed=4)
    uv = _views(cams, X)
    rng = np.random.default_rng(1)
    seen = rng.random(uv.shape[:2]) >= 0.3
    keep = seen.sum(axis=0) >= 3
    uv, seen, X = uv[:, keep], seen[:, keep], X[keep]
    uv_missing = np.where(seen[..., None], uv, 1e6)  # what is not seen must not matter
    rec = projective_factorization(uv_missing, seen, tol=1e-12, max_iter=3000)
    assert rec.rms_px < 1e-2, rec.rms_px
    # The filled entries are the true views of the points the cameras did not see.
    assert np.max(np.abs(rec.project()[~seen] - uv[~seen])) < 0.1
    mr = metric_upgrade(rec.P, rec.X, [(c.width, c.height) for c in cams], [800.0] * len(cams), seen)
    pairs = rng.integers(0, len(X), (60, 2))
    assert np.max(np.abs(_angles(mr.X, pairs) - _angles(X, pairs))) < 2e-3


def test_factorization_and_upgrade_bad_input() -> None:
    cams = _cameras(3)
    X = led_path(50, seed=1)
    uv = _views(cams, X)
    seen = np.ones(uv.shape[:2], dtype=bool)
    with pytest.raises(FactorizationError, match="at least 2 cameras"):
        projective_factorization(uv[:1], seen[:1])
    lonely = seen.copy()
    lonely[1:, 0] = False
    with pytest.raises(FactorizationError, match="at least 2 cameras"):
        projective_factorization(uv, lonely)
    blind = seen.copy()
    blind[2, 3:] = False
    with pytest.raises(FactorizationError, match="at least 6 points"):
        projective_factorization(uv, blind)
    rec = projective_factorization(uv[:2], seen[:2])
    with pytest.raises(MetricUpgradeError, match="at least 3 cameras"):
        metric_upgrade(rec.P, rec.X, [(1280, 1024)] * 2, [800.0] * 2)


def test_report_plot_has_equal_3d_axes() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from flytrack_host.calibration.report import set_equal_3d

    ax = plt.figure().add_subplot(projection="3d")
    pts = np.array([[0.0, 0.0, 0.0], [4.0, 1.0, 0.5], [np.nan, 0.0, 0.0]])
    set_equal_3d(ax, pts)
    spans = [np.ptp(lim) for lim in (ax.get_xlim(), ax.get_ylim(), ax.get_zlim())]
    assert np.allclose(spans, spans[0]) and spans[0] >= 4.0
    assert np.allclose(ax.get_box_aspect() / ax.get_box_aspect()[0], 1.0)
    plt.close("all")
