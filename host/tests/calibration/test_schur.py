"""The Schur-complement Levenberg-Marquardt bundle adjustment (calibration/schur.py): its analytic
Jacobian against finite differences, its minimum against scipy's trust-region solver on the same
problem, robust losses, and bad arguments."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flytrack_host.calibration.bundle import bundle_adjust
from flytrack_host.calibration.evaluate import centre_error
from flytrack_host.calibration.schur import levenberg_marquardt, project_jacobian
from flytrack_host.calibration.synthetic import synthetic_rig
from flytrack_host.geometry.camera import Camera


def _random_problem(nd: int, seed: int = 0):  # noqa: ANN202
    rng = np.random.default_rng(seed)
    nc, npnt, nobs = 3, 30, 80
    R = Rotation.random(nc, random_state=seed).as_matrix()
    cp = np.zeros((nc, 9 + nd))
    cp[:, 6] = [800.0, 1200.0, 950.0]
    cp[:, 7:9] = [[320.0, 240.0], [640.0, 512.0], [300.0, 250.0]]
    cp[:, 9:] = np.array([-0.2, 0.05, 1e-3, -2e-3])[:nd]
    aspect = np.array([1.0, 1.01, 0.98])
    fixed = np.zeros((nc, 5))
    fixed[:, 4] = 0.01  # k3, held by every model: still in the projection and its derivatives
    cam = rng.integers(0, nc, nobs)
    pt = rng.integers(0, npnt, nobs)
    # Points 3-5 m in front of each camera that sees them (the projection divides by depth).
    X = np.zeros((npnt, 3))
    for p in range(npnt):
        c = cam[pt == p][0] if np.any(pt == p) else 0
        Xc = np.array([*rng.uniform(-0.6, 0.6, 2), 1.0]) * rng.uniform(3, 5)
        X[p] = R[c].T @ (Xc - cp[c, 3:6])
    front = np.einsum("nij,nj->ni", R[cam], X[pt])[:, 2] + cp[cam, 5] > 1.0
    return R, cp, aspect, fixed, X, cam[front], pt[front]


@pytest.mark.parametrize("nd", [0, 1, 2, 4])
def test_analytic_jacobian_matches_central_differences(nd: int) -> None:
    R, cp, aspect, fixed, X, cam, pt = _random_problem(nd)
    _, Jc, Jp = project_jacobian(R, cp, aspect, fixed, X, cam, pt, nd)
    assert Jc is not None and Jp is not None
    h = 1e-6
    worst = 0.0
    for k in range(9 + nd):
        d = np.zeros_like(cp)
        d[:, k] = h
        if k < 3:  # a rotation increment on the left: R <- exp([w]x) R
            plus = project_jacobian(Rotation.from_rotvec(d[:, :3]).as_matrix() @ R, cp, aspect, fixed, X, cam, pt,
                                    nd, False)[0]
            minus = project_jacobian(Rotation.from_rotvec(-d[:, :3]).as_matrix() @ R, cp, aspect, fixed, X, cam, pt,
                                     nd, False)[0]
        else:
            plus = project_jacobian(R, cp + d, aspect, fixed, X, cam, pt, nd, False)[0]
            minus = project_jacobian(R, cp - d, aspect, fixed, X, cam, pt, nd, False)[0]
        num = (plus - minus) / (2 * h)
        worst = max(worst, float(np.abs(num - Jc[:, :, k]).max() / max(1.0, np.abs(num).max())))
    for k in range(3):
        d = np.zeros_like(X)
        d[:, k] = h
        num = (project_jacobian(R, cp, aspect, fixed, X + d, cam, pt, nd, False)[0]
               - project_jacobian(R, cp, aspect, fixed, X - d, cam, pt, nd, False)[0]) / (2 * h)
        worst = max(worst, float(np.abs(num - Jp[:, :, k]).max() / max(1.0, np.abs(num).max())))
    assert worst < 1e-6  # measured ~2e-8 (the differences' own rounding)


def _perturbed_start(seed: int):  # noqa: ANN202
    rig = synthetic_rig(4, n_points=400, noise_px=0.5, outliers=0.0, seed=seed)
    rng = np.random.default_rng(seed)
    cams = list(rig.cameras.values())
    start = []
    for i, c in enumerate(cams):
        if i == 0:  # the gauge camera keeps its pose
            start.append(Camera(c.name, c.width, c.height, c.K * [[1.03], [1.03], [1]], c.R, c.t, c.dist * 0))
            continue
        dR = Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix()
        start.append(Camera(c.name, c.width, c.height, c.K * [[1.03], [1.03], [1]], dR @ c.R,
                            c.t + rng.normal(0, 0.02, 3), c.dist * 0))
    frames, inv = rig.obs.point_index()
    # Frames seen by two cameras or more, as self-calibration keeps (one view leaves a point's depth free).
    keep = np.bincount(inv, minlength=len(frames))[inv] >= 2
    kept, inv = np.unique(inv[keep], return_inverse=True)
    rig.obs = rig.obs.subset(keep)
    rig.outlier = rig.outlier[keep]
    X0 = rig.points[frames[kept]] + rng.normal(0, 0.01, (len(kept), 3))
    return rig, start, X0, inv


def test_schur_reaches_the_minimum_trf_reaches() -> None:
    """Same problem, same start, tight tolerances: both solvers end at the same cost and cameras."""
    rig, start, X0, inv = _perturbed_start(3)
    common = dict(distortion="k1k2", loss="linear", max_nfev=200, ftol=1e-12, gauge=(0, 1))
    schur = bundle_adjust(start, X0, rig.obs.cam, inv, rig.obs.uv, solver="schur", **common)
    trf = bundle_adjust(start, X0, rig.obs.cam, inv, rig.obs.uv, solver="trf", lsmr_tol=1e-12, **common)
    assert schur.success
    rms = np.sqrt(np.mean(np.sum(schur.residuals**2, axis=1)))
    print(f"\nschur cost {schur.cost:.6f} ({schur.nfev} evaluations), trf cost {trf.cost:.6f} ({trf.nfev}); "
          f"rms {rms:.4f} px")
    assert schur.cost <= trf.cost * (1 + 1e-7)
    assert abs(schur.cost - trf.cost) < 1e-5 * trf.cost
    centres = {c.name: c for c in schur.cameras}
    other = {c.name: c for c in trf.cameras}
    assert centre_error(centres, other) < 1e-4  # 0.1 mm between the two solvers' camera centres
    for a, b in zip(schur.cameras, trf.cameras, strict=True):
        assert a.K[0, 0] == pytest.approx(b.K[0, 0], rel=1e-5)
        assert a.dist[:2] == pytest.approx(b.dist[:2], abs=1e-4)
    # 0.5 px of noise (a point's 2D rms), less what the fit absorbs.
    assert 0.47 < rms < 0.51  # measured 0.4925


def test_robust_losses_reach_trfs_minimum_and_resist_outliers() -> None:
    """5 % of the detections 40 px off: soft_l1 (by reweighting) ends where scipy's trf ends on the same
    problem; it and huber end far closer to the true cameras than least squares."""
    rig, start, X0, inv = _perturbed_start(5)
    uv = rig.obs.uv.copy()
    rng = np.random.default_rng(5)
    bad = rng.random(len(uv)) < 0.05
    uv[bad] += rng.uniform(-40, 40, (int(bad.sum()), 2))
    kw = dict(distortion="k1k2", max_nfev=200, ftol=1e-10, gauge=(0, 1))
    truth = rig.cameras

    def err(res: object) -> float:
        return centre_error({c.name: c for c in res.cameras}, truth)  # type: ignore[attr-defined]

    soft = bundle_adjust(start, X0, rig.obs.cam, inv, uv, loss="soft_l1", f_scale=1.0, **kw)
    trf = bundle_adjust(start, X0, rig.obs.cam, inv, uv, loss="soft_l1", f_scale=1.0, solver="trf", lsmr_tol=1e-10,
                        **kw)
    huber = bundle_adjust(start, X0, rig.obs.cam, inv, uv, loss="huber", f_scale=1.0, **kw)
    plain = bundle_adjust(start, X0, rig.obs.cam, inv, uv, loss="linear", **kw)
    print(f"\n5 % outliers of +-40 px: soft_l1 cost {soft.cost:.3f} (trf {trf.cost:.3f}); centre error soft_l1 "
          f"{err(soft) * 1e3:.2f} mm (trf {err(trf) * 1e3:.2f}), huber {err(huber) * 1e3:.2f}, least squares "
          f"{err(plain) * 1e3:.2f}")
    # Measured: soft_l1 2363.644 vs trf 2363.644, centres 23.25 / 23.18 mm; huber 22.8 mm; least squares 55.9 mm.
    assert soft.cost <= trf.cost * (1 + 1e-6)
    assert abs(err(soft) - err(trf)) < 0.5e-3
    assert err(soft) < 0.5 * err(plain) and err(huber) < 0.5 * err(plain)


def test_bad_arguments_are_clear_errors() -> None:
    rig, start, X0, inv = _perturbed_start(3)
    with pytest.raises(ValueError, match="solver"):
        bundle_adjust(start, X0, rig.obs.cam, inv, rig.obs.uv, solver="magic")
    with pytest.raises(ValueError, match="loss"):
        bundle_adjust(start, X0, rig.obs.cam, inv, rig.obs.uv, loss="cauchy")
    uv = rig.obs.uv.copy()
    uv[7, 0] = np.nan
    with pytest.raises(ValueError, match="1 of .* residuals are not finite"):
        bundle_adjust(start, X0, rig.obs.cam, inv, uv)
    R, cp, aspect, fixed, X, cam, pt = _random_problem(2)
    with pytest.raises(ValueError, match="loss"):
        levenberg_marquardt(R, cp, aspect, fixed, X, cam, pt, np.zeros((len(cam), 2)), 2,
                            np.ones(cp.shape, dtype=bool), loss="cauchy")
