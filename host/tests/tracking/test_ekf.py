"""The EKF maths: Braid's process noise, prediction, and the Joseph-form update's guarantees."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flytrack_host.tracking.ekf import (
    cv_process_noise,
    cv_transition,
    is_symmetric_positive_definite,
    joseph_covariance,
    joseph_update,
    predict,
)


def test_process_noise_is_braids_matrix() -> None:
    dt, q = 0.01, 0.1
    Q = cv_process_noise(dt, q)
    I3 = np.eye(3)
    expected = q * np.block([[dt**3 / 3 * I3, dt**2 / 2 * I3], [dt**2 / 2 * I3, dt * I3]])
    np.testing.assert_allclose(Q, expected, rtol=1e-15)
    assert is_symmetric_positive_definite(Q)


def test_predict_moves_position_by_velocity_and_grows_covariance() -> None:
    x = np.array([[0.1, 0.2, 0.3, 1.0, -2.0, 0.5]])
    P = np.eye(6)[None] * 1e-4
    dt = 0.02
    xp, Pp = predict(x, P, cv_transition(dt), cv_process_noise(dt, 0.1))
    np.testing.assert_allclose(xp[0, :3], [0.12, 0.16, 0.31])
    np.testing.assert_allclose(xp[0, 3:], x[0, 3:])
    assert np.all(np.linalg.eigvalsh(Pp[0] - P[0]) > 0)


def test_joseph_update_equals_kalman_on_a_linear_problem() -> None:
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    P = (A @ A.T + np.eye(6))[None]
    x = rng.normal(size=(1, 6))
    H = rng.normal(size=(1, 4, 6))
    R = np.eye(4) * 0.3
    z = rng.normal(size=(1, 4))
    xp, Pp, ok = joseph_update(x, P, z, (H @ x[..., None])[..., 0], H, R)
    S = H[0] @ P[0] @ H[0].T + R
    K = P[0] @ H[0].T @ np.linalg.inv(S)
    np.testing.assert_allclose(xp[0], x[0] + K @ (z[0] - H[0] @ x[0]), rtol=1e-10)
    np.testing.assert_allclose(Pp[0], (np.eye(6) - K @ H[0]) @ P[0], rtol=1e-8, atol=1e-12)
    assert ok.all()


def test_zero_rows_carry_no_information() -> None:
    """Padding a target's observation with zero Jacobian rows (zero innovation) changes nothing."""
    rng = np.random.default_rng(1)
    A = rng.normal(size=(6, 6))
    P = (A @ A.T + np.eye(6))[None]
    x = rng.normal(size=(1, 6))
    H = rng.normal(size=(1, 2, 6))
    z = rng.normal(size=(1, 2))
    hx = (H @ x[..., None])[..., 0]
    x1, P1, _ = joseph_update(x, P, z, hx, H, np.eye(2))
    Hp = np.concatenate([H, np.zeros((1, 2, 6))], axis=1)
    x2, P2, _ = joseph_update(x, P, np.concatenate([z, [[5.0, 7.0]]], 1), np.concatenate([hx, [[5.0, 7.0]]], 1),
                              Hp, np.eye(4))
    np.testing.assert_allclose(x1, x2, rtol=1e-12)
    np.testing.assert_allclose(P1, P2, rtol=1e-10, atol=1e-14)


@st.composite
def absurd_cases(draw: st.DrawFn) -> tuple:
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    T = draw(st.integers(1, 4))
    m = 2 * draw(st.integers(1, 6))
    # Covariances from tiny to huge, badly conditioned.
    scales = 10.0 ** rng.uniform(-9, 3, size=(T, 6))
    Q, _ = np.linalg.qr(rng.normal(size=(T, 6, 6)))
    P = Q @ (scales[..., None] * np.swapaxes(Q, 1, 2))
    P = 0.5 * (P + np.swapaxes(P, 1, 2))
    # Jacobians as wild as a target grazing a camera's image plane gives, observations absurd.
    H = rng.normal(size=(T, m, 6)) * 10.0 ** rng.uniform(-3, 9, size=(T, m, 1))
    H[..., 3:] = 0.0
    z = rng.normal(size=(T, m)) * 10.0 ** draw(st.sampled_from([0, 6, 12, 30]))
    r = 10.0 ** draw(st.floats(-6, 2))
    return rng.normal(size=(T, 6)), P, z, H, r


