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
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import typer

from flytrack_host import hostclock
from flytrack_host.camera import Camera
from flytrack_host.eventcam.observations import DvsObservations
from flytrack_host.latency import LatencyStats
from flytrack_host.live import LiveSender
from flytrack_host.outputs.launch import HTTP_HELP, POSE_HELP, THUMBS_HELP, LiveOutputs, OutputsError
from flytrack_host.ratelog import RateLimitedLog
from flytrack_host.receiver import DvsSlice, Receiver, StatusReport
from flytrack_host.recording.schema import (
    ASSOCIATION,
    CAM_INFO,
    CAMERA_STATUS,
    COV_NAMES,
    DATA2D,
    FLAG_DVS,
    FLAG_INCOMPLETE,
    FLAG_LATE,
    FLAG_REJECTED,
    FLAG_TRACKED,
    FLAG_TRUNCATED,
    KALMAN,
    TRIGGER_CLOCK,
)
from flytrack_host.recording.writer import Recorder
from flytrack_host.rig import RigConfig
from flytrack_host.sync import (
    CameraFrame,
    FixedRateClock,
    FrameClock,
    FrameSynchronizer,
    SyncedBundle,
    SyncEvent,
    UntrackedFrame,
)
from flytrack_host.tracking.params import TrackingParams
from flytrack_host.tracking.types import FrameBundle, FrameResult

log = logging.getLogger("flytrack.pipeline")


TrackerFactory = Callable[[Mapping[int, Camera], TrackingParams, float], Any]
_POINT_FIELDS = ("x_dist", "y_dist", "x_undist", "y_undist", "area", "peak_diff", "orientation",
                 "eccentricity", "cur_val", "mean_val", "sumsq_val")
_FLOAT_FIELDS = tuple(f for f in _POINT_FIELDS if f != "cur_val")
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


class ResultSink(Protocol):
    """A consumer of every tracked frame: a live output (event stream, VR pose) or the actuation rules.

    `on_frame` runs on the tracking thread right after the tracker, so it must only hand the frame on
    (append to a bounded queue, a non-blocking send) and return: a slow sink would delay tracking.
    `frame_time` is the host time of the frame's trigger pulse (the clock model's), `estimate_time` the
    host time the estimate was made; their difference is the trigger-to-estimate latency. An exception
    is caught, counted in `sink_errors` and logged (rate-limited); the sink stays attached. `close` is
    called once when the pipeline stops.
    """

    def on_frame(self, result: FrameResult, frame_time: float, estimate_time: float) -> None: ...

    def close(self) -> None: ...


def default_tracker_factory(cameras: Mapping[int, Camera], params: TrackingParams, period: float) -> Any:
    mod = importlib.import_module("flytrack_host.tracking.tracker")
    return mod.Tracker(cameras, params, period)


_INT_LIMITS = {name: np.iinfo(DATA2D[name]) for name in DATA2D.names if DATA2D[name].kind in "iu"}
_FALLBACK = {"trigger_frame": -1}  # out of range: "not mapped"; unsigned fields: 0


def _fit(name: str, value: int, bad: list[str]) -> int:
    """`value` if the DATA2D column holds it, else a fallback, and the column is named in `bad`."""
    lim = _INT_LIMITS[name]
    v = int(value)
    if lim.min <= v <= lim.max:
        return v
    bad.append(f"{name}={v}")
    return _FALLBACK.get(name, 0)


