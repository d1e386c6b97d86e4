"""`FrameSynchronizer`: per-camera frames -> one bundle per trigger frame (the package doc,
`flytrack_host.intake.sync`, says how). Its restart placement and drift check live in `restart.py` and
`drift.py`."""

from __future__ import annotations

import math
import statistics
from collections import deque
from collections.abc import Callable, Iterable

from flytrack_host.intake.sync.clock import FixedRateClock, FrameClock
from flytrack_host.intake.sync.drift import _DriftDetection
from flytrack_host.intake.sync.restart import _RestartPlacement
from flytrack_host.intake.sync.state import _Cam, _Pending
from flytrack_host.intake.sync.types import (
    CameraFrame,
    CameraSyncStats,
    SyncedBundle,
    SyncEvent,
    SyncOutput,
    UntrackedFrame,
)
from flytrack_host.tracking.types import FrameBundle


class FrameSynchronizer(_RestartPlacement, _DriftDetection):
    def __init__(
        self,
        camera_indices: Iterable[int],
        fps: float,
        clock: FrameClock | None = None,
        deadline_fraction: float = 0.5,
        dead_timeout_s: float = 0.5,
        start_time: float = 0.0,
        jump_confirm_frames: int = 3,
        max_gap_s: float = 10.0,
        future_tolerance_s: float = 0.5,
        drift_frames: int = 10,
        drift_min_s: float = 0.5,
        late_tolerance_s: float = 0.25,
        tie_window_s: float = 0.5,
        drift_settle_s: float = 0.5,
        early_fraction: float = 1.5,
        early_slack_s: float = 0.005,
        early_confirm_s: float = 0.2,
        reanchor_s: float = 0.2,
        restart_settle_frames: int = 10,
        restart_hold_frames: int = 300,
        on_event: Callable[[SyncEvent], None] | None = None,
    ):
        self.period = 1.0 / fps
        self.clock: FrameClock = clock if clock is not None else FixedRateClock(fps)
        self.deadline_s = deadline_fraction * self.period
        self.dead_timeout_s = dead_timeout_s
        self.jump_confirm = jump_confirm_frames
        self.max_gap = max(2, int(max_gap_s * fps))
        self.future_tolerance_s = future_tolerance_s
        self.future_frames = max(2, int(future_tolerance_s * fps))
        # Evidence for a drift must span at least drift_min_s as well as drift_frames: at high frame
        # rates a busy host or network can shift one camera's arrivals by most of a period for a
        # fraction of a second, which a missed pulse never does (its shift lasts for good).
        self.drift_frames = max(drift_frames, math.ceil(drift_min_s * fps))
        self.late_tolerance_s = late_tolerance_s
        self.tie_window_s = max(tie_window_s, 0.9 * self.period)
        # A trigger frame's arrivals are compared once every live camera delivered it, or this long
        # after the newest frame passed it (a stalled camera's frames then count where they came).
        self.drift_settle = max(3, int(drift_settle_s * fps))
        # Host scheduling jitter makes a camera's lag vary by a few ms: only a frame early by more
        # than that and by more than a period counts (a number more than one ahead).
        self.early_s = early_fraction * self.period + early_slack_s
        self.early_confirm_s = early_confirm_s  # early frames confirm a jump only over this long
        self.lag_window_s = 1.0
        self.reanchor_frames = max(5, int(reanchor_s * fps))
        # A restarted edge is placed once this many frames in a row came paced without a new lowest
        # bound, or (an edge that never catches up) once this many frames were held.
        self.restart_settle = max(2, restart_settle_frames)
        self.restart_hold = max(self.restart_settle + 1, restart_hold_frames)
        self._late_run: deque = deque()  # (first arrival, lag, frame) of recent bundles (fixed-rate re-anchor)
        self.reanchors = 0
        self._arrivals: dict[int, dict[int, float]] = {}
        self._eval_next: int | None = None
        self._quiet_tie = False
        self._edge_numbered: dict[int, bool] = {}
        # After a global jump: the edge-numbered cameras that had sent nothing in the new numbering
        # yet, and its lowest trigger frame seen (see _follows_jump).
        self._to_follow: set[int] = set()
        self._jump_low = 0
        self.cams: dict[int, _Cam] = {i: _Cam(i, True, start_time) for i in camera_indices}
        self.pending: dict[int, _Pending] = {}
        self.last_closed = -1
        self.max_accepted = -1
        self._sync_started: float | None = None
        self.bundles_complete = 0
        self.bundles_deadline = 0

    # --- public -------------------------------------------------------------------------------
    def synchronize(self) -> None:
        """Start (again) the frame-0 tie: the next first frame of each camera is trigger frame 0.
        Call after restarting the trigger, once the cameras went quiet."""
        for cam in self.cams.values():
            cam.offset = cam.last_cf = cam.last_tf = None
            cam.suspects.clear()
            cam.rel_window.clear()
            cam.seen_cf.clear()
            cam.lag_win.clear()
        self._late_run.clear()
        self._arrivals.clear()
        self._eval_next = None
        self._to_follow.clear()
        self._quiet_tie = True
        self._sync_started = None
        self.pending.clear()
        self.last_closed = -1
        self.max_accepted = -1

    def stats(self) -> dict[int, CameraSyncStats]:
        return {i: c.stats for i, c in self.cams.items()}

    def live_cameras(self) -> list[int]:
        return [i for i, c in self.cams.items() if c.alive]

    def add(self, frame: CameraFrame, now: float) -> list[SyncOutput]:
        out: list[SyncOutput] = []
        cam = self.cams.get(frame.camera_index)
        if cam is None:
            return [UntrackedFrame(frame, -1, "unknown_camera")]
        cam.stats.frames += 1
        cam.last_recv = now
        if not cam.alive:
            cam.alive = True
            cam.stats.revivals += 1
            out.append(SyncEvent("alive", cam.index, f"camera {cam.index} is sending again"))
        self._edge_numbered[cam.index] = frame.trigger_frame >= 0
        if frame.restarted and cam.offset is not None and frame.trigger_frame < 0:
            if cam.placing:  # restarted again while still held: those frames placed and recorded first
                out.extend(self._place_held(cam))
            cam.placing, cam.place_best, cam.place_at = [], None, 0  # placed once it caught up (_place)
            cam.lag_win.clear()  # the old edge's lags: stale, and no measure of the new one
        if cam.placing is not None:
            cam.stats.frames -= 1  # counted again when placed
            return out + self._place(cam, frame)
        if cam.last_cf is not None and frame.camera_frame == cam.last_cf:
            cam.stats.duplicate += 1
            # last_tf is set whenever last_cf is (they are always set and cleared together).
            tf = frame.trigger_frame if frame.trigger_frame >= 0 else cam.last_tf
            out.append(UntrackedFrame(frame, tf, "duplicate"))
            return out
        tf = self._map(cam, frame, now)
        reason = self._suspect_reason(cam, frame, tf, now)
        if reason is not None and self._follows_jump(cam, frame, tf):
            reason = None
        if reason is not None:
            cam.suspects.append((frame, tf))
            # A good stream with wrong frames mixed in breaks every streak of suspects; a short gap
            # in the good one (a stalled edge) must not let the wrong ones confirm a jump.
            span = frame.recv_time - cam.suspects[0][0].recv_time
            if (reason != "early" or span >= self.early_confirm_s) and self._confirmed(cam):
                out.extend(self._accept_jump(cam, frame, now))
                # Earlier confirming frames were reported as suspect; tracking resumes next frame.
                out.append(UntrackedFrame(frame, cam.last_tf if cam.last_tf is not None else tf, "clock_jump"))
                return out
            if reason == "future":
                cam.stats.future += 1
            elif reason == "early":
                cam.stats.early += 1
            else:
                cam.stats.suspect += 1
            out.append(UntrackedFrame(frame, tf, reason))
            return out
        cam.suspects.clear()
        cam.seen_cf.append(frame.camera_frame)
        if cam.last_cf is None or frame.camera_frame > cam.last_cf:
            cam.last_cf, cam.last_tf = frame.camera_frame, tf
        self.max_accepted = max(self.max_accepted, tf)
        self._note_lag(cam, frame, tf)
        if frame.trigger_frame < 0 and frame.recv_time >= cam.ahead_check_at:
            cam.ahead_check_at = frame.recv_time + 0.05
            out.extend(self._check_ahead(cam, frame.recv_time))
        out.extend(self._check_drift(cam, frame, tf))
        if tf <= self.last_closed:
            cam.stats.late += 1
            out.append(UntrackedFrame(frame, tf, "late"))
            return out
        p = self.pending.get(tf)
        if p is None:
            deadline = now + self.deadline_s
            others = [c.last_tf for c in self.cams.values() if c is not cam and c.alive and c.last_tf is not None]
            if others and tf > max(others) + 1:
                # Ahead of every other camera: a frame numbered wrongly must not close (and make late)
                # the bundles the others have not delivered yet. It waits for them, or a dead timeout.
                deadline = now + max(self.deadline_s, self.dead_timeout_s)
            p = self.pending[tf] = _Pending({}, now, deadline)
        elif p.deadline > now + self.deadline_s:
            p.deadline = now + self.deadline_s  # another camera reached it: the usual deadline
        if frame.camera_index in p.frames:
            cam.stats.duplicate += 1
            out.append(UntrackedFrame(frame, tf, "duplicate"))
            return out
        p.frames[frame.camera_index] = frame
        if all(i in p.frames for i, c in self.cams.items() if c.alive):
            out.extend(self._close_through(tf, "complete"))
        return out

    def poll(self, now: float) -> list[SyncOutput]:
        """Close bundles whose deadline passed; mark silent cameras dead."""
        out: list[SyncOutput] = []
        for cam in self.cams.values():
            if cam.alive and now - cam.last_recv > self.dead_timeout_s:
                cam.alive = False
                cam.stats.deaths += 1
                msg = f"camera {cam.index} silent for {now - cam.last_recv:.2f} s: marked dead"
                out.append(SyncEvent("dead", cam.index, msg))
        live = [i for i, c in self.cams.items() if c.alive]
        close_to = None
        for tf in sorted(self.pending):
            p = self.pending[tf]
            if p.deadline <= now or (live and all(i in p.frames for i in live)):
                close_to = tf
        if close_to is not None:
            out.extend(self._close_through(close_to, "deadline"))
        return out

    def next_deadline(self) -> float | None:
        if not self.pending:
            return None
        return min(p.deadline for p in self.pending.values())

    def flush(self) -> list[SyncOutput]:
        """Close every pending bundle (at stop); a restarted edge's frames still held are placed by
        the best bound they gave and recorded."""
        out: list[SyncOutput] = []
        for cam in self.cams.values():
            if cam.placing:
                out.extend(self._place_held(cam))
        if self.pending:
            out.extend(self._close_through(max(self.pending), "flush"))
        return out

    # --- mapping ------------------------------------------------------------------------------
    def frame_time(self, tf: int) -> float:
        try:
            t = float(self.clock.frame_to_host_time(tf))
        except Exception:  # a clock model not ready yet
            return math.nan
        return t

    def _lag(self, exclude: int | None = None) -> float:
        lags = [c.lag_ewma for c in self.cams.values() if c.lag_ewma is not None and c.index != exclude]
        return statistics.median(lags) if lags else 0.0

    def _frame_at(self, t: float) -> int:
        # A fixed-rate clock is anchored by then: the first frame mapped (_map) anchors it.
        ref = max(self.max_accepted, 0)
        t_ref = self.frame_time(ref)
        if not math.isfinite(t_ref):
            return ref
        return ref + round((t - t_ref) / self.period)

    def _map(self, cam: _Cam, frame: CameraFrame, now: float) -> int:
        if frame.trigger_frame >= 0:  # the edge's number wins, always
            if isinstance(self.clock, FixedRateClock) and not self.clock.anchored:
                self.clock.anchor(frame.trigger_frame, frame.recv_time)
            return frame.trigger_frame
        if cam.offset is None:
            if self._sync_started is None:
                self._sync_started = frame.recv_time
            # First frames of all cameras come from the same first pulse. After synchronize() the
            # cameras were quiet, so a first frame is pulse 0 however late or bursty it comes (within
            # tie_window_s); otherwise they were running and only most of a period of spread is allowed.
            if self._quiet_tie:
                tie = frame.recv_time - self._sync_started <= self.tie_window_s
            else:
                tie = frame.recv_time - self._sync_started <= self.period * 0.9 and self.max_accepted < 1
            if tie:
                tf = 0  # the frame-0 tie: all cameras' first frames come from the same first pulse
                if isinstance(self.clock, FixedRateClock) and not self.clock.anchored:
                    self.clock.anchor(0, frame.recv_time)
            else:
                tf = self._frame_at(frame.recv_time - self._lag(cam.index))
            cam.offset = frame.camera_frame - tf
        return frame.camera_frame - cam.offset

    def _suspect_reason(self, cam: _Cam, frame: CameraFrame, tf: int, now: float) -> str | None:
        t = self.frame_time(tf)
        if math.isfinite(t) and t > now + self.future_tolerance_s:
            return "future"
        # A frame that continues its camera's counter (and the mapping) is never misnumbered by the
        # edge: if it looks early, the clock model moved (a new snapshot), not the frame.
        d_cf = frame.camera_frame - cam.last_cf if cam.last_cf is not None else 0
        continuous = cam.last_tf is not None and 0 < d_cf <= 3 and tf - cam.last_tf == d_cf
        w = cam.lag_win
        while w and w[0][0] < frame.recv_time - self.lag_window_s:
            w.popleft()
        if math.isfinite(t) and len(w) >= 3 and not continuous:
            floor = w.min1()
            # Earlier than its camera's frames came in the last second. (A camera late for longer than
            # that, back on time after a gap, is rejected for up to early_confirm_s, then confirmed.)
            if frame.recv_time - t < floor - self.early_s:
                return "early"  # claims a pulse that had not happened when such frames arrive
        if not math.isfinite(t) and self.max_accepted >= 0 and tf > self.max_accepted + self.future_frames:
            return "future"
        if cam.last_cf is None or cam.last_tf is None:
            return None
        d_cf = frame.camera_frame - cam.last_cf
        d_tf = tf - cam.last_tf
        if d_cf < 0 and d_tf == d_cf and (
            (math.isfinite(t) and now - t < self.late_tolerance_s)
            or (-d_cf < (cam.seen_cf.maxlen or 0) and frame.camera_frame not in cam.seen_cf
                and cam.seen_cf and frame.camera_frame > min(cam.seen_cf))
        ):
            # Reordered or held up in the network, numbering intact: just late. A frame number not
            # seen yet, a little behind the newest, is such a frame however long it was held; a
            # restarted counter repeats numbers already seen.
            return None
        if d_cf < 0 or d_cf > self.max_gap or d_tf <= 0 or d_tf - d_cf > self.max_gap:
            return "discontinuity"
        return None

    def _note_lag(self, cam: _Cam, frame: CameraFrame, tf: int) -> None:
        t = self.frame_time(tf)
        if not math.isfinite(t):
            return
        w = cam.lag_win
        w.append((frame.recv_time, frame.recv_time - t, tf))
        while w and w[0][0] < frame.recv_time - self.lag_window_s:
            w.popleft()

    def _check_ahead(self, cam: _Cam, now: float) -> list[SyncOutput]:
        """A camera whose frames all arrive well before their mapped pulses, compared with the other
        cameras' arrivals (so a clock-model step, common to all, cancels), is mapped ahead: a restarted
        edge whose first frames came late and bunched up, or a counter that jumped. Frames cannot come
        before their pulse: move its mapping back by the whole periods it is ahead."""
        w = cam.lag_win
        if cam.offset is None or len(w) < 8 or w[-1][0] - w[0][0] < 0.1:
            return []
        model = self._lag_model()
        if model is None:
            return []
        others = [c.lag_win.min_lag(*model, since=now - self.lag_window_s)
                  for c in self._lag_peers(cam, now) if len(c.lag_win) >= 8]
        if not others:
            return []
        mine = w.min_lag(*model)
        # Against the fastest other camera: ahead of all of them, not of their middle (one other
        # camera still late, e.g. a restarted edge working off its queue, must not make a camera
        # on time look ahead).
        d = mine - min(others)
        # Ahead of the others (a clock step moves all cameras alike) and before its own pulses (other
        # cameras late for longer than the window, in a stall, make no camera arrive before its pulse).
        if d >= -self.early_s or mine >= -self.early_s:
            return []
        k = round(-d / self.period)
        if k < 1:
            return []
        # Still catching up (a joiner's or a restarted edge's first frames came late and bunched, and
        # it works off its queue): its lags keep falling, and moving it now would stop short, leaving
        # it ahead by less than the threshold, for good. It is moved once the last 0.1 s brought no
        # lag lower than the ones before by more than a quarter period (`mine` is the window's least).
        lag = self._lag_now()
        assert lag is not None  # the model is ready (checked above)
        if mine < min((lag(x) for x in w if x[0] <= now - 0.1), default=-math.inf) - 0.25 * self.period:
            return []
        cam.offset += k
        if cam.last_tf is not None:
            cam.last_tf -= k
        w.clear()
        cam.rel_window.clear()
        cam.stats.ahead += 1
        note = ""
        if cam.restarted_at is not None and now - cam.restarted_at < 3.0:
            cam.stats.missed = max(0, cam.stats.missed - k)  # its gap was counted from the wrong mapping
            note = " (after its restart)"
        return [SyncEvent("ahead", cam.index, f"camera {cam.index}: frames numbered {k} ahead of their arrival "
                                              f"against the other cameras{note}: re-mapped")]

    def _lag_now(self) -> Callable[[tuple], float] | None:
        """A lag window entry's lag to the trigger clock as it is now. The clock model is refitted, and
        restarts after a jump (a loaded host's late clock replies: it stepped by tens of ms at load
        11): lags noted before and after a step are not comparable, and one camera's newest frame
        after it, against the others' older ones, looked frames ahead (two healthy cameras re-mapped
        by 2 and 4, 270 frames misnumbered). The model is a line in the frame number; None while it
        is not ready."""
        model = self._lag_model()
        if model is None:
            return None
        t_ref, ref, slope = model
        return lambda x: x[0] - (t_ref + (x[2] - ref) * slope)

    def _lag_model(self) -> tuple[float, int, float] | None:
        """(t_ref, ref, slope) of `_lag_now`'s line: frame `ref` at host time `t_ref`, `slope` s/frame."""
        ref = max(self.max_accepted, 0)
        t_ref = self.frame_time(ref)
        t_far = self.frame_time(ref + 1000)
        if not (math.isfinite(t_ref) and math.isfinite(t_far)):
            return None
        return t_ref, ref, (t_far - t_ref) / 1000.0

    def _lag_peers(self, cam: _Cam, now: float) -> list[_Cam]:
        """The other cameras whose arrival lags describe now: alive, placed, and heard from within the
        lag window (a camera's window is only pruned when it delivers: one held or silent for a while
        keeps lags from before, perhaps from before a clock-model restart, and would tilt the others)."""
        return [c for c in self.cams.values() if c is not cam and c.alive and c.placing is None and c.lag_win
                and c.lag_win[-1][0] >= now - self.lag_window_s]

    def _check_reanchor(self, f: int, first_arrival: float, n_frames: int) -> list[SyncOutput]:
        """Fixed-rate clock only: re-anchor after a pause of every camera (see the package doc)."""
        clock = self.clock
        if not isinstance(clock, FixedRateClock) or not clock.anchored:
            return []
        lag = first_arrival - clock.frame_to_host_time(f)
        run = self._late_run
        if -2 * self.period < lag < 0 and n_frames >= 2:  # one camera alone may be misnumbered
            # A frame cannot come before its pulse: the first frame (the anchor) came late. The clock
            # follows the earliest arrivals, so no estimate is timed before its own frame.
            clock.start_time = (clock.start_time or 0.0) + lag
            run.clear()
            return []
        if lag <= max(2 * self.period, 0.01):
            run.clear()
            return []
        run.append((first_arrival, lag, f))
        if len(run) < self.reanchor_frames:
            return []
        # Paced: a burst after a stall delivers its frames together; a resumed rig a period apart.
        if run[-1][0] - run[0][0] < 0.5 * (run[-1][2] - run[0][2]) * self.period:
            run.popleft()
            return []
        shift = min(x[1] for x in run)
        clock.start_time = (clock.start_time or 0.0) + shift
        run.clear()
        for c in self.cams.values():
            c.lag_win.clear()
            # Each camera's lag is learnt again from its next frame: the estimate (its steps bounded
            # against stalls) had followed only part of the pause, so taking the shift off it would
            # leave it that far below the truth and misplace a camera joining in the next second.
            c.lag_ewma = None
        self.reanchors += 1
        return [SyncEvent("reanchor", -1, f"fixed-rate clock re-anchored at trigger frame {f}: frames came "
                                          f"{shift * 1e3:.0f} ms after their expected time (a pause of the cameras?)")]

    def _confirmed(self, cam: _Cam) -> bool:
        s = cam.suspects
        if len(s) < self.jump_confirm:
            return False
        s = s[-self.jump_confirm :]
        for (a, ta), (b, tb) in zip(s, s[1:], strict=False):
            d_cf = b.camera_frame - a.camera_frame
            if not (0 < d_cf <= self.max_gap and 0 < tb - ta <= self.max_gap):
                return False
        return True

    def _follows_jump(self, cam: _Cam, frame: CameraFrame, tf: int) -> bool:
        """A camera that had sent nothing in the trigger's new numbering when the jump was confirmed
        (it is slower than the confirming one) takes it on its first such frame, as the cameras already
        seeing it did at once: a jump of its own would close the bundles the others filled since and
        open them again without them. Only a number of the new numbering, not ahead of it, counts (the
        camera is behind)."""
        if cam.index not in self._to_follow or frame.trigger_frame < 0:
            return False
        if not self._jump_low <= tf <= self.max_accepted:
            return False
        self._to_follow.discard(cam.index)
        return True

    def _accept_jump(self, cam: _Cam, frame: CameraFrame, now: float) -> list[SyncOutput]:
        out: list[SyncOutput] = []
        old_tf = cam.last_tf
        cam.stats.clock_jumps += 1
        cam.lag_win.clear()
        if frame.trigger_frame >= 0:
            new_tf = frame.trigger_frame
            global_jump = True  # the trigger's own count moved: every camera sees it
        else:
            # The camera's counter restarted or jumped: map it again by arrival time.
            new_tf = self._frame_at(frame.recv_time - self._lag(cam.index))
            cam.offset = frame.camera_frame - new_tf
            global_jump = False
        if global_jump:
            out.extend(self._close_through(max(self.pending), "flush") if self.pending else [])
            self._arrivals.clear()  # drift comparisons start again in the new numbering
            for c in self.cams.values():
                c.lag_win.clear()
            self._eval_next = None
            if new_tf <= self.last_closed:
                self.last_closed = new_tf
            self.max_accepted = new_tf
            if isinstance(self.clock, FixedRateClock):
                self.clock.anchor(new_tf, frame.recv_time - self._lag(cam.index))
            self._jump_low = min([tf for _, tf in cam.suspects] + [new_tf])
            self._to_follow = set()
            for other in self.cams.values():
                if other is cam:
                    continue
                # Cameras already seeing the new numbering follow at once instead of waiting; the others
                # (nothing in it yet, or a far suspect) on their first frame in it (_follows_jump).
                o_frame, o_tf = other.suspects[-1] if other.suspects else (None, 0)
                if o_frame is not None and o_frame.trigger_frame >= 0 and abs(o_tf - new_tf) <= self.jump_confirm + 2:
                    other.last_cf, other.last_tf = o_frame.camera_frame, o_tf
                    other.suspects.clear()
                else:
                    self._to_follow.add(other.index)
        else:
            self.max_accepted = max(self.max_accepted, new_tf)
        cam.last_cf, cam.last_tf = frame.camera_frame, new_tf
        cam.suspects.clear()
        out.append(SyncEvent(
            "clock_jump", cam.index,
            f"camera {cam.index}: frame numbers jumped from trigger frame {old_tf} to {new_tf}; mapping re-established",
            global_jump=global_jump,
        ))
        return out

    # --- closing ------------------------------------------------------------------------------
    def _close_through(self, tf: int, why: str) -> list[SyncOutput]:
        out: list[SyncOutput] = []
        for f in sorted(k for k in self.pending if k <= tf):
            p = self.pending.pop(f)
            closed_by = why if f == tf else ("deadline" if why != "flush" else "flush")
            missing = tuple(i for i, c in self.cams.items() if c.alive and i not in p.frames)
            if closed_by == "complete" and not missing:
                self.bundles_complete += 1
            else:
                self.bundles_deadline += 1
            for i in p.frames:
                self.cams[i].stats.tracked += 1
            arr = sorted(fr.recv_time for fr in p.frames.values())
            # The second earliest arrival when there are several: one misnumbered frame cannot move it.
            events = self._check_reanchor(f, arr[1] if len(arr) > 1 else arr[0], len(arr))
            bundle = FrameBundle(
                trigger_frame=f,
                timestamp=self.frame_time(f),
                detections={i: fr.points for i, fr in p.frames.items()},
                missing_cameras=missing,
            )
            out.append(SyncedBundle(bundle, p.frames, p.first_arrival,
                                    max(fr.recv_time for fr in p.frames.values()), closed_by))
            out.extend(events)
        self.last_closed = max(self.last_closed, tf)
        return out
