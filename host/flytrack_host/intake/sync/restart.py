"""Placing a restarted edge: its first frames are held until it caught up, then its counter is tied
to the trigger frames by the least lag the cameras have (see the package doc, `flytrack_host.intake.sync`)."""

from __future__ import annotations

import math

from flytrack_host.intake.sync.state import _Cam
from flytrack_host.intake.sync.types import CameraFrame, SyncEvent, SyncOutput


class _RestartPlacement:
    """`FrameSynchronizer`'s placement of a restarted edge (a mixin: it works on the synchroniser's
    state and calls its mapping methods)."""

    def _floor_lag(self, cam: _Cam, now: float) -> float:
        """The least lag to the trigger clock a frame has now: the lowest of the other cameras' last
        few frames (the fastest camera's). Their recent frames only: on a loaded host the simulated
        cameras, the edges and the trigger clock model each drift by tens of ms within a second, so
        a floor over a longer span places a restart several frames off; what the other cameras
        deliver at the same moment moves with all of that. The usual lag when no other camera has any."""
        lag = self._lag_now()
        lows = [min(lag(x) for x in list(c.lag_win)[-5:]) for c in self._lag_peers(cam, now)] if lag else []
        return min(lows) if lows else self._lag(cam.index)

    def _place(self, cam: _Cam, frame: CameraFrame) -> list[SyncOutput]:
        """Hold a restarted edge's frame; place the edge once it caught up (see the package doc).

        Frame c arriving at r answered a pulse no later than the one at r - floor lag, so camera frame
        0 is at most that trigger frame - c. While the edge works off its queue every frame lowers
        this bound (they come bunched); once it caught up they come paced and the bound stays.
        """
        held = cam.placing
        assert held is not None
        held.append(frame)
        bound = None
        if math.isfinite(self.frame_time(max(self.max_accepted, 0))):  # else the clock model is not ready
            bound = self._frame_at(frame.recv_time - self._floor_lag(cam, frame.recv_time)) - frame.camera_frame
        if bound is not None and (cam.place_best is None or bound < cam.place_best):
            cam.place_best, cam.place_at = bound, len(held) - 1
        k = self.restart_settle
        since = len(held) - 1 - cam.place_at
        # Paced: most of the last k frames came half a period or more after the one before (one long
        # stall before a burst is no pacing: the burst's frames come together).
        paced = since >= k and 2 * sum(held[-j].recv_time - held[-j - 1].recv_time >= 0.5 * self.period
                                       for j in range(1, k)) >= k - 1
        if not paced and len(held) < self.restart_hold:
            return []
        return self._place_held(cam)

    def _place_held(self, cam: _Cam) -> list[SyncOutput]:
        held, best = cam.placing, cam.place_best
        assert held
        if best is None:  # the clock model was never ready while it was held: by its last arrival
            best = self._frame_at(held[-1].recv_time - self._lag(cam.index)) - held[-1].camera_frame
        cam.placing, cam.place_best = None, None
        out = self._restart(cam, held[0], best)
        for f in held:
            f.restarted = False
            out.extend(self.add(f, f.recv_time))
        return out

    def _restart(self, cam: _Cam, first: CameraFrame, first_tf: int) -> list[SyncOutput]:
        """An edge restarted (new sender): its camera frame 0 is trigger frame `first_tf`; count what
        it missed before `first`, its first frame."""
        old_tf = cam.last_tf
        cam.stats.restarts += 1
        cam.suspects.clear()
        cam.seen_cf.clear()
        cam.lag_win.clear()
        cam.rel_window.clear()
        # rel_base is kept: the camera arrives as it did against the others (same link, same edge), so
        # the drift check can correct a restart placed a few frames off, instead of taking the wrong
        # placement as the new normal.
        cam.offset = -first_tf
        new_tf = first.camera_frame - cam.offset
        cam.last_cf, cam.last_tf = None, None
        cam.restarted_at = first.recv_time
        missed = max(0, new_tf - (old_tf if old_tf is not None else new_tf) - 1)
        cam.stats.missed += missed
        return [SyncEvent("restart", cam.index,
                          f"camera {cam.index}: edge restarted; its camera frame {first.camera_frame} is trigger "
                          f"frame {new_tf} (by arrival); {missed} trigger frames missed while it was down")]