def data2d_rows(fr: CameraFrame, tf: int, timestamp: float, flags: int,
                range_errors: list[str] | None = None) -> np.ndarray:
    """One DATA2D row per point of a camera frame (one NaN row for a frame without points).

    Every integer is range-checked before it is written: a value the column cannot hold (a wild frame
    number from a misbehaving edge) is stored as -1 (trigger frame) or 0 and named in `range_errors`,
    and the row is flagged rejected; the frame is never lost."""
    pts = fr.points
    n = len(pts)
    bad: list[str] = []
    rows = np.zeros(max(n, 1), dtype=DATA2D)
    rows["trigger_frame"] = _fit("trigger_frame", tf, bad)
    rows["camera_index"] = _fit("camera_index", fr.camera_index, bad)
    rows["camera_frame"] = _fit("camera_frame", fr.camera_frame, bad)
    rows["timestamp"] = timestamp
    rows["cam_received_timestamp"] = fr.recv_time
    rows["device_timestamp_ns"] = _fit("device_timestamp_ns", fr.device_timestamp_ns, bad)
    rows["edge_recv_ns"] = _fit("edge_recv_ns", fr.edge_recv_ns, bad)
    rows["edge_done_ns"] = _fit("edge_done_ns", fr.edge_done_ns, bad)
    rows["n_points"] = _fit("n_points", n, bad)
    rows["total_points"] = _fit("total_points", fr.total_points, bad)
    if bad:
        flags = (flags & ~FLAG_TRACKED) | FLAG_REJECTED
        if range_errors is not None:
            range_errors.extend(bad)
    rows["flags"] = (flags | (FLAG_TRUNCATED if fr.truncated else 0) | (FLAG_INCOMPLETE if fr.incomplete else 0)
                     | (FLAG_DVS if fr.dvs else 0))
    if n:
        rows["frame_pt_idx"] = np.arange(n)
        names = pts.dtype.names or ()
        for f in _POINT_FIELDS:
            if f in names:
                rows[f] = pts[f]
    else:
        for f in _FLOAT_FIELDS:
            rows[f] = np.nan
    return rows


_COV_IU = np.triu_indices(6)  # COV_NAMES order (recording.schema.cov_upper)


def result_rows(result: FrameResult, timestamp: float) -> tuple[np.ndarray, np.ndarray]:
    """KALMAN and ASSOCIATION rows of a frame, column by column (the tracking thread makes them for
    every frame: one row at a time cost ~0.1 ms a frame more with 3 objects)."""
    est = result.estimates
    n = len(est)
    k = np.zeros(n, dtype=KALMAN)
    if n:
        states = np.array([np.asarray(e.state, dtype=np.float64)[:6] for e in est]).reshape(n, 6)
        covs = np.array([np.asarray(e.covariance, dtype=np.float64)[:6, :6] for e in est]).reshape(n, 6, 6)
        k["obj_id"] = [e.obj_id for e in est]
        k["trigger_frame"] = result.trigger_frame
        k["timestamp"] = timestamp
        for j, name in enumerate(("x", "y", "z", "xvel", "yvel", "zvel")):
            k[name] = states[:, j]
        upper = covs[:, _COV_IU[0], _COV_IU[1]]
        for j, name in enumerate(COV_NAMES):
            k[name] = upper[:, j]
        k["n_cameras"] = [e.n_cameras for e in est]
    a = np.zeros(len(result.associations), dtype=ASSOCIATION)
    for i, asc in enumerate(result.associations):
        a[i] = (asc.obj_id, result.trigger_frame, asc.camera_index, asc.point_index)
    return k, a


def default_recording_path(rig: RigConfig) -> Path:
    stamp = time.strftime("%Y%m%d_%H%M%S")
    return rig.recording_dir / f"{stamp}_{rig.name}.flytrack"


