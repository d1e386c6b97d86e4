"""Drift detection: a camera whose counter hides a missed or extra pulse, judged on its arrivals
against the other cameras' per trigger frame (see the package doc)."""

from __future__ import annotations

import math
import statistics

from flytrack_host.intake.sync.state import _Cam
from flytrack_host.intake.sync.types import CameraFrame, SyncEvent, SyncOutput


class _DriftDetection:
    """`FrameSynchronizer`'s drift check (a mixin: it works on the synchroniser's state)."""

    def _check_drift(self, cam: _Cam, frame: CameraFrame, tf: int) -> list[SyncOutput]:
        """Note the frame's arrival; compare the trigger frames that settled (see the package doc)."""
        t = self.frame_time(tf)
        if math.isfinite(t):  # the late joiners' placement only; drift never looks at the clock
            lag = frame.recv_time - t
            if cam.lag_ewma is None or lag < cam.lag_ewma:
                # A frame cannot come before its pulse: one sooner than the estimate brings it down at once
                # (first frames that queued while the rig started must not place a camera joining in the
                # next seconds frames behind, where nothing moves it back).
                cam.lag_ewma = lag
            else:  # a stall's late frames move it by at most 2 periods each (no pollution by outliers)
                cam.lag_ewma += 0.1 * min(2 * self.period, lag - cam.lag_ewma)
        if len(self.cams) < 3:
            return []  # with two cameras, which one drifted cannot be told from arrivals
        if self._eval_next is None:
            self._eval_next = tf
        if tf >= self._eval_next:  # less the periods an edge-numbered camera was found to arrive late by
            self._arrivals.setdefault(tf, {}).setdefault(cam.index, frame.recv_time - cam.arrival_shift)
        out: list[SyncOutput] = []
        live = [i for i, c in self.cams.items() if c.alive]
        while self._eval_next <= self.max_accepted:
            f = self._eval_next
            rec = self._arrivals.get(f)
            if self.max_accepted - f <= self.drift_settle and (rec is None or any(i not in rec for i in live)):
                break
            self._arrivals.pop(f, None)
            self._eval_next = f + 1
            if rec is None:  # skip straight to the next frame that has arrivals (after a jump ahead)
                self._eval_next = max(f + 1, min(self._arrivals, default=self.max_accepted + 1))
                continue
            if len(rec) < 3:
                continue
            # Each camera against the median of the others: one sort for all (the same values
            # statistics.median would pick from the others' sorted arrivals).
            vals = sorted(rec.values())
            m = len(vals) - 1
            h = m // 2
            for i, t_i in rec.items():
                k = vals.index(t_i)
                o = vals[:k] + vals[k + 1:]
                d = t_i - (o[h] if m % 2 else (o[h - 1] + o[h]) / 2)
                out.extend(self._drift_sample(self.cams[i], f, d, t_i))
        return out

    def _drift_sample(self, cam: _Cam, tf: int, d: float, recv: float) -> list[SyncOutput]:
        w = cam.rel_window
        w.append((tf, d, recv))
        while len(w) > self.drift_frames:
            w.popleft()
        if cam.rel_base is not None and abs(d - cam.rel_base) < 0.25 * self.period:
            cam.rel_base += 0.02 * (d - cam.rel_base)  # follows slow changes of the camera's latency
        if len(w) < self.drift_frames:
            return []
        # Paced: a burst's frames come together; frames answering drift_frames pulses span most of it.
        if w[-1][2] - w[0][2] < 0.5 * (w[-1][0] - w[0][0]) * self.period:
            return []
        if cam.rel_base is None:
            if w.max1() - w.min1() <= 0.5 * self.period:
                cam.rel_base = statistics.median(x[1] for x in w)
            return []
        half = 0.5 * self.period
        if w.max1() - cam.rel_base <= half and w.min1() - cam.rel_base >= -half:
            # Every sample within half a period of the baseline: so is their median, which rounds to a
            # shift of 0 (the common case, decided without sorting the window).
            return []
        e = [x[1] - cam.rel_base for x in w]
        med = statistics.median(e)
        shift = round(med / self.period)
        # A missed or extra pulse moves the arrivals by whole periods: the median must sit close to
        # one, and every sample near it.
        if shift == 0 or abs(med - shift * self.period) > 0.25 * self.period:
            return []
        if any(abs(x - shift * self.period) > 0.4 * self.period for x in e):
            return []
        # With three cameras the others' arrivals are compared through their mean: one camera two periods
        # off moves it by one, and the good cameras look a period off too. The camera furthest off its
        # baseline is the one that drifted: the others wait for it.
        # (Once it is re-mapped, their next samples are back on their baselines: their windows no longer
        # agree on a whole period, so they are never re-mapped for it.)
        if any(self._further_off(c, abs(shift)) for c in self.cams.values() if c is not cam):
            return []
        w.clear()
        cam.stats.drift += 1
        dev = statistics.median(e)
        msg = (f"camera {cam.index} drifted by {shift} frames: its frames arrive {dev * 1e3:.1f} ms off the "
               f"other cameras' over {self.drift_frames} trigger frames")
        for rec in self._arrivals.values():  # its unsettled arrivals carry the old numbering (or shift)
            rec.pop(cam.index, None)
        if cam.offset is not None and cam.last_tf is not None and self._edge_numbered.get(cam.index) is False:
            # Arriving `shift` periods later than the others: its frames belong `shift` later.
            cam.offset -= shift
            cam.last_tf += shift
            cam.lag_win.clear()  # its lags to the clock change by the shift
            msg += "; re-mapped"
        else:  # numbered by the edge (its number wins) or not mapped yet: reported once, not renumbered;
            # its arrivals are compared `shift` periods earlier from now on (its own baseline and the
            # others' reference both stay as they were).
            cam.arrival_shift += shift * self.period
        return [SyncEvent("drift", cam.index, msg)]

    def _further_off(self, other: _Cam, shift: int) -> bool:
        """Whether `other`'s recent arrivals sit more than `shift` whole periods off its baseline."""
        w = other.rel_window
        if other.rel_base is None or len(w) < self.drift_frames // 2:
            return False
        return abs(round(statistics.median(x[1] - other.rel_base for x in w) / self.period)) > shift
