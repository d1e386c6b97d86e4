"""Each equation's module on known inputs: line distances (eq. 4.2, C kernel == NumPy), Plucker distance,
the iterated EKF, the smoother (eqs 4.3-4.4), curvature (eq. 5.2) and the fast-start detector, eq. 4.1."""

from __future__ import annotations

import numpy as np
import pytest

from flytrack_host.fish import fit as F
from flytrack_host.fish.association import associate
from flytrack_host.fish.curvature import curvature, detect_fast_starts, signed_curvature, total_curvature
from flytrack_host.fish.iekf import iekf_update
from flytrack_host.fish.kernel import line_distances_c
from flytrack_host.fish.school import make_school
from flytrack_host.fish.shape import ShapeModel, default_model, make_state, p_for_length
from flytrack_host.fish.silhouette import Blob
from flytrack_host.fish.smoother import SmootherConfig, TrackFilter


def _random_lines(rng: np.random.Generator, n: int) -> F.LineSet:
    o = rng.normal(0, 20, (n, 3))
    v = rng.normal(0, 1, (n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return F.LineSet(o - v * np.sum(o * v, axis=1, keepdims=True), v)


def test_c_kernel_matches_numpy() -> None:
    if line_distances_c(np.zeros((1, 2, 8, 3)), np.zeros((1, 3)), np.array([[1.0, 0, 0]])) is None:
        pytest.skip("fish kernel not built (make build)")
    rng = np.random.default_rng(0)
    m = F.model_in_mm(default_model())
    X = make_state(rng.normal(0, 2, (6, 3)), rng.normal(0, 1, (6, 3)), p_for_length(rng.normal(0, 0.2, (6, 3)), 50))
    S = m.surface(X)
    ls = _random_lines(rng, 300)
    a = F.line_distances_numpy(S, ls)
    b = F.line_distances(S, ls)
    assert np.max(np.abs(a - b)) < 1e-9


def test_line_distance_to_a_cylinder_is_exact_and_plucker_agrees() -> None:
    # a straight "fish" of constant circular section, radius 2 mm, along x; lines parallel to z at offset y
    n = 9
    model = ShapeModel(np.linspace(-0.1, 1.0, n), np.full(n, 2.0), np.full(n, 2.0), np.zeros(n), 50.0, 16)
    X = make_state([0.0, 0.0, 0.0], [1.0, 0, 0], [50.0, 0, 0, 0, 0])
    S = model.surface(X)
    ys = np.array([2.0, 2.5, 3.0, 5.0])
    o = np.stack([np.full(4, -20.0), ys, np.zeros(4)], axis=1)  # x = -20 mm: mid-body
    v = np.tile([0.0, 0.0, 1.0], (4, 1))
    ls = F.LineSet(o - v * np.sum(o * v, axis=1, keepdims=True), v)
    for use_c in (False, True):
        D = F.line_distances(S, ls, use_c=use_c)[0]
        assert np.allclose(D, ys - 2.0, atol=0.02)
    # the Plucker form ||S x l_v - l_m|| gives the same as the foot form for every surface point
    P = S.reshape(-1, 3)
    d_pl = np.linalg.norm(np.cross(P[:, None], ls.v[None]) - ls.moment[None], axis=2)
    ds = P[:, None] - ls.p[None]
    d_ft = np.sqrt(np.sum(ds**2, axis=2) - np.sum(ds * ls.v[None], axis=2) ** 2)
    assert np.allclose(d_pl, d_ft, atol=1e-9)


def test_iekf_converges_to_the_map_estimate() -> None:
    # 2D position from three range measurements (strongly nonlinear from a poor prior)
    beacons = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    truth = np.array([3.0, 4.0])

    def h(X: np.ndarray) -> np.ndarray:
        return np.linalg.norm(X[:, None, :] - beacons[None], axis=2)

    z = h(truth[None])[0]
    R = np.eye(3) * 1e-6
    res = iekf_update(h, z, R, np.array([8.0, 8.0]), np.eye(2) * 100.0, max_iter=30)
    assert res.converged
    assert np.allclose(res.x, truth, atol=1e-3)
    one = iekf_update(h, z, R, np.array([8.0, 8.0]), np.eye(2) * 100.0, max_iter=1)
    assert np.linalg.norm(one.x - truth) > 10 * np.linalg.norm(res.x - truth)  # iterating is what gets there
    assert np.all(np.linalg.eigvalsh(res.P) < 1e-4)


def test_smoother_bend_decays_at_lambda_and_rts_beats_the_filter() -> None:
    f = TrackFilter(1 / 250, SmootherConfig())
    X0 = make_state([0, 0, 0.2], [1, 0, 0], [0.05, 0.001, 0.01, 0.0, 0.0])[0]
    f.start(X0)
    for _ in range(250):  # one second with no measurement: eq. 4.4's mean decays as exp(-lambda t)
        f.predict()
        f.update(None)
    assert f.x[11] == pytest.approx(0.01 * np.exp(-5.0), rel=1e-6)
    assert f.x[9] == pytest.approx(0.05)  # p1 is a random walk: no drift
    # noisy measurements of a constant-velocity fish: the RTS pass is closer to the truth than the filter
    rng = np.random.default_rng(3)
    g = TrackFilter(1 / 250, SmootherConfig())
    g.start(X0)
    truth = []
    for k in range(1, 200):
        Xt = X0.copy()
        Xt[0] = 0.1 * k / 250
        truth.append(Xt)
        g.predict()
        g.update(Xt + np.concatenate([rng.normal(0, 0.0004, 3), np.zeros(3), rng.normal(0, 0.0005, 5)]))
    truth = np.array(truth)
    fx, _ = g.filtered()
    sx, sP = g.smoothed()
    e_f = np.abs(fx[1:, 0] - truth[:, 0]).mean()
    e_s = np.abs(sx[1:, 0] - truth[:, 0]).mean()
    assert e_s < 0.8 * e_f
    assert sP.shape == (200, 11, 11)


def test_curvature_of_known_shapes() -> None:
    assert np.allclose(curvature(np.array([0.05, 0, 0, 0, 0])), 0.0)
    # f1 = -p1 s, f2 = p3 s^2: at s = 0 kappa = 2 p3 / p1^2 exactly
    p = np.array([0.05, 0.0, 0.01, 0.0, 0.0])
    assert curvature(p, np.array([0.0]))[0] == pytest.approx(2 * 0.01 / 0.05**2)
    # an S shape changes sign along the body, a C does not
    s_shape = p_for_length(np.array([[0.7, -0.52, 0.0]]), 0.05)[0]
    c_shape = p_for_length(np.array([[0.55, 0.0, -0.05]]), 0.05)[0]
    ks, kc = signed_curvature(s_shape), signed_curvature(c_shape)
    assert ks.min() < 0 < ks.max()
    assert kc.max() < 0 or kc.min() > 0  # one sign along the whole body
    # total curvature of a parabola-bent fish approaches the turning angle / length scale
    assert total_curvature(c_shape) > 10.0


def test_fast_starts_detected_at_their_onsets_in_the_synthetic_school() -> None:
    school = make_school(2, 200, cross_frame=60)
    found = {}
    for f in range(2):
        for d in detect_fast_starts(school.truth[:, f, 6:], school.fps, school.length, f):
            found[(f, d.kind)] = d.onset
    for ev in school.events:
        if ev.kind in ("C-start", "S-start"):
            assert abs(found[(ev.fish, ev.kind)] - ev.frame) <= 2
    assert len(found) == 2  # no false starts from the tail beat or the coasting turns


def test_association_picks_the_silhouette_along_the_midline() -> None:
    # two parallel silhouettes 6 px apart; midlines over each; a third target far away matches none
    def blob(y0: int) -> Blob:
        xx, yy = np.meshgrid(np.arange(10, 60), np.arange(y0, y0 + 4))
        pix = np.stack([xx.ravel(), yy.ravel()], 1).astype(float)
        return Blob(0, len(pix), (10, y0, 50, 4), pix, pix)

    blobs = [blob(10), blob(20)]
    mid = lambda y: np.stack([np.linspace(12, 58, 15), np.full(15, y)], 1)  # noqa: E731
    assert associate([mid(21.5), mid(11.5), mid(200.0)], blobs, gate_px=12.0) == [1, 0, -1]
    # two targets on one silhouette (an occlusion) both take it
    assert associate([mid(11.0), mid(12.5)], blobs, 12.0) == [0, 0]