class HostPipeline:
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
            try:
                h5 = self.recorder.stop(finalize=True)
            except Exception as exc:  # e.g. a full disk: the raw files stay, `recording recover` later
                self.recording_error = f"{exc!r}"
                log.error("finalising the recording failed: %r; the raw files in %s are kept",
                          exc, self.recording_path)
        if self.receiver is not None:
            self.receiver.close()
        if self.live is not None:
            self.live.close()
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
        self.recorder = Recorder(self.recording_path, self.rig.recording.flush_interval_s, meta=meta)
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

    def _dvs_slice(self, item: DvsSlice) -> None:
        """An event camera's time slice: kept, to give its clusters to the tracker at the trigger
        frames it covers (flytrack_host.eventcam)."""
        self.dvs_slices[item.camera_index] = self.dvs_slices.get(item.camera_index, 0) + 1
        if self.dvs_obs is not None:
            self.dvs_obs.add(item, self._frame_of_host_time)

    def _frame_of_host_time(self, t: float) -> float:
        """The trigger clock model inverted: host time -> trigger frame (NaN before it is known)."""
        clock = self.sync.clock if self.sync is not None else None
        if clock is None:
            return math.nan
        t0, t1 = float(clock.frame_to_host_time(0)), float(clock.frame_to_host_time(1000))
        if not (math.isfinite(t0) and math.isfinite(t1)) or t1 <= t0:
            return math.nan
        return (t - t0) / ((t1 - t0) / 1000.0)

    def _add_dvs(self, sb: SyncedBundle, count: bool = True) -> None:
        """Event cameras' observations join the bundle of frame cameras (a rig may mix them)."""
        if self.dvs_obs is None:
            return
        tf = sb.bundle.trigger_frame
        for ci in self.dvs_obs.indices:
            got = self.dvs_obs.frame(ci, tf)
            if got is not None:
                fr, cov = got
                if count:
                    self.dvs_obs.count(ci, len(fr.points))
                sb.frames[ci] = fr
                sb.bundle.detections[ci] = fr.points
                # their own covariance is their measurement noise, and they never start a track
                sb.bundle.point_cov[ci] = cov

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
            if self.recorder is not None:
                self.recorder.append_many([("data2d_distorted", self._rows(fr, bundle.trigger_frame, bundle.timestamp,
                                                                           FLAG_LATE)) for fr in sb.frames.values()])
            if self.dvs_bundles.maxlen:  # tracked later, by the comparison, with its event points
                self._add_dvs(sb, count=False)
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

    # --- reporting ----------------------------------------------------------------------------
    def status_line(self) -> str:
        parts = [f"tracked {self.frames_tracked}", f"objects {self.n_objects}"]
        if self.receiver is not None and self.sync is not None:
            rs = self.receiver.stats
            ss = self.sync.stats()
            for c in self.rig.cameras:
                if c.kind == "dvs":
                    r = rs.cameras[c.index]
                    parts.append(f"{c.name}: slices {r.dvs_slices} events {r.status_frames_seen}")
                    continue
                r, s = rs.cameras[c.index], ss[c.index]
                alive = "" if self.sync.cams[c.index].alive else " DEAD"
                parts.append(f"{c.name}: rx {r.frames} lost {r.lost} late {s.late} bad {r.malformed} "
                             f"dup {r.duplicated + s.duplicate} reo {r.reordered}{alive}")
            rej = rs.rejected_address + rs.rejected_camera
            if rej:
                parts.append(f"rejected {rej}")
        if self.recorder is not None:
            parts.append(self.recorder_status())
        if self.tracker_errors:
            parts.append(f"tracker errors {self.tracker_errors}")
        if self.loop_errors:
            parts.append(f"ERRORS {self.loop_errors}")
        s = self.latency.summary()
        if "total_p50_ms" in s:
            parts.append(f"latency P50 {s['total_p50_ms']:.1f} P99 {s['total_p99_ms']:.1f} ms")
        for src in self.status_sources:
            try:
                parts.append(src())
            except Exception as exc:  # a status line must never take the run down
                parts.append(f"status error {exc!r}")
        return " | ".join(parts)

    def recorder_status(self) -> str:
        """Queue depth of the recorder, and what it lost (write errors, full queue) if anything."""
        rec = self.recorder
        if rec is None:
            return "not recording"
        st = rec.stats
        out = f"rec queue {rec.queue_bytes / 1e6:.1f} MB"
        lost = sum(st.dropped_rows.values())
        if st.write_errors:
            out += f" WRITE ERRORS {st.write_errors} ({rec.last_error})"
        if lost or st.dropped_log_lines:
            out += f" LOST {lost} rows"
        return out

    def _why_nothing(self) -> list[str]:
        """Reasons, with numbers, that a run whose points arrived produced no estimate."""
        stats = getattr(self.tracker, "stats", None)
        if self.n_estimates or not isinstance(stats, dict) or not stats.get("points"):
            return []
        from flytrack_host.tracking.diagnosis import why_no_estimates

        return why_no_estimates(stats, self.cameras, self.params)

    def summary(self, recording_h5: Path | None = None) -> dict[str, Any]:
        rs = self.receiver.stats if self.receiver else None
        out: dict[str, Any] = {
            "why_nothing": list(self.why_nothing),
            "estimates": self.n_estimates,
            "duration_s": (self._stopped_at or hostclock.now()) - self._started_at,
            "frames_tracked": self.frames_tracked,
            "bundles_complete": self.sync.bundles_complete if self.sync else 0,
            "bundles_deadline": self.sync.bundles_deadline if self.sync else 0,
            "untracked": dict(self.untracked),
            "tracker_errors": self.tracker_errors,
            "tracker_resets": self.tracker_resets,
            "loop_errors": self.loop_errors,
            "wall_clock_steps": self.wall_steps,
            "stalls": self.stalls,
            "behind_skipped": self.behind_skipped,
            "range_errors": self.range_errors,
            "log_counts": self.warn.counts,
            "sink_errors": self.sink_errors,
            "latency": self.latency.summary(),
            "latency_text": self.latency.format(),
            "recording": str(recording_h5) if recording_h5 else (str(self.recording_path) if self.record else None),
            "recording_error": self.recording_error,
        }
        if rs is not None:
            out["receiver"] = {
                "datagrams": rs.datagrams, "rejected_address": rs.rejected_address,
                "rejected_camera": rs.rejected_camera, "malformed_unattributed": rs.malformed_unattributed,
                "internal_errors": rs.internal_errors,
                "errors_by_name": dict(rs.errors_by_name),
                "cameras": {i: asdict(c) for i, c in rs.cameras.items()},
            }
        if self.sync is not None:
            out["sync"] = {i: asdict(s) for i, s in self.sync.stats().items()}
        if self.dvs_obs is not None:
            out["dvs"] = self.dvs_obs.stats()
        if self.live is not None:
            out["live"] = asdict(self.live.stats)
        if self.recorder is not None:
            out["recorder"] = asdict(self.recorder.stats)
        return out


