"""`make bench-fish`: the per-frame shape fit side by side on the same frames, same cost (eq. 4.2 + our outside
term), same start (the previous frame's true state, as a prediction would give):
- FlyTrack: batched simulated annealing (Table 2's schedule cut to 6 levels) + least-squares polish;
- scipy.optimize.dual_annealing (generalised SA with its own L-BFGS-B local search), bounded around the start;
- scipy L-BFGS-B quasi-Newton alone from the start;
and the cost's line-distance kernel in C against the NumPy path. Prints means and ratios; never fails on speed.

Every path runs with one BLAS thread (threadpoolctl, as `fish track` and the demo track: the fit's matrices are
tiny, more threads only spin and bill CPU time), so the CPU times compare as the fish figures are quoted;
`--blas-threads 0` leaves the BLAS library's default. The header prints the BLAS libraries and their threads.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import time
from pathlib import Path

import numpy as np
from scipy.optimize import dual_annealing
from threadpoolctl import threadpool_info, threadpool_limits

from flytrack_host.fish import fit as F
from flytrack_host.fish.render import render_sequence
from flytrack_host.fish.school import make_school
from flytrack_host.fish.shape import default_model
from flytrack_host.fish.silhouette import warm_up
from flytrack_host.fish.tracker import mm_per_px
from flytrack_host.fish.views import AirView, tank_rig


def _costs(n_frames: int, seed: int) -> list[tuple[F.FishCost, np.ndarray, np.ndarray, np.ndarray]]:
    school = make_school(1, n_frames + 1, seed=seed)
    rig = tank_rig((640, 512), (512, 384), top_zoom=2.0)
    views = [AirView(rig["top"]), AirView(rig["side"])]
    model = default_model(school.length)
    imgs = render_sequence(views, model, school.truth, np.random.default_rng(seed), n_background=3)
    bms = [warm_up(imgs[c][:3]) for c in range(2)]
    cfg = F.FitConfig()
    mm = F.model_in_mm(model)
    out = []
    for k in range(1, n_frames + 1):
        Xp = school.truth[k - 1, 0]
        Xt = school.truth[k, 0]
        r0 = Xp[:3]
        sets, oms = [], []
        for c in range(2):
            sil = bms[c].segment(imgs[c][3 + k])
            b = max(sil.blobs, key=lambda b: b.area)
            sets.append(F.contour_lines(views[c], b.contour, r0, cfg.max_lines, c))
            oms.append(F.OutsideMap.build(views[c], sil.fg, sil.mask, mm_per_px(views[c], Xp), r0))
        zp = F.z_from_state(Xp, r0)[0]
        cost = F.make_cost(mm, r0, sets, [None] * len(sets), cfg, z_prior=zp, outside=oms)
        out.append((cost, zp, Xt, r0))
    return out


def _errors(z: np.ndarray, Xt: np.ndarray, r0: np.ndarray) -> tuple[float, float]:
    X = F.state_from_z(z, r0)[0]
    return (float(np.linalg.norm(X[:3] - Xt[:3]) * 1000),
            float(np.degrees(np.arccos(np.clip(X[3:6] @ Xt[3:6], -1, 1)))))


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--json", default=None)
    ap.add_argument("--blas-threads", type=int, default=1,
                    help="BLAS threads for every compared path (0: the BLAS library's default)")
    args = ap.parse_args(argv)
    if args.blas_threads < 0:
        ap.error("--blas-threads must be 0 (the library's default) or more")
    limit = threadpool_limits(limits=args.blas_threads, user_api="blas") if args.blas_threads else None
    with limit or contextlib.nullcontext():
        return _run(args)


def _blas() -> str:
    """The BLAS libraries loaded now and their thread counts, as threadpoolctl reads them."""
    libs = [f"{i.get('internal_api', '?')} of {Path(i.get('filepath', '')).parent.name.removesuffix('.libs')} "
            f"{i['num_threads']} thread{'s' if i['num_threads'] != 1 else ''}"
            for i in threadpool_info() if i.get("user_api") == "blas"]
    return ", ".join(libs) or "none loaded"


def _run(args: argparse.Namespace) -> dict:
    cases = _costs(args.frames, 1)
    cfg = F.FitConfig()
    rng = np.random.default_rng(0)
    half = np.array([6, 6, 6, 10, 10, 12, 12, 15, 15, 15], float)  # search box for dual_annealing (z units)
    methods = {
        "flytrack SA+lsq": lambda c, z0: F.fit_fish(c, z0, cfg, rng)[0],
        "scipy dual_annealing": lambda c, z0: dual_annealing(lambda z: float(c(z[None])[0]),
                                                             list(zip(z0 - half, z0 + half, strict=True)),
                                                             maxfun=3000, seed=0, x0=z0).x,
        "scipy L-BFGS-B": lambda c, z0: F.quasi_newton(c, z0, 60)[0],
    }
    rows = {}
    for name, fn in methods.items():
        head, hd, cost, evals, secs = [], [], [], [], []
        for c, zp, Xt, r0 in cases:
            c.evaluations = 0
            t0 = time.process_time()
            z = fn(c, zp)
            secs.append(time.process_time() - t0)
            evals.append(c.evaluations)
            cost.append(float(c(z[None])[0]))
            e, h = _errors(z, Xt, r0)
            head.append(e)
            hd.append(h)
        rows[name] = {"head_mm": float(np.mean(head)), "heading_deg": float(np.mean(hd)),
                      "cost": float(np.mean(cost)), "evaluations": float(np.mean(evals)),
                      "ms_per_fit": 1000 * float(np.mean(secs))}
    ours = rows["flytrack SA+lsq"]
    threads = (f"{args.blas_threads} BLAS thread{'s' if args.blas_threads != 1 else ''} for every path"
               if args.blas_threads else "the BLAS library's default threads")
    print(f"per-frame fit, 1 fish, {args.frames} frames, same cost and start (CPU time; {threads}: {_blas()})")
    cols = ("head mm", "heading", "cost", "evals", "ms/fit", "time ratio")
    print(f"{'method':24s} " + " ".join(f"{c:>8s}" for c in cols))
    for name, r in rows.items():
        print(f"{name:24s} {r['head_mm']:8.2f} {r['heading_deg']:8.2f} {r['cost']:8.1f} {r['evaluations']:7.0f} "
              f"{r['ms_per_fit']:8.1f} {r['ms_per_fit'] / ours['ms_per_fit']:9.1f}x")
    # the kernel: C vs NumPy on one batch of 11 states (a finite-difference Jacobian's worth)
    c, zp, _, _ = cases[0]
    Z = zp + np.random.default_rng(1).normal(0, 1, (11, zp.size))
    X = np.concatenate([Z[:, 0:3], F.heading_from_angles(Z[:, 3] * F.ANG, Z[:, 4] * F.ANG), Z[:, 5:10]], axis=1)
    S = c.model.surface(X)
    timing = {}
    for name, f in (("C", lambda: [F.line_distances(S, ls) for ls in c.line_sets]),
                    ("NumPy", lambda: [F.line_distances_numpy(S, ls) for ls in c.line_sets])):
        n = 0
        t0 = time.process_time()
        while time.process_time() - t0 < 1.0:
            f()
            n += 1
        timing[name] = (time.process_time() - t0) / n / 11 * 1e3
    print(f"line distances per state ({sum(len(ls.p) for ls in c.line_sets)} lines x {S.shape[1] * S.shape[2]} "
          f"surface points): C {timing['C']:.3f} ms, NumPy {timing['NumPy']:.3f} ms, "
          f"ratio {timing['NumPy'] / timing['C']:.1f}x")
    result = {"fit": rows, "kernel_ms_per_state": timing, "blas_threads": args.blas_threads or None,
              "blas": _blas()}
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"bench-fish": result}, fh, indent=2)
    return result


if __name__ == "__main__":
    main()