# make mutation lowers the examples (FLYTRACK_HYPOTHESIS_EXAMPLES) to test many mutants in its time.
@settings(max_examples=int(os.environ.get("FLYTRACK_HYPOTHESIS_EXAMPLES", "200")), deadline=None)
@given(absurd_cases())
def test_joseph_posterior_stays_symmetric_positive_definite(case: tuple) -> None:
    x, P, z, H, r = case
    m = z.shape[1]
    hx = np.zeros_like(z)
    xp, Pp, ok = joseph_update(x, P, z, hx, H, r * np.eye(m))
    for k in range(P.shape[0]):
        assert is_symmetric_positive_definite(Pp[k]), (k, np.linalg.eigvalsh(Pp[k]))
        if not ok[k]:  # a refused update keeps the prior untouched
            np.testing.assert_array_equal(Pp[k], P[k])
            np.testing.assert_array_equal(xp[k], x[k])
    # Symmetric exactly, as the update symmetrises.
    np.testing.assert_array_equal(Pp, np.swapaxes(Pp, 1, 2))


def test_nan_observation_is_refused_and_prior_kept() -> None:
    x = np.zeros((2, 6))
    P = np.broadcast_to(np.eye(6) * 1e-2, (2, 6, 6)).copy()
    H = np.zeros((2, 2, 6))
    H[:, 0, 0] = H[:, 1, 1] = 100.0
    z = np.array([[np.nan, 1.0], [1.0, 1.0]])
    xp, Pp, ok = joseph_update(x, P, z, np.zeros((2, 2)), H, np.eye(2))
    assert ok.tolist() == [False, True]
    np.testing.assert_array_equal(xp[0], x[0])
    np.testing.assert_array_equal(Pp[0], P[0])
    assert xp[1, 0] > 0


def _precise_correlated_update(r: float, gap: float) -> tuple:
    """A well-posed update that the short form cannot be trusted with, by construction: the prior's x and
    y are correlated to 1 - gap (an ill-conditioned S = H P H^T + R), both seen through a steep Jacobian
    (1000 px/m) with a precise measurement (R = r px^2 I). The posterior variance of x and y is then about
    r / 1e6 m^2, orders of magnitude below the prior's 1e-2: most of the prior cancels in the update."""
    P = np.diag([1e-2, 1e-2, 1e-2, 1.0, 1.0, 1.0])
    P[0, 1] = P[1, 0] = 1e-2 * (1.0 - gap)
    H = np.zeros((2, 6))
    H[0, 0] = H[1, 1] = 1e3
    return P[None], H[None], r * np.eye(2)


# (R, 1 - correlation): posterior x, y variance 1e-12 to 1e-14 m^2, 1e-10 to 1e-12 of the prior's;
# cond(S) up to 2e6.
_PRECISE_CASES = [(1e-6, 1e-2), (1e-6, 1e-6), (1e-7, 1e-5), (1e-8, 1e-4), (1e-8, 1e-6)]


@pytest.mark.parametrize(("r", "gap"), _PRECISE_CASES)
def test_joseph_form_keeps_precise_updates_the_short_form_would_lose(r: float, gap: float) -> None:
    """The short form (I - K H) P is only right for the exactly optimal gain; the Joseph form is positive
    definite for any gain. A gain off by a relative 1e-6 (far above what round-off leaves in these solves,
    about cond(S) x 1e-16 <= 2e-10, so the case holds on every BLAS kernel) makes the short form's x
    variance P+ - 1e-6 K H P ~ -1e-8 m^2, negative by a hundred times the true one or more; the Joseph form's
    stays positive."""
    P, H, R = _precise_correlated_update(r, gap)
    x, z = np.zeros((1, 6)), np.array([[1e-3, -2e-3]])
    xp, Pp, ok = joseph_update(x, P, z, np.zeros_like(z), H, R)
    assert ok.all(), "a well-posed update was refused"
    assert is_symmetric_positive_definite(Pp[0])
    assert not np.array_equal(xp[0], x[0])
    assert Pp[0, 0, 0] < 10.0 * r / 1e6 and Pp[0, 1, 1] < 10.0 * r / 1e6  # the measurement was taken in
    PHt = P[0] @ H[0].T
    K = np.linalg.solve(H[0] @ PHt + R, PHt.T).T  # the gain as ekf.py computes it
    K_off = K * (1.0 + 1e-6)
    joseph = joseph_covariance(P, K_off[None], H, R)[0]
    assert is_symmetric_positive_definite(joseph)
    short = (np.eye(6) - K_off @ H[0]) @ P[0]
    short = 0.5 * (short + short.T)
    assert short[0, 0] < -1e2 * Pp[0, 0, 0]  # a negative variance: what the Joseph form is there to avoid
    assert not is_symmetric_positive_definite(short)


