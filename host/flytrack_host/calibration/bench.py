"""Benchmark: FlyTrack's self-calibration vs aniposelib's bundle adjustment, same data, same start.

For each synthetic rig (cameras around a 1 m arena, 3000 LED frames, 0.5 px noise, 30 % missing views,
2 % gross outliers, radial distortion) both bundle adjustments start from FlyTrack's initial cameras
and get the same observations (those that survived the pairwise RANSAC). Both results are judged the
same way: mean reprojection error of the true inliers (each frame triangulated and refined with the
result's cameras), against the true cameras' own error (the noise floor), and the largest camera-centre
error after a similarity onto the true centres.

FlyTrack starts from its default initialisation (projective factorisation + Euclidean upgrade) or, with
--init pairwise/both, from the essential-matrix + PnP one; the table and JSON say which ("init") and how far
the start's camera centres were from the truth ("init_centre_err_m", before any bundle adjustment).

Two camera models (--model, default both, one row each):
- "full": k1 and k2 radial distortion and principal points up to 15 px off centre. aniposelib's camera
  cannot fit these (one focal length, k1 only, the principal point held where it starts).
- "anipose": within aniposelib's model: k2 = 0 and centred principal points. Both are judged the same.

Bundle-adjustment times are CPU seconds of this process (time.process_time) with one BLAS/OpenMP thread
on each side: OMP_NUM_THREADS, OPENBLAS_NUM_THREADS, MKL_NUM_THREADS and NUMBA_NUM_THREADS are set to 1
before NumPy loads (mk/calibration.mk sets them too, since `python -m` imports the package first).

Run: python -m flytrack_host.calibration.bench [--cameras 4 6 11] [--init factorization|pairwise|both]
     [--model full|anipose|both] [--json PATH]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from flytrack_host.calibration.evaluate import centre_error, reprojection_error  # noqa: E402
from flytrack_host.calibration.selfcal import self_calibrate  # noqa: E402
from flytrack_host.calibration.synthetic import synthetic_rig  # noqa: E402
from flytrack_host.geometry.camera import Camera  # noqa: E402

MODELS = {"full": {}, "anipose": {"dist_k2": 0.0, "principal_offset_px": 0.0}}


def _anipose(res: object, obs: object) -> tuple[dict[str, Camera], float]:
    import cv2
    from aniposelib.cameras import Camera as ACam
    from aniposelib.cameras import CameraGroup

    names = obs.camera_names  # type: ignore[attr-defined]
    init = res.initial_cameras  # type: ignore[attr-defined]
    acams = []
    for n in names:
        c = init[n]
        rvec, _ = cv2.Rodrigues(c.R)
        acams.append(ACam(name=n, size=(c.width, c.height), matrix=c.K.copy(), dist=c.dist.copy(),
                          rvec=rvec.ravel(), tvec=c.t.copy()))
    group = CameraGroup(acams)
    frames, inv = obs.point_index()  # type: ignore[attr-defined]
    p2ds = np.full((len(names), len(frames), 2), np.nan)
    m = res.initial_obs_mask  # type: ignore[attr-defined]
    p2ds[obs.cam[m], inv[m]] = obs.uv[m]  # type: ignore[attr-defined]
    t = time.process_time()
    group.bundle_adjust_iter(p2ds, verbose=False)
    dt = time.process_time() - t
    out = {}
    for n, a in zip(names, group.cameras, strict=True):
        R, _ = cv2.Rodrigues(np.asarray(a.get_rotation(), dtype=float))
        out[n] = Camera(name=n, width=init[n].width, height=init[n].height, K=np.asarray(a.get_camera_matrix()),
                        R=R, t=np.asarray(a.get_translation(), dtype=float).ravel(),
                        dist=np.asarray(a.get_distortions(), dtype=float).ravel()[:5])
    return out, dt


def run(n_cameras: int, seed: int = 0, init: str = "factorization", model: str = "full") -> dict[str, float | str]:
    rig = synthetic_rig(n_cameras, n_points=3000, seed=seed, **MODELS[model])
    focal = {k: c.K[0, 0] * 1.1 for k, c in rig.cameras.items()}  # a 10 % wrong focal-length guess
    t = time.perf_counter()
    res = self_calibrate(rig.obs, focal_px=focal, seed=seed, init=init)
    t_ours = time.perf_counter() - t
    truth = ~rig.outlier
    fig: dict[str, float | str] = {
        "cameras": n_cameras,
        "model": model,
        "init": res.init_method,  # which initialisation started the bundle adjustment
        "init_centre_err_m": centre_error(res.initial_cameras, rig.cameras),  # of the start, before any BA
        "flytrack_init_s": res.timings["init_s"],
        "observations": len(rig.obs.frame),
        "noise_floor_px": reprojection_error(rig.cameras, rig.obs, truth),
        "flytrack_px": reprojection_error(res.cameras, rig.obs, truth),
        "flytrack_centre_err_m": centre_error(res.cameras, rig.cameras),
        "flytrack_total_s": t_ours,
        "flytrack_bundle_s": res.timings["bundle_s"],
        "flytrack_bundle_cpu_s": res.timings["bundle_cpu_s"],
    }
    try:
        acams, t_ani = _anipose(res, rig.obs)
        fig["aniposelib_px"] = reprojection_error(acams, rig.obs, truth)
        fig["aniposelib_centre_err_m"] = centre_error(acams, rig.cameras)
        fig["aniposelib_bundle_cpu_s"] = t_ani
    except ImportError as exc:
        raise SystemExit(f"aniposelib is not importable ({exc}); run `make bench-calib`, which installs it.") from None
    return fig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cameras", type=int, nargs="+", default=[4, 6, 11])
    ap.add_argument("--init", choices=["factorization", "pairwise", "both"], default="factorization",
                    help="initialisation of FlyTrack's self-calibration (both: one row each)")
    ap.add_argument("--model", choices=["full", "anipose", "both"], default="both",
                    help="synthetic camera model: full (k2, off-centre principal points), anipose (within "
                         "aniposelib's model), both (one row each)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    inits = ["factorization", "pairwise"] if args.init == "both" else [args.init]
    models = ["full", "anipose"] if args.model == "both" else [args.model]
    rows = []
    print(f"BLAS/OpenMP threads: OMP {os.environ.get('OMP_NUM_THREADS')}, OPENBLAS "
          f"{os.environ.get('OPENBLAS_NUM_THREADS')}; BA times in CPU seconds (time.process_time)")
    print(f"{'cams':>4} {'model':>7} {'init':>13} {'init ctr mm':>11} {'obs':>6} {'floor px':>9} {'ours px':>8} "
          f"{'anipose px':>10} {'ours ctr mm':>11} {'anip ctr mm':>11} {'ours BA cpu s':>13} {'anip BA cpu s':>13} "
          f"{'speed':>6}")
    for model in models:
        for n in args.cameras:
            for init in inits:
                f = run(n, init=init, model=model)
                rows.append(f)
                print(f"{n:>4d} {model:>7} {f['init']:>13} {1000 * f['init_centre_err_m']:>11.1f} "
                      f"{f['observations']:>6.0f} {f['noise_floor_px']:>9.3f} {f['flytrack_px']:>8.3f} "
                      f"{f['aniposelib_px']:>10.3f} {1000 * f['flytrack_centre_err_m']:>11.1f} "
                      f"{1000 * f['aniposelib_centre_err_m']:>11.1f} {f['flytrack_bundle_cpu_s']:>13.2f} "
                      f"{f['aniposelib_bundle_cpu_s']:>13.2f} "
                      f"{f['aniposelib_bundle_cpu_s'] / f['flytrack_bundle_cpu_s']:>5.1f}x", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"bench-calib": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
