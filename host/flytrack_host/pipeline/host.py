"""The host's main loop: receive -> synchronise -> track -> live output, everything recorded.

    pipe = HostPipeline(rig, cameras, on_result=print)
    pipe.start(); ...; summary = pipe.stop()

One tracking thread owns the socket: it waits for datagrams until the next bundle deadline, hands
frames to the synchroniser, runs the tracker on each closed bundle and sends the live datagram at
once. Recording rows are queued to the recorder's own thread, so disk writes never hold it up.

With a trigger box (`trigger_session.TriggerSession`, as `flytrack run` does) the pipeline is built
with the trigger's exact rate (`fps=`), its clock (`clock=`) and `hold_until_synchronized=True`:
frames are then recorded but not tracked until `resynchronize()` has re-armed the frame-0 tie,
which the session calls once the cameras went quiet and just before it starts the trigger.
"""

from __future__ import annotations

import importlib
import json
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from flytrack_host.dvs.clusters.observations import DvsObservations
from flytrack_host.geometry.camera import Camera
from flytrack_host.intake.receiver import DvsSlice, Receiver, StatusReport
from flytrack_host.intake.sync import (
    CameraFrame,
    FixedRateClock,
    FrameClock,
    FrameSynchronizer,
    SyncedBundle,
    SyncEvent,
    UntrackedFrame,
)
from flytrack_host.live.udp import LiveSender
from flytrack_host.pipeline.cameras import calibration_problems
from flytrack_host.pipeline.cpu_latency import CpuWakeLatency, wanted_us
from flytrack_host.pipeline.dvs import DvsIntake
from flytrack_host.pipeline.report import PipelineReport
from flytrack_host.pipeline.sink import ResultSink
from flytrack_host.recording.latency import LatencyStats
from flytrack_host.recording.parts import PartPolicy
from flytrack_host.recording.rows import data2d_rows, dvs_covariance_rows, result_rows
from flytrack_host.recording.schema import (
    CAM_INFO,
    CAMERA_STATUS,
    FLAG_LATE,
    FLAG_REJECTED,
    FLAG_TRACKED,
    TRIGGER_CLOCK,
)
from flytrack_host.recording.writer import Recorder
from flytrack_host.rig import RigConfig
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.types import FrameBundle, FrameResult
from flytrack_host.util import hostclock
from flytrack_host.util.ratelog import RateLimitedLog

log = logging.getLogger("flytrack.pipeline")

TrackerFactory = Callable[[Mapping[int, Camera], TrackingParams, float], Any]
_UNTRACKED_WHY = {
    "early": "is numbered ahead of its arrival (a misbehaving or replaying edge?)",
    "future": "claims a trigger frame in the future",
    "discontinuity": "breaks its camera's numbering (jump back or far ahead)",
    "unknown_camera": "is from a camera the synchroniser does not know",
    "late": "came after its trigger frame was tracked (late)",
}
RECORDING_INCOMPLETE_EXIT = 3  # `flytrack run` exit code when the recording lost data (a full disk)
RECEIVE_BATCH = 256  # datagrams taken from the socket per turn of the tracking thread
MAX_BACKLOG_S = 1.0  # a frame this far behind real time is recorded, not tracked: the host catches up
STALL_S = 0.2  # a turn of the tracking thread this late means the host was not scheduled


def default_tracker_factory(cameras: Mapping[int, Camera], params: TrackingParams, period: float) -> Any:
    mod = importlib.import_module("flytrack_host.tracking.tracker")
    return mod.Tracker(cameras, params, period)

def default_recording_path(rig: RigConfig) -> Path:
    stamp = time.strftime("%Y%m%d_%H%M%S")
    return rig.recording_dir / f"{stamp}_{rig.name}.flytrack"