def test_ordinary_updates_are_taken_and_shrink_the_covariance() -> None:
    """Updates that are fine must be taken: a filter that refused every update would keep the prior."""
    rng = np.random.default_rng(5)
    T = 8
    A = rng.normal(size=(T, 6, 6))
    P = A @ np.swapaxes(A, 1, 2) * 1e-3 + np.eye(6) * 1e-4
    x = rng.normal(size=(T, 6))
    H = rng.normal(size=(T, 4, 6)) * 500.0
    H[..., 3:] = 0.0
    z = rng.normal(size=(T, 4))
    xp, Pp, ok = joseph_update(x, P, z, np.zeros_like(z), H, np.eye(4))
    assert ok.shape == (T,) and ok.all()
    for k in range(T):
        assert np.trace(Pp[k, :3, :3]) < 0.1 * np.trace(P[k, :3, :3])
        assert not np.allclose(xp[k], x[k])


def test_transition_and_process_noise_are_cached_and_read_only() -> None:
    """The matrices are shared between calls (one per dt and scale): a caller must not be able to
    change them for everyone."""
    F, Q = cv_transition(0.01), cv_process_noise(0.01, 0.1)
    assert cv_transition(0.01) is F and cv_process_noise(0.01, 0.1) is Q
    for M in (F, Q):
        with pytest.raises(ValueError, match="read-only"):
            M[0, 0] = 2.0


def test_a_singular_innovation_covariance_refuses_that_target_only() -> None:
    """One target of a batch with S singular (no information, R = 0 on its rows): numpy's batched
    solve fails, the per-target fallback refuses just that one and updates the others."""
    T, m = 3, 4
    x = np.arange(T * 6, dtype=float).reshape(T, 6) * 0.01
    P = np.broadcast_to(np.eye(6) * 1e-2, (T, 6, 6)).copy()
    H = np.zeros((T, m, 6))
    for k in (0, 2):
        H[k, :3, :3] = np.eye(3) * 100.0
        H[k, 3, 0] = 50.0
    R = np.broadcast_to(np.eye(m), (T, m, m)).copy()
    R[1] = 0.0  # target 1: H = 0 and R = 0, so S = 0
    z = np.ones((T, m))
    xp, Pp, ok = joseph_update(x, P, z, np.zeros((T, m)), H, R)
    assert ok.shape == (T,) and ok.tolist() == [True, False, True]
    np.testing.assert_array_equal(xp[1], x[1])
    np.testing.assert_array_equal(Pp[1], P[1])
    for k in (0, 2):
        S = H[k] @ P[k] @ H[k].T + R[k]
        K = P[k] @ H[k].T @ np.linalg.inv(S)
        np.testing.assert_allclose(xp[k], x[k] + K @ z[k], rtol=1e-9, atol=1e-12)


def test_symmetric_positive_definite_check() -> None:
    A = np.diag([1.0, 2, 3, 4, 5, 6]) * 1e3
    assert is_symmetric_positive_definite(A)
    B = A.copy()
    B[0, 1] = 1e-7  # asymmetry 1.7e-11 of the scale (the largest entry, 6e3): within rtol 1e-9
    assert is_symmetric_positive_definite(B)
    B[0, 1] = 1e-5  # 1.7e-9 of the scale: not symmetric
    assert not is_symmetric_positive_definite(B)
    C = A.copy()
    C[2, 2] = np.nan
    assert not is_symmetric_positive_definite(C)
    D = A.copy()
    D[3, 3] = -1.0
    assert not is_symmetric_positive_definite(D)
