"""The C tracker kernel against the NumPy path, frame by frame, and how the tracker picks its path.

The kernel's own memory safety is checked by the ASan + UBSan ctest `tracker_kernel_asan`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from flytrack_host.protocol import POINT_DTYPE
from flytrack_host.tracking import kernel as ckernel
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.synthetic import Scenario, make_scenario
from flytrack_host.tracking.tracker import KERNEL_ENV, Tracker, select_kernel
from flytrack_host.tracking.types import FrameBundle, FrameResult

needs_c = pytest.mark.c_kernel  # conftest.py: a failure under make when the kernel is not built


def _run(sc: Scenario, kernel: str, bundles: list[FrameBundle] | None = None,
         **params: object) -> tuple[Tracker, list[FrameResult]]:
    tr = Tracker(sc.cameras, TrackingParams(kernel=kernel, **params), sc.frame_period_s)
    assert tr.kernel_path == kernel
    return tr, [tr.process(b) for b in (bundles or sc.bundles)]


def _assert_same(a: tuple[Tracker, list[FrameResult]], b: tuple[Tracker, list[FrameResult]]) -> float:
    """Same identities, associations, births and deaths in every frame, estimates within 1e-9 m
    (covariances 1e-12); returns the largest state difference."""
    (ta, ra), (tb, rb) = a, b
    worst = 0.0
    for f, (x, y) in enumerate(zip(ra, rb, strict=True)):
        assert [e.obj_id for e in x.estimates] == [e.obj_id for e in y.estimates], f"frame {f}"
        assert ([(s.obj_id, s.camera_index, s.point_index) for s in x.associations]
                == [(s.obj_id, s.camera_index, s.point_index) for s in y.associations]), f"frame {f}"
        assert (x.born, x.died) == (y.born, y.died), f"frame {f}"
        for ex, ey in zip(x.estimates, y.estimates, strict=True):
            assert ex.n_cameras == ey.n_cameras, f"frame {f}"
            np.testing.assert_allclose(ey.state, ex.state, rtol=0, atol=1e-9, err_msg=f"frame {f}")
            np.testing.assert_allclose(ey.covariance, ex.covariance, rtol=1e-9, atol=1e-15, err_msg=f"frame {f}")
            assert (ex.orientation is None) == (ey.orientation is None), f"frame {f}"
            if ex.orientation is not None:
                np.testing.assert_allclose(ey.orientation, ex.orientation, atol=1e-9, err_msg=f"frame {f}")
            worst = max(worst, float(np.abs(ex.state - ey.state).max()))
    assert ta.stats == tb.stats
    assert ta._next_obj_id == tb._next_obj_id
    return worst


SCENARIOS = {
    "2 cameras x 1": dict(n_cameras=2, n_targets=1, close_pass_m=None, seed=1),
    "5 cameras x 2, close pass": dict(n_cameras=5, n_targets=2, seed=1),
    "5 cameras x 4, NaN/inf points, outage": dict(n_cameras=5, n_targets=4, corrupt_fraction=0.03,
                                                  camera_outages=((2, 80, 140),), seed=3),
    "11 cameras x 8, many false positives": dict(n_cameras=11, n_targets=8, false_positives_per_camera=1.5,
                                                 seed=2),
}


@needs_c
@pytest.mark.parametrize("name", list(SCENARIOS))
def test_c_and_numpy_paths_agree_frame_by_frame(name: str) -> None:
    sc = make_scenario(duration_s=3.0, **SCENARIOS[name])
    c = _run(sc, "c")
    worst = _assert_same(_run(sc, "numpy"), c)
    print(f"\n{name}: largest state difference {worst:.1e}, stats {c[0].stats}")
    if "close pass" in name or "11 cameras" in name:
        assert c[0].stats["conflicts_resolved"] > 0  # the scipy clash path ran in both
    assert c[0].stats["births"] > 0


@needs_c
def test_flydra_distortion_frame_agrees() -> None:
    """Cameras whose distortion is about another K than P's (Camera.K_dist, flydra's intrinsic_linear):
    the kernel's distortion frame gives the NumPy path's estimates, and both track well."""
    from flytrack_host.geometry.camera import Camera
    from flytrack_host.tracking.evaluation import score_frames
    from flytrack_host.tracking.synthetic import arena_cameras

    cams = {}
    for i, c in arena_cameras(5, seed=4).items():
        Kd = c.K.copy()
        Kd[0, 2] += 30.0 * (1 if i % 2 else -1)
        Kd[1, 2] -= 20.0
        Kd[0, 0] *= 1.02
        cams[i] = Camera(c.name, c.width, c.height, c.K, c.R, c.t, c.dist, K_dist=Kd)
    sc = make_scenario(n_targets=3, duration_s=3.0, seed=4, cameras=cams)
    c = _run(sc, "c")
    worst = _assert_same(_run(sc, "numpy"), c)
    s = score_frames(sc.truth, [{e.obj_id: e.state[:3] for e in r.estimates} for r in c[1]])
    print(f"\nflydra distortion frame: largest state difference {worst:.1e}; {s.line()}")
    assert s.rmse_mm < 2.0 and s.mota > 0.9


@needs_c
def test_flydra_merge_rule_and_skipped_frames_agree() -> None:
    sc = make_scenario(n_cameras=5, n_targets=4, duration_s=4.0, seed=1)
    kept = [b for b in sc.bundles if b.trigger_frame % 4 != 1]
    a = _run(sc, "numpy", kept, exclusive_points=False)
    b = _run(sc, "c", kept, exclusive_points=False)
    _assert_same(a, b)
    assert b[0].stats["merges_prevented"] > 0 and b[0].stats["skipped_frames"] > 0


@needs_c
def test_other_params_and_empty_frames_agree() -> None:
    """Non-default gates and a long silence (deaths, births again) give the same on both paths."""
    sc = make_scenario(n_cameras=4, n_targets=3, duration_s=2.0, seed=5)
    bundles = sc.bundles[:80] + [FrameBundle(f, f / 100, {}) for f in range(80, 130)] + sc.bundles[130:]
    params = dict(min_area_px=3.0, gate_px=12.0, confirm_min_frames=1, birth_max_combination=2,
                  motion_noise_scale=0.3, orientation_min_plane_angle_deg=25.0)
    a, b = _run(sc, "numpy", bundles, **params), _run(sc, "c", bundles, **params)
    _assert_same(a, b)
    assert b[0].stats["deaths"] > 0


@needs_c
def test_buffers_grow_for_crowded_frames() -> None:
    """A frame with many more points and targets than the first buffers hold."""
    sc = make_scenario(n_cameras=5, n_targets=14, duration_s=1.0, false_positives_per_camera=40.0,
                       enter_exit=False, seed=6)
    a, b = _run(sc, "numpy"), _run(sc, "c")
    _assert_same(a, b)
    assert b[0]._kern is not None and b[0]._kern.n_cap > 64 and b[0]._kern.t_cap > 8


@needs_c
def test_other_point_dtypes_are_read_as_protocol_points() -> None:
    sc = make_scenario(n_cameras=3, n_targets=1, duration_s=0.3, close_pass_m=None, seed=7)
    fields = ["x_dist", "y_dist", "x_undist", "y_undist", "area", "orientation", "eccentricity"]
    other = np.dtype([(f, "<f4") for f in reversed(fields)])  # same values, other layout
    conv = []
    for bnd in sc.bundles:
        dets = {}
        for ci, arr in bnd.detections.items():
            o = np.zeros(len(arr), other)
            for f in fields:
                o[f] = arr[f]
            dets[ci] = o
        conv.append(FrameBundle(bnd.trigger_frame, bnd.timestamp, dets))
    _assert_same(_run(sc, "numpy"), _run(sc, "c", conv))


def test_path_selection(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(KERNEL_ENV, "numpy")
    assert select_kernel(TrackingParams())[0] == "numpy"
    monkeypatch.setenv(KERNEL_ENV, "fortran")
    with pytest.raises(ValueError, match=KERNEL_ENV):
        select_kernel(TrackingParams())
    assert select_kernel(TrackingParams(kernel="numpy"))[0] == "numpy"  # the params win
    monkeypatch.delenv(KERNEL_ENV)
    assert select_kernel(TrackingParams())[0] == ("c" if ckernel.unavailable_reason() is None else "numpy")


def test_missing_library_falls_back_or_refuses(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(ckernel, "_lib", None)
    monkeypatch.setenv("FLYTRACK_BUILD_DIR", str(tmp_path))
    monkeypatch.delenv(KERNEL_ENV, raising=False)
    path, why = select_kernel(TrackingParams())
    assert path == "numpy" and "make build" in why
    sc = make_scenario(n_cameras=2, n_targets=1, duration_s=0.1, close_pass_m=None, seed=1)
    assert Tracker(sc.cameras, TrackingParams(), 0.01).kernel_path == "numpy"
    with pytest.raises(ckernel.KernelUnavailable, match="not built"):
        Tracker(sc.cameras, TrackingParams(kernel="c"), 0.01)
    monkeypatch.setenv(KERNEL_ENV, "c")
    with pytest.raises(ckernel.KernelUnavailable, match=KERNEL_ENV):
        Tracker(sc.cameras, TrackingParams(), 0.01)


@needs_c
def test_kernel_refuses_bad_calls() -> None:
    sc = make_scenario(n_cameras=2, n_targets=1, duration_s=0.1, close_pass_m=None, seed=1)
    tr = Tracker(sc.cameras, TrackingParams(kernel="c"), 0.01)
    k = tr._kern
    assert k is not None
    with pytest.raises(RuntimeError, match="invalid argument"):
        k.frame(None, 0, k.t_cap + 1, 0.01)  # more targets than the buffers hold
    with pytest.raises(RuntimeError, match="invalid argument"):
        k.frame(None, 0, 1, float("nan"))  # no time step
    k.counts[0] = 3
    with pytest.raises(RuntimeError, match="invalid argument"):
        k.frame(None, 3, 0, 0.01)  # points announced, no bytes
    k.counts[0] = 0
    assert POINT_DTYPE.itemsize == 4 * 11
