"""A Stone Soup tracker equivalent to ours, for the side-by-side benchmark only (`flytrack bench tracker`).

What a user would otherwise build from Stone Soup 1.9.1: its ExtendedKalmanPredictor and
ExtendedKalmanUpdater, the same constant-velocity model (ConstantVelocity per axis: Braid's Q with the
same noise scale), a nonlinear camera measurement model that projects with our `Camera` (lens
distortion included, analytic Jacobian), and nearest-neighbour association: DistanceHypothesiser with
the Mahalanobis measure plus GNNWith2DAssignment, run camera by camera in each frame so that each
camera gives a track at most one point (sequential EKF updates at one timestamp).

Two ways to start and end tracks:

- own (`StoneSoupTracker(..., volume=(lo, hi))`, the main comparison): Stone Soup's own
  MultiMeasurementInitiator. A point no track takes starts a holding track from a prior that covers
  the volume (its centre, std half its extent per axis; velocity std initial_velocity_std_m_s) through
  a single EKF update; holding tracks take further points by the same GNN association, camera by
  camera, are confirmed after `min_points` updates and dropped when a frame period passes without one
  (UpdateTimeDeleter). Confirmed tracks end by Stone Soup's CovarianceBasedDeleter on the position
  block with our death threshold (trace over 3 x death_position_std_m^2). Every confirmed track is
  reported.
- given births (`add_births`, no volume): each birth our tracker makes (`Tracker.last_births`) starts
  a Stone Soup track at the same frame with the same state and covariance; deaths use our rule
  (position std over death_position_std_m), reporting our rule too (updated in confirm_min_frames
  frames). This isolates the per-frame filter and association, with initiation handed over.

Stone Soup is imported only here.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Mapping, Sequence

import numpy as np
from stonesoup.base import Property
from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
from stonesoup.deleter.error import CovarianceBasedDeleter
from stonesoup.deleter.time import UpdateTimeDeleter
from stonesoup.hypothesiser.distance import DistanceHypothesiser
from stonesoup.initiator.simple import MultiMeasurementInitiator, SinglePointInitiator
from stonesoup.measures import Mahalanobis
from stonesoup.models.measurement.nonlinear import NonLinearGaussianMeasurement
from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity
from stonesoup.predictor.kalman import ExtendedKalmanPredictor
from stonesoup.types.array import StateVector, StateVectors
from stonesoup.types.detection import Detection
from stonesoup.types.state import GaussianState, State
from stonesoup.types.track import Track
from stonesoup.updater.kalman import ExtendedKalmanUpdater

from flytrack_host.geometry.camera import Camera
from flytrack_host.tracking.birth import Birth
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.types import FrameBundle

_POS = (0, 2, 4)  # Stone Soup's state order is (x, vx, y, vy, z, vz)
_EPOCH = _dt.datetime(2020, 1, 1)


class CameraMeasurementModel(NonLinearGaussianMeasurement):
    """Distorted pixel (u, v) of the state's position through a FlyTrack `Camera`."""

    camera: Camera = Property(doc="The calibrated camera (FlyTrack's model)")

    @property
    def ndim_meas(self) -> int:
        return 2

    def function(self, state, noise=False, **kwargs):  # noqa: ANN001, ANN201 - Stone Soup's signature
        X = np.asarray(state.state_vector[self.mapping, :], dtype=np.float64).T
        uv = self.camera.project(X).T
        if isinstance(noise, bool) or noise is None:
            noise = self.rvs(num_samples=X.shape[0], **kwargs) if noise else 0
        out = uv + noise
        return StateVectors(out) if out.shape[1] > 1 else StateVector(out)

    def jacobian(self, state, **kwargs):  # noqa: ANN001, ANN201
        X = np.asarray(state.state_vector[self.mapping, 0], dtype=np.float64)
        _, J = self.camera.project_jacobian(X)
        H = np.zeros((2, self.ndim_state))
        H[:, list(self.mapping)] = J
        return H