class HostPipeline(DvsIntake, PipelineReport):
    def __init__(
        self,
        rig: RigConfig,
        cameras: Mapping[int, Camera] | None = None,
        clock: FrameClock | None = None,
        tracker_factory: TrackerFactory | None = default_tracker_factory,
        record: bool = True,
        recording_path: Path | str | None = None,
        on_result: Callable[[FrameResult], object] | None = None,
        bind: str | None = None,
        keep_results: bool = False,
        dead_timeout_s: float = 0.5,
        rig_text: str | None = None,
        calibration_path: Path | None = None,
        params: TrackingParams | None = None,
        fps: float | None = None,
        hold_until_synchronized: bool = False,
        sinks: list[ResultSink] | None = None,
    ):
        self.rig = rig
        self.cameras = dict(cameras) if cameras else {}
        self.params = params or rig.tracking
        self.fps = float(fps) if fps is not None else rig.trigger.fps  # fps: the trigger's exact rate
        self.period = 1.0 / self.fps
        self.clock: FrameClock = clock if clock is not None else FixedRateClock(self.fps)
        self.tracker_factory = tracker_factory
        self.record = record
        self.recording_path = Path(recording_path) if recording_path else default_recording_path(rig)
        self.on_result = on_result
        self.bind = bind
        self.keep_results = keep_results
        self.dead_timeout_s = dead_timeout_s
        self.rig_text = rig_text
        self.calibration_path = calibration_path if calibration_path is not None else rig.calibration_path
        self.results: list[FrameResult] = []
        self.latency = LatencyStats()
        self.untracked: dict[str, int] = {}
        self.dvs_slices: dict[int, int] = {}  # DVS_CLUSTERS slices taken in, per event camera
        dvs_idx = [c.index for c in rig.cameras if c.kind == "dvs"]
        self.dvs_obs = (DvsObservations({i: self.cameras.get(i) for i in dvs_idx}, self.fps)
                        if dvs_idx and self.fps else None)
        # Every bundle of the run with the event cameras' points, for eventcam.comparison (with and
        # without them, side by side); off (maxlen 0) unless a caller sets a bound, e.g. the demo.
        self.dvs_bundles: deque[FrameBundle] = deque(maxlen=0)
        self.events: deque[str] = deque(maxlen=200)
        self.frames_tracked = 0
        self.tracker_errors = 0
        self.tracker_resets = 0
        self.n_objects = 0
        self.n_estimates = 0  # estimates reported over the run
        self.why_nothing: list[str] = []  # why no estimates although points arrived (set by stop)
        self.callback_errors = 0
        self.sinks: list[ResultSink] = list(sinks or [])  # live outputs and actuation, fed per frame
        self.sink_errors = 0
        self.last_synced: SyncedBundle | None = None  # the last bundle tracked (read by the live page)
        self.recording_error: str | None = None  # finalising the recording failed (raw files kept)
        # Seconds stop() took to write what was queued and turn the raw files into HDF5 (None: not done): in
        # parts, the last part only (and one the background finaliser was still on).
        self.recording_finalize_s: float | None = None
        self.range_errors = 0  # camera frames with a value the recording's column cannot hold
        self.warn = RateLimitedLog(lambda m: self.log(m, "sync"))
        self.stalls = 0  # turns of the tracking thread that came STALL_S late or more
        self._last_turn = 0.0
        self.behind_skipped = 0  # frames recorded but not tracked because the host was too far behind
        self.max_backlog_s = MAX_BACKLOG_S
        self.wall_steps = 0  # wall-clock steps seen (labels moved; timing did not)
        self._wall_checked = 0.0
        self.loop_errors = 0  # exceptions caught per item in the tracking thread (it goes on)
        self.recorder: Recorder | None = None
        self.cpu_wake: CpuWakeLatency | None = None  # PM QoS request while running (pipeline/cpu_latency.py)
        self.receiver: Receiver | None = None
        self.live: LiveSender | None = None
        self.sync: FrameSynchronizer | None = None
        self.tracker: Any = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._started_at = 0.0
        self._stopped_at = 0.0
        self._error: BaseException | None = None
        self._summary: dict[str, Any] | None = None
        self._lock = threading.Lock()
        # Frame-0 tie on request of the trigger session (done by the tracking thread, which owns sync).
        self.last_frame_recv = 0.0  # host time the last camera frame arrived (quiet-camera check)
        self.resyncs = 0
        self.status_sources: list[Callable[[], str]] = []  # extra status-line parts (the trigger's)
        self._armed = threading.Event()
        if not hold_until_synchronized:
            self._armed.set()
        self._resync_request = threading.Event()
        self._resync_done = threading.Event()

    # --- control ------------------------------------------------------------------------------
    def start(self) -> None:
        self.receiver = Receiver(self.rig, bind=self.bind, log=lambda m: self.log(m, "receiver"))
        self.live = LiveSender(self.rig.host.live_subscribers)
        self.sync = FrameSynchronizer(
            [c.index for c in self.rig.cameras if c.kind == "frame"], self.fps, clock=self.clock,
            deadline_fraction=self.rig.host.sync_deadline_fraction,
            dead_timeout_s=self.dead_timeout_s, start_time=hostclock.now(),
        )
        if self.record:
            self._start_recorder()
        self._make_tracker(first=True)  # after the recorder: what it says goes into the text log too
        target = wanted_us(self.rig.host.cpu_wake_latency_us,
                           drives_devices=bool(self.rig.rules and self.rig.actuators))
        if target is not None:  # last: nothing after it can fail and leave the request held
            self.cpu_wake = CpuWakeLatency(target)
            self.log(self.cpu_wake.hold(), level=logging.INFO if self.cpu_wake.held else logging.WARNING)
        self._started_at = hostclock.now()
        self.log(f"pipeline started: {len(self.rig.cameras)} cameras, {self.fps:g} fps, "
                 f"listening on {self.receiver.address[0]}:{self.receiver.address[1]}")
        self._thread = threading.Thread(target=self._loop, name="flytrack-tracking", daemon=True)
        self._thread.start()

    @property
    def address(self) -> tuple[str, int]:
        """Where the pipeline receives feature datagrams (useful with port 0)."""
        assert self.receiver is not None, "start() first"
        return self.receiver.address

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def stop(self) -> dict[str, Any]:
        """Stop receiving, track what is pending, finalise the recording; returns the summary."""
        if self._summary is not None:
            return self._summary
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self.receiver is not None and self.sync is not None and self._error is None:
            # What is still queued in the socket was received: take it in before the last bundles
            # close (a backlog at stop, e.g. after a flood, is recorded, not dropped). Bounded in time.
            end = time.monotonic() + 2.0
            while time.monotonic() < end:
                items = self.receiver.receive(0.0, max_batch=RECEIVE_BATCH)
                if not items:
                    break
                for item in items:
                    self._guarded(self._item, item)
        if self.sync is not None:
            self._handle(self.sync.flush())
        self._stopped_at = hostclock.now()
        self.why_nothing = self._why_nothing()
        for w in self.why_nothing:
            self.log(f"no estimates: {w}", level=logging.WARNING)
        self.warn.flush()
        if self.receiver is not None:
            self.receiver.warn.flush()
        self.log("pipeline stopped")
        self.log(self.latency.format(), "latency")
        # Outputs first: what they still record (actuation firings) gets into the recording.
        for sink in self.sinks:
            try:
                sink.close()
            except Exception as exc:
                self.log(f"closing output {type(sink).__name__} failed: {exc!r}")
        h5 = None
        if self.recorder is not None:
            t0 = time.monotonic()
            try:
                h5 = self.recorder.stop(finalize=True)
                self.recording_finalize_s = time.monotonic() - t0
            except Exception as exc:  # e.g. a full disk: the raw files stay, `recording recover` later
                self.recording_error = f"{exc!r}"
                log.error("finalising the recording failed: %r; the raw files in %s are kept",
                          exc, self.recording_path)
        if self.receiver is not None:
            self.receiver.close()
        if self.live is not None:
            self.live.close()
        if self.cpu_wake is not None:
            self.cpu_wake.release()
        self._summary = self.summary(recording_h5=h5)
        if self._error is not None:
            raise RuntimeError(f"tracking thread failed: {self._error}") from self._error
        return self._summary

    def run_for(self, seconds: float) -> dict[str, Any]:
        self.start()
        try:
            time.sleep(seconds)
        finally:
            summary = self.stop()
        return summary

    def log(self, message: str, source: str = "host", level: int = logging.INFO) -> None:
        t = hostclock.now()
        # The wall clock only labels the line; the recording keeps host time (monotonic).
        label = time.strftime('%H:%M:%S', time.localtime(hostclock.wall()))
        self.events.append(f"{label} {source}: {message}")
        log.log(level, "%s: %s", source, message)
        if self.recorder is not None:
            self.recorder.log(message, source, t)

    def resynchronize(self, timeout_s: float = 2.0) -> None:
        """Re-arm the frame-0 tie: pending bundles are tracked, the synchroniser forgets its camera
        mappings (the next first frame of each camera is trigger frame 0) and the tracker restarts if
        it tracked anything. Call with the trigger stopped and the cameras quiet, just before START.
        Thread-safe: the tracking thread does it and this call waits until it is done."""
        if self._thread is None or not self._thread.is_alive():
            self._do_resync()
            return
        self._resync_done.clear()
        self._resync_request.set()
        if not self._resync_done.wait(timeout_s):
            raise RuntimeError(f"tracking thread did not re-synchronise within {timeout_s} s")

    def _do_resync(self) -> None:
        self._resync_request.clear()
        if self.sync is not None:
            self._handle(self.sync.flush())
            self.sync.synchronize()
        if self.tracker is not None and (self.frames_tracked or self.resyncs):
            self.tracker_resets += 1
            self._make_tracker()
        self.resyncs += 1
        self._armed.set()
        self.log("frame-0 tie armed: each camera's next first frame is trigger frame 0", "sync")
        self._resync_done.set()

    def record_clock_sample(self, start_time: float, framecount: int, fraction: float, stop_time: float) -> None:
        """Record one trigger clock sample (host time before/after the query, frame count, fraction)."""
        if self.recorder is not None:
            r = np.zeros(1, dtype=TRIGGER_CLOCK)
            r[0] = (start_time, framecount, fraction, stop_time)
            self.recorder.append("trigger_clock_info", r)

    # --- setup --------------------------------------------------------------------------------
    def _make_tracker(self, first: bool = False) -> None:
        self.tracker = None
        if self.tracker_factory is None:
            return
        for problem in calibration_problems(self.rig, self.cameras) if first else []:
            self.log(problem, level=logging.WARNING)
        if not self.cameras:
            return
        self.tracker = self.tracker_factory(self.cameras, self.params, self.period)
        path = getattr(self.tracker, "kernel_path", None)
        if path is not None:
            self.log(f"tracker: {'C kernel' if path == 'c' else 'NumPy'} path")

    def _start_recorder(self) -> None:
        meta = {
            "rig_name": self.rig.name,
            "fps": self.fps,
            "trigger_kind": self.rig.trigger.kind,
            "cameras": [c.model_dump() for c in self.rig.cameras],
            "tracking_params": self.params.model_dump(),
            "saving_program": "flytrack",
        }
        rc = self.rig.recording
        self.recorder = Recorder(self.recording_path, rc.flush_interval_s, meta=meta,
                                 parts=PartPolicy.from_rig(rc.part_minutes, rc.part_gb))
        self.recorder.start()
        if self.rig_text is not None:
            self.recorder.attach("rig.toml", self.rig_text.encode())
        else:
            self.recorder.attach("rig.json", json.dumps(self.rig.model_dump(mode="json"), indent=1).encode())
        if self.calibration_path is not None and Path(self.calibration_path).exists():
            p = Path(self.calibration_path)
            self.recorder.attach("calibration" + p.suffix, p.read_bytes())
        ci = np.zeros(len(self.rig.cameras), dtype=CAM_INFO)
        for i, c in enumerate(self.rig.cameras):
            ci[i] = (c.index, c.name.encode()[:64], c.edge.encode()[:64], c.calib_name.encode()[:64])
        self.recorder.append("cam_info", ci)
        self.recorder.log(f"MainBrain running at {self.fps:g} fps", "host")

    # --- tracking thread ----------------------------------------------------------------------
    def _loop(self) -> None:
        assert self.receiver is not None and self.sync is not None
        try:
            while not self._stop.is_set():
                if not self._guarded(self._step):
                    time.sleep(0.001)  # a turn failing every time must not spin the CPU
        except BaseException as exc:  # not an Exception (e.g. SystemExit): report in stop()
            self._error = exc
            log.exception("tracking thread failed")

    def _step(self) -> None:
        """One turn of the tracking thread: receive until the next deadline, hand on, close bundles.
        Each item is handled on its own, so no datagram or bundle can end the thread."""
        assert self.receiver is not None and self.sync is not None
        if self._resync_request.is_set():
            self._do_resync()
        d = self.sync.next_deadline()
        now = hostclock.now()
        if self._last_turn and now - self._last_turn > STALL_S:
            self.stalls += 1
            self.warn("stall", f"host stalled for {now - self._last_turn:.2f} s (not scheduled: overloaded, "
                      "stopped or swapping); catching up")
        self._last_turn = now
        timeout = 0.05 if d is None else min(0.05, max(0.0, d - now))
        items = self.receiver.receive(timeout, max_batch=RECEIVE_BATCH)
        for item in items:
            self._guarded(self._item, item)
        poll_at = hostclock.now()
        if len(items) >= RECEIVE_BATCH:
            # Still working through a backlog: judge deadlines and silent cameras at the newest arrival
            # handled, not at the wall of datagrams still queued (they would all look dead).
            poll_at = min(poll_at, max((getattr(i, "recv_time", 0.0) for i in items), default=poll_at))
        self._handle(self.sync.poll(poll_at))
        if now - self._wall_checked > 0.25:
            self._wall_checked = now
            step = hostclock.CLOCK.check_wall()
            if step is not None:
                self.wall_steps += 1
                self.log(hostclock.wall_step_message(step), "clock")

    def _item(self, item: CameraFrame | StatusReport) -> None:
        assert self.sync is not None
        if isinstance(item, CameraFrame):
            self.last_frame_recv = item.recv_time
            if not self._armed.is_set():
                # The trigger has not started yet: these frames belong to no trigger frame.
                self._handle([UntrackedFrame(item, -1, "before_trigger_start")])
                return
            try:
                outputs = self.sync.add(item, item.recv_time)
            except Exception:
                # Keep the frame (recorded as rejected, not tracked), then let _guarded count it.
                self._handle([UntrackedFrame(item, -1, "error")])
                raise
            self._handle(outputs)
        elif isinstance(item, StatusReport):
            self._status(item)
        elif isinstance(item, DvsSlice):
            self._dvs_slice(item)

    def _guarded(self, fn: Callable[..., object], *args: Any) -> bool:
        """Run one step of the tracking thread; an exception is logged (the first few in full) and
        counted (`loop_errors`), and the thread goes on."""
        try:
            fn(*args)
            return True
        except Exception as exc:
            self.loop_errors += 1
            if self.loop_errors <= 10:
                log.exception("tracking thread: %s failed", getattr(fn, "__name__", fn))
                self.log(f"{getattr(fn, '__name__', fn)} failed: {exc!r} (going on)", "pipeline")
            elif self.loop_errors == 11:
                self.log("more tracking-thread errors: counted, no longer logged", "pipeline")
            return False

    def _status(self, rep: StatusReport) -> None:
        if self.recorder is None:
            return
        s = rep.status
        r = np.zeros(1, dtype=CAMERA_STATUS)
        r[0] = (rep.recv_time, rep.camera_index, int(s.state), s.frames_seen, s.frames_dropped, s.fps,
                s.proc_us_mean, s.proc_us_max)
        self.recorder.append("camera_status", r)
        if s.last_error_code:
            self.log(f"camera {rep.camera_index} reports error {s.last_error_code}: {s.last_error}", "edge")

    def _handle(self, outputs: list) -> None:
        for o in outputs:
            self._guarded(self._output, o)

    def _output(self, o: object) -> None:
        if isinstance(o, SyncedBundle):
            self._track(o)
        elif isinstance(o, UntrackedFrame):
            self.untracked[o.reason] = self.untracked.get(o.reason, 0) + 1
            why = _UNTRACKED_WHY.get(o.reason)
            if why is not None:
                cam = o.frame.camera_index
                self.warn(f"untracked:{o.reason}:{cam}",
                          f"camera {cam}: frame {o.frame.camera_frame} {why}: recorded, not tracked")
            if self.recorder is not None:
                flag = FLAG_LATE if o.reason == "late" else FLAG_REJECTED
                t = self.sync.frame_time(o.trigger_frame) if self.sync and o.trigger_frame >= 0 else np.nan
                self.recorder.append("data2d_distorted", self._rows(o.frame, o.trigger_frame, t, flag))
        elif isinstance(o, SyncEvent):
            # Rate-limited per kind and camera, with counts: a flapping camera cannot flood the log.
            self.warn(f"sync:{o.kind}:{o.camera_index}", o.message)
            if o.kind == "clock_jump" and o.global_jump and self.tracker is not None:
                self.tracker_resets += 1
                self._make_tracker()
                self.log("tracker restarted after the trigger clock jump", "sync")

    def _rows(self, fr: CameraFrame, tf: int, t: float, flags: int) -> np.ndarray:
        bad: list[str] = []
        rows = data2d_rows(fr, tf, t, flags, bad)
        if bad:
            self.range_errors += 1
            self.warn(f"range:{fr.camera_index}", f"camera {fr.camera_index}: values out of range ({', '.join(bad)}): "
                      "recorded as -1/0 and flagged rejected")
        return rows

    @staticmethod
    def _dvs_cov_items(bundle: FrameBundle) -> list[tuple[str, np.ndarray]]:
        """The event cameras' point covariances, so that a re-track weighs their points as here."""
        return [("dvs_point_covariance", dvs_covariance_rows(ci, bundle.trigger_frame, cov))
                for ci, cov in bundle.point_cov.items() if len(cov)]

    def _track(self, sb: SyncedBundle) -> None:
        bundle: FrameBundle = sb.bundle
        result: FrameResult | None = None
        # How far the host itself is behind: since the bundle's last frame reached this machine (the
        # kernel's receive stamp), not since the trigger: cameras that deliver late are not the host's
        # backlog and are still tracked.
        behind = hostclock.now() - sb.last_arrival
        if behind > self.max_backlog_s and self.tracker is not None:
            # Bounded backlog: after a stall or an overload, frames this old are recorded, not tracked,
            # until the host is back near real time (the tracker predicts across the gap).
            self.behind_skipped += 1
            self.warn("behind", f"host {behind:.2f} s behind real time: frames recorded, not tracked, to "
                      f"catch up ({self.behind_skipped} so far)")
            self._add_dvs(sb, count=False)  # the event cameras' points are recorded too
            if self.recorder is not None:
                self.recorder.append_many(
                    [("data2d_distorted", self._rows(fr, bundle.trigger_frame, bundle.timestamp, FLAG_LATE))
                     for fr in sb.frames.values()] + self._dvs_cov_items(bundle))
            if self.dvs_bundles.maxlen:  # tracked later, by the comparison, with its event points
                self.dvs_bundles.append(bundle)
            return
        self._add_dvs(sb)
        self.dvs_bundles.append(bundle)
        if self.tracker is not None:
            try:
                result = self.tracker.process(bundle)
            except Exception as exc:  # a tracker bug must not stop receiving and recording
                # The tracker may be left half-updated, so later frames could fail the same way:
                # start a fresh one (tracks restart; the 2D data of every frame is recorded anyway).
                self.tracker_errors += 1
                if self.tracker_errors <= 10:
                    log.error("tracker failed on frame %d", bundle.trigger_frame, exc_info=exc)
                    self.log(f"tracker failed on frame {bundle.trigger_frame}: {exc!r}; tracker restarted",
                             "tracker")
                self.tracker_resets += 1
                self._make_tracker()
        t_est = hostclock.now()
        self.last_synced = sb  # the live page shows its cameras' points and arrival times
        if result is not None:
            if self.dvs_obs is not None:
                for a in result.associations:
                    if a.camera_index in self.dvs_obs.cams:
                        self.dvs_obs.count(a.camera_index, 0, 1)
            self.frames_tracked += 1
            self.n_objects = len(result.estimates)
            self.n_estimates += len(result.estimates)
            # The sinks first: they only hand the frame on (the actuation rules queue device commands),
            # while the live datagram's sendto releases the GIL, and another thread (a local live
            # consumer woken by that very datagram, the recorder) may then hold it for up to a switch
            # interval: measured 0.7-0.8 ms P50 added to estimate -> device command when live went first.
            for sink in self.sinks:
                try:
                    sink.on_frame(result, bundle.timestamp, t_est)
                except Exception as exc:  # an output's bug must not stop tracking
                    self.sink_errors += 1
                    if self.sink_errors <= 10:
                        self.log(f"output {type(sink).__name__} failed on frame {bundle.trigger_frame}: {exc!r}")
            if self.live is not None:
                self.live.send(result, bundle.timestamp)
        lat_row = self.latency.row(bundle.trigger_frame, bundle.timestamp, sb.first_arrival, sb.last_arrival,
                                   t_est, len(sb.frames), len(bundle.missing_cameras))
        if self.recorder is not None:
            items = [("data2d_distorted", self._rows(fr, bundle.trigger_frame, bundle.timestamp, FLAG_TRACKED))
                     for fr in sb.frames.values()]
            items += self._dvs_cov_items(bundle)
            if result is not None:
                k, a = result_rows(result, bundle.timestamp)
                items += [("kalman_estimates", k), ("data_association", a)]
            items.append(("latency", lat_row))
            self.recorder.append_many(items)
        if result is not None:
            if self.keep_results:
                self.results.append(result)
            if self.on_result is not None:
                try:
                    self.on_result(result)
                except Exception as exc:
                    self.callback_errors += 1
                    if self.callback_errors <= 10:
                        self.log(f"on_result callback failed: {exc!r}")