# --- `flytrack run` -------------------------------------------------------------------------------


def calibration_problems(rig: RigConfig, cameras: Mapping[int, Camera]) -> list[str]:
    """What is missing for 3D tracking: no calibration at all, or rig cameras absent from it."""
    if not cameras:
        where = f" ({rig.calibration_path} has none of the rig's cameras)" if rig.calibration_path else ""
        return [f"no calibration{where}: recording 2D data only, NO 3D tracking"]
    missing = [f"{c.index} ({c.calib_name})" for c in rig.cameras if c.index not in cameras]
    if missing:
        return [f"camera(s) {', '.join(missing)} are not in the calibration {rig.calibration_path}: their points "
                "cannot be used for 3D"]
    return []


def load_cameras(rig: RigConfig) -> dict[int, Camera]:
    """Calibration file of the rig -> camera_index -> Camera (empty without a calibration)."""
    path = rig.calibration_path
    if path is None:
        return {}
    from flytrack_host.calibration.formats import load_calibration

    by_name = load_calibration(path)
    cams = {}
    for c in rig.cameras:
        if c.calib_name in by_name:
            cams[c.index] = by_name[c.calib_name]
    return cams



def run_command(
    rig_path: Path = typer.Argument(..., help="The rig TOML file."),
    seconds: float | None = typer.Option(None, "--seconds", help="Stop after this many seconds (default: Ctrl-C)."),
    bind: str | None = typer.Option(None, help="Listen on HOST:PORT instead of the rig's host.listen."),
    recording: Path | None = typer.Option(None, help="Recording folder (default: in the rig's recording folder)."),
    no_record: bool = typer.Option(False, "--no-record", help="Do not record."),
    dead_timeout_s: float = typer.Option(0.5, help="A camera silent this long is marked dead."),
    no_trigger: bool = typer.Option(
        False, "--no-trigger",
        help="Do not open the trigger: fixed-rate clock anchored at the first frame (no trigger latency).",
    ),
    trigger_port: str | None = typer.Option(None, help="Serial port of the trigger instead of the rig's trigger.port."),
    trigger_reset_wait: float | None = typer.Option(
        None, help="Seconds to wait after opening the trigger port (default 2 for a board, 0 for a pty)."),
    http: str = typer.Option("127.0.0.1:8397", "--http", help=HTTP_HELP),
    pose: str | None = typer.Option(None, "--pose", help=POSE_HELP),
    pose_rate: float = typer.Option(200.0, "--pose-rate", help="Pose datagrams per second."),
    pose_lead_ms: float = typer.Option(0.0, "--pose-lead-ms", help="Extrapolate the pose this far past now."),
    pose_lock: str = typer.Option("auto", "--pose-lock", help="auto (oldest live object), all, or an obj_id."),
    thumbnails: float = typer.Option(0.0, "--thumbnails", help=THUMBS_HELP),
    rules: Path | None = typer.Option(
        None, "--rules", help="Closed-loop rules file (default: the rig's `rules`); its actions drive the rig's "
        "[[actuators]]."),
    skip_bad_rules: bool = typer.Option(
        False, "--skip-bad-rules", help="Run with the rules that are valid; each bad one is reported, logged in "
        "the recording and counted (default: a bad rules file stops the run before it starts)."),
) -> None:
    """Run the host live: open the trigger, receive, synchronise, track, serve live estimates and record
    until Ctrl-C.

    Without a trigger board, pass --no-trigger (frames are timed by a fixed-rate clock anchored at the
    first frame), or use a rig file with [trigger] kind = "software"."""
    import signal

    from rich.console import Console
    from rich.live import Live

    from flytrack_host.rig import RigError, load_rig

    console = Console()
    try:
        outputs = LiveOutputs.from_options(http=http, pose=pose, pose_rate=pose_rate, pose_lead_ms=pose_lead_ms,
                                           pose_lock=pose_lock, thumbnails_every_s=thumbnails)
    except OutputsError as exc:
        console.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    try:
        rig = load_rig(rig_path)
    except RigError as exc:
        console.print(f"[red]error[/red] {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    try:
        cameras = load_cameras(rig)
    except Exception as exc:
        console.print(f"[red]error[/red] calibration {rig.calibration_path}: {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    for problem in calibration_problems(rig, cameras):
        Console(stderr=True).print(f"[yellow]warning[/yellow] {problem}", highlight=False, soft_wrap=True)
    from flytrack_host.actuation.cli import rules_for_run

    run_rules = rules_for_run(rig, rules, skip_bad_rules)  # a bad rules file exits 2 here unless skipped
    session = None
    if not no_trigger:
        from flytrack_host.trigger.common import TriggerError
        from flytrack_host.trigger_session import TriggerSession

        session = TriggerSession(rig.trigger, port=trigger_port, reset_wait_s=trigger_reset_wait)
        try:
            session.open()  # before anything is recorded: a trigger problem leaves no empty recording
        except TriggerError as exc:
            err = Console(stderr=True)
            err.print(f"[red]error[/red] trigger ({rig.trigger.kind}): {exc}", highlight=False, soft_wrap=True)
            err.print(f"no trigger board? run without one: flytrack run {rig_path} --no-trigger", highlight=False,
                      soft_wrap=True)
            raise typer.Exit(code=2) from None
    pipe = HostPipeline(rig, cameras, bind=bind, record=not no_record, recording_path=recording,
                        rig_text=Path(rig_path).read_text(encoding="utf-8"), dead_timeout_s=dead_timeout_s,
                        clock=session.clock if session else None, fps=session.fps if session else None,
                        hold_until_synchronized=session is not None)
    engine = run_rules.engine(pipe.fps, session) if run_rules is not None else None
    try:
        outputs.attach(pipe, echo=lambda s: None)  # printed after the first line below
        pipe.start()
    except OSError as exc:
        if session is not None:
            session.close()
        for sink in pipe.sinks:
            sink.close()
        where = f"{bind or rig.host.listen} (features) or {http} (live outputs)"
        console.print(f"[red]error[/red] cannot listen on {where}: {exc}", highlight=False)
        raise typer.Exit(code=2) from None
    if engine is not None:  # after start: its messages go into the recording's log too
        engine.attach(pipe)
        engine.start()
    if session is not None:
        session.attach(pipe)
        try:
            session.start(pipe)
        except (TriggerError, OSError) as exc:
            session.close()
            pipe.stop()
            Console(stderr=True).print(f"[red]error[/red] trigger did not start: {exc}", highlight=False,
                                       soft_wrap=True)
            raise typer.Exit(code=2) from None
    host, port = pipe.address
    # Plain first line, so scripts (and tests) can find the port and the recording.
    print(f"listening on {host}:{port}; recording to {pipe.recording_path if pipe.record else '-'}", flush=True)
    for line in outputs.started:
        print(line, flush=True)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    end = None if seconds is None else time.monotonic() + seconds
    try:
        if console.is_terminal:
            with Live(pipe.status_line(), console=console, refresh_per_second=4, transient=False) as live:
                while not stop.is_set() and (end is None or time.monotonic() < end) and pipe.running:
                    stop.wait(0.25)
                    live.update(pipe.status_line())
        else:
            last = 0.0
            while not stop.is_set() and (end is None or time.monotonic() < end) and pipe.running:
                stop.wait(0.25)
                if time.monotonic() - last > 5:
                    print(pipe.status_line(), flush=True)
                    last = time.monotonic()
    except KeyboardInterrupt:
        pass
    finally:
        if session is not None:
            session.stop()  # the cameras stop with the trigger; pending frames are tracked by pipe.stop()
        summary = pipe.stop()
    console.print(pipe.status_line(), highlight=False)
    console.print(summary["latency_text"], highlight=False)
    for w in summary.get("why_nothing") or []:
        Console(stderr=True).print(f"[yellow]warning[/yellow] no estimates: {w}", highlight=False, soft_wrap=True)
    if session is not None:
        t = session.summary()
        m = t["clock_model"]
        resid = f"{m['residual_us']:.1f} us over {m['n_samples']:.0f} samples" if m else "no fit"
        console.print(f"trigger: {t['fps']:.6f} fps; clock residual {resid}; {t['clock_samples']} clock samples, "
                      f"{t['clock_errors']} errors, lost {t['lost']}, device restarts {t['device_restarts']}",
                      highlight=False)
    if summary["recording"]:
        console.print(f"recording: {summary['recording']}", highlight=False)
    rs = summary.get("recorder") or {}
    lost = sum(rs.get("dropped_rows", {}).values())
    if rs.get("write_errors") or lost or summary.get("recording_error"):
        console.print(f"[red]recording incomplete[/red]: {rs.get('write_errors', 0)} write errors, {lost} rows lost"
                      + (f"; not finalised ({summary['recording_error']}): run `flytrack recording recover`"
                         " (its --out writes the file on another disk)"
                         if summary.get("recording_error") else ""), highlight=False)
        raise typer.Exit(code=RECORDING_INCOMPLETE_EXIT)  # scripts must not take this run for a good one