def check_camera_model(cameras: Mapping[int, Camera], X: Sequence[float] = (0.6, 0.05, 0.1)) -> None:
    """The comparison is only fair if Stone Soup sees our cameras: its measurement function and
    Jacobian through CameraMeasurementModel must equal Camera.project / project_jacobian at X (each
    camera), and the velocity columns be zero. Raises AssertionError naming the camera otherwise."""
    X = np.asarray(X, dtype=np.float64)
    sv = np.zeros(6)
    sv[list(_POS)] = X
    state = State(StateVector(sv))
    for ci, cam in cameras.items():
        model = CameraMeasurementModel(ndim_state=6, mapping=_POS, noise_covar=np.eye(2), camera=cam)
        np.testing.assert_allclose(np.asarray(model.function(state), dtype=np.float64).ravel(), cam.project(X)[0],
                                   rtol=1e-12, atol=1e-9, err_msg=f"camera {ci}: Stone Soup projection")
        H = np.asarray(model.jacobian(state), dtype=np.float64)
        np.testing.assert_allclose(H[:, list(_POS)], cam.project_jacobian(X)[1], rtol=1e-12, atol=1e-9,
                                   err_msg=f"camera {ci}: Stone Soup Jacobian")
        vel = [i for i in range(6) if i not in _POS]
        assert np.all(H[:, vel] == 0), f"camera {ci}: Stone Soup Jacobian has velocity terms"


