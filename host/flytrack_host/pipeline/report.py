"""Reporting of the host pipeline: the live status line, the recorder's state and the run summary.
A mixin of `HostPipeline`."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any

from flytrack_host.util import hostclock


class PipelineReport:
    """`HostPipeline`'s reporting part (reads its counters, receiver, synchroniser and recorder)."""

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

    def recording_stop_text(self) -> str | None:
        """What finalising cost at stop and what reading the recording back costs: its parts, the bytes
        finalised at stop and how long it took, the memory a part-by-part reader holds."""
        rec = self.recorder
        if rec is None or rec.stats.finalise_at_stop_s is None:
            return None
        st = rec.stats
        at_stop = f"finalised at stop: {st.finalise_at_stop_bytes / 1e6:.1f} MB in {st.finalise_at_stop_s:.2f} s"
        if rec.parts is None:
            return (f"one unparted recording, {at_stop} (the whole recording: this grows with its length; read "
                    f"back whole it needs about {st.bytes_written / 1e6:.0f} MB of memory)")
        bg = (f"{st.parts_finalised_background} in the background ({st.finalise_background_s:.1f} s)"
              if st.parts_finalised_background else "none in the background")
        return (f"{st.parts} part{'s' if st.parts != 1 else ''} ({rec.parts.describe()}), {bg}; {at_stop}; "
                f"read part by part (export, retrack) it needs about {2 * st.largest_part_bytes / 1e6:.0f} MB of "
                f"memory (two parts of {st.largest_part_bytes / 1e6:.0f} MB at most)")

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
            "recording_finalize_s": self.recording_finalize_s,
            "recording_stop": self.recording_stop_text(),
            "cpu_wake_latency": self.cpu_wake.summary() if self.cpu_wake is not None else None,
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