class StoneSoupTracker:
    def __init__(self, cameras: Mapping[int, Camera], params: TrackingParams, frame_period_s: float,
                 gate_sigma: float = 10.0, volume: tuple[Sequence[float], Sequence[float]] | None = None,
                 min_points: int = 3) -> None:
        self.params = params
        self.frame_period_s = frame_period_s
        q = params.motion_noise_scale
        self.transition = CombinedLinearGaussianTransitionModel([ConstantVelocity(q)] * 3)
        self.predictor = ExtendedKalmanPredictor(self.transition)
        self.updater = ExtendedKalmanUpdater(measurement_model=None)
        r2 = params.measurement_noise_px**2
        self.models = {
            ci: CameraMeasurementModel(ndim_state=6, mapping=_POS, noise_covar=np.eye(2) * r2, camera=cam)
            for ci, cam in cameras.items()
        }
        hyp = DistanceHypothesiser(self.predictor, self.updater, measure=Mahalanobis(), missed_distance=gate_sigma)
        self.associator = GNNWith2DAssignment(hyp)
        self.tracks: list[Track] = []
        self._n_upd: dict[int, int] = {}
        self._obj: dict[int, int] = {}
        self._own_ids: dict[str, int] = {}
        self._next = 0
        p = params
        self._P0 = np.diag([p.initial_position_std_m**2, p.initial_velocity_std_m_s**2] * 3)
        self.initiator: MultiMeasurementInitiator | None = None
        if volume is not None:
            lo, hi = np.asarray(volume[0], np.float64), np.asarray(volume[1], np.float64)
            sv = np.zeros(6)
            sv[list(_POS)] = (lo + hi) / 2
            var = np.zeros(6)
            var[list(_POS)] = ((hi - lo) / 2) ** 2
            var[[1, 3, 5]] = p.initial_velocity_std_m_s**2
            prior = GaussianState(StateVector(sv), np.diag(var))
            self.initiator = MultiMeasurementInitiator(
                prior_state=prior,
                deleter=UpdateTimeDeleter(_dt.timedelta(seconds=frame_period_s * 0.999)),
                data_associator=GNNWith2DAssignment(hyp),
                updater=self.updater,
                min_points=min_points,
                initiator=SinglePointInitiator(prior, updater=self.updater),
            )
            self.deleter = CovarianceBasedDeleter(covar_trace_thresh=3 * p.death_position_std_m**2,
                                                  mapping=list(_POS))

    def add_births(self, births: Sequence[Birth], frame: int) -> None:
        ts = self._ts(frame)
        for b in births:
            sv = np.zeros(6)
            sv[list(_POS)] = b.position
            self.tracks.append(Track([GaussianState(StateVector(sv), self._P0.copy(), timestamp=ts)]))

    def _ts(self, frame: int) -> _dt.datetime:
        return _EPOCH + _dt.timedelta(seconds=frame * self.frame_period_s)

    def process(self, bundle: FrameBundle) -> dict[int, np.ndarray]:
        """Track one frame; returns reported id -> position (3,)."""
        if self.initiator is not None:
            return self._process_own(bundle)
        return self._process_given(bundle)

    def _detections(self, bundle: FrameBundle, ci: int, ts: _dt.datetime) -> set[Detection]:
        arr = bundle.detections[ci]
        u = arr["x_dist"].astype(np.float64)
        v = arr["y_dist"].astype(np.float64)
        ok = np.isfinite(u) & np.isfinite(v) & np.isfinite(arr["area"])
        model = self.models[ci]
        return {Detection(StateVector([u[i], v[i]]), timestamp=ts, measurement_model=model)
                for i in np.flatnonzero(ok)}

    def _process_own(self, bundle: FrameBundle) -> dict[int, np.ndarray]:
        """Stone Soup end to end: association, its initiator, its deleter (see the module docstring)."""
        assert self.initiator is not None
        ts = self._ts(bundle.trigger_frame)
        tracks = set(self.tracks)
        for ci in sorted(bundle.detections):
            if ci not in self.models or not len(bundle.detections[ci]):
                continue
            dets = self._detections(bundle, ci, ts)
            used: set[Detection] = set()
            if tracks:
                for track, hyp in self.associator.associate(tracks, dets, ts).items():
                    if hyp:
                        track.append(self.updater.update(hyp))
                        used.add(hyp.measurement)
            tracks |= self.initiator.initiate(dets - used, ts)
        for track in tracks:
            if track.state.timestamp < ts:
                track.append(self.predictor.predict(track.state, timestamp=ts))
        tracks -= self.deleter.delete_tracks(tracks)
        self.tracks = list(tracks)
        out: dict[int, np.ndarray] = {}
        for track in self.tracks:
            if track.id not in self._own_ids:  # Stone Soup's track uuid; id() could be reused
                self._own_ids[track.id] = self._next
                self._next += 1
            out[self._own_ids[track.id]] = np.asarray(track.state.state_vector[list(_POS), 0], dtype=np.float64)
            if len(track.states) > 2:  # only the latest state is needed; memory must not grow
                last = track.states[-1]
                track.states.clear()
                track.append(last)
        return out

    def _process_given(self, bundle: FrameBundle) -> dict[int, np.ndarray]:
        ts = self._ts(bundle.trigger_frame)
        updated: set[int] = set()
        tracks = set(self.tracks)
        for ci in sorted(bundle.detections):
            arr = bundle.detections[ci]
            model = self.models.get(ci)
            if model is None or not len(arr) or not tracks:
                continue
            u = arr["x_dist"].astype(np.float64)
            v = arr["y_dist"].astype(np.float64)
            ok = np.isfinite(u) & np.isfinite(v) & np.isfinite(arr["area"])
            dets = {
                Detection(StateVector([u[i], v[i]]), timestamp=ts, measurement_model=model)
                for i in np.flatnonzero(ok)
            }
            hyps = self.associator.associate(tracks, dets, ts)
            for track, hyp in hyps.items():
                if hyp:
                    track.append(self.updater.update(hyp))
                    updated.add(id(track))
        out: dict[int, np.ndarray] = {}
        alive: list[Track] = []
        death_var = self.params.death_position_std_m**2
        for track in self.tracks:
            if track.state.timestamp < ts:
                track.append(self.predictor.predict(track.state, timestamp=ts))
            if id(track) in updated:
                self._n_upd[id(track)] = self._n_upd.get(id(track), 0) + 1
            cov = np.asarray(track.state.covar)
            if not max(cov[i, i] for i in _POS) <= death_var:
                continue
            alive.append(track)
            if self._n_upd.get(id(track), 0) >= self.params.confirm_min_frames:
                if id(track) not in self._obj:
                    self._obj[id(track)] = self._next
                    self._next += 1
                out[self._obj[id(track)]] = np.asarray(track.state.state_vector[list(_POS), 0], dtype=np.float64)
        self.tracks = alive
        # Keep only the latest state (what a live tracker needs) so memory does not grow.
        for track in alive:
            if len(track.states) > 2:
                last = track.states[-1]
                track.states.clear()
                track.append(last)
        return out
