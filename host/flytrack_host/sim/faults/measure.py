"""What a fault did to a run, from its recording: frames lost, frames misnumbered, how long until the
numbering was right again, and what the user was told.

Truth: every edge of the simulated rig got `preroll` frames before the trigger started, then one frame
per pulse, so camera frame c is trigger frame c - preroll. A fault that replaces an edge says which
trigger frame each of the new edge's frames answered (`Fault.truth`, from `truth_after` on). Frames
injected by the fault (marked `ROGUE_MARK`) are left out of the counts; `rogue_tracked` counts those
the tracker was given (should be none).
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

from flytrack_host.recording import load_recording
from flytrack_host.recording.schema import FLAG_TRACKED
from flytrack_host.sim.faults.inject import ROGUE_MARK, Fault


def measure(recording: str | None, fault: Fault, preroll: int, n_frames: int, n_cams: int,
            message_re: str) -> dict[str, Any]:
    out: dict[str, Any] = {"frames_lost": None, "frames_misnumbered": None, "recovery_s": None,
                           "rogue_tracked": 0, "message": "(no recording)", "message_count": 0}
    if not recording:
        return out
    rec = load_recording(recording)
    d = rec.table("data2d_distorted")
    rogue = d["device_timestamp_ns"] == np.uint64(ROGUE_MARK)
    out["rogue_recorded"] = int(rogue.sum())
    out["rogue_tracked"] = int(np.sum((d["flags"][rogue] & FLAG_TRACKED) != 0))
    d = d[~rogue]
    # One row per camera frame received (the first; a frame with several points has several rows).
    cam = d["camera_index"].astype(np.int64)
    cf = d["camera_frame"].astype(np.int64)
    recv = d["cam_received_timestamp"]
    replaced = np.zeros(len(d), dtype=bool)
    for c, t0 in fault.truth_after.items():
        replaced |= (cam == c) & (recv >= t0)
    key = cam * (1 << 40) + cf * 2 + replaced
    _, first = np.unique(key, return_index=True)
    u = d[first]
    ucam, ucf, urep = cam[first], cf[first], replaced[first]
    truth = np.full(len(u), -(1 << 40), dtype=np.int64)
    orig = ~urep
    truth[orig] = ucf[orig] - preroll
    for i in np.nonzero(urep)[0]:
        truth[i] = fault.truth.get(int(ucam[i]), {}).get(int(ucf[i]), -(1 << 40))
    in_run = (truth >= 0) & (truth < n_frames)
    tf = u["trigger_frame"].astype(np.int64)
    bad = in_run & (tf != truth)
    out["frames_misnumbered"] = int(bad.sum())
    t_end = fault.t_end if math.isfinite(fault.t_end) else fault.t_start
    if bad.any() and math.isfinite(t_end):
        out["recovery_s"] = max(0.0, float(u["cam_received_timestamp"][bad].max()) - t_end)
    else:
        out["recovery_s"] = 0.0
    got = {(int(c), int(t)) for c, t in zip(ucam[in_run], truth[in_run], strict=True)}
    out["frames_lost"] = n_frames * n_cams - len(got)
    # What the user was told: the log lines since the fault began that name it.
    rx = re.compile(message_re)
    lines = [r for r in rec.textlog
             if r.get("host_time", 0) >= (fault.t_start - 0.05 if math.isfinite(fault.t_start) else 0)
             and rx.search(str(r.get("message", "")))]
    out["message_count"] = len(lines)
    out["message"] = str(lines[0]["message"]) if lines else "(nothing logged)"
    lat = rec.table("latency")
    if len(lat) and math.isfinite(fault.t_start):
        # What a clock step would do to the timing: the least arrival lag (trigger pulse -> last
        # camera packet) of the 100 frames with a trigger time that arrived last before the fault
        # began, against that of the 100 first after it. A step of s seconds moves every frame's lag,
        # the least too, by s; a loaded host delays frames, by up to 0.9 s measured, but not all of
        # 100 in a row, so the least stays near the floor (a median moved by 875 ms across a -1 s
        # step at load 13). Counted in frames: a window in seconds once held no frame with a trigger
        # time (the clock model not ready on a loaded host).
        v = (lat["last_arrival"] - lat["trigger_time"]) * 1e3
        t = lat["last_arrival"]
        ok = np.isfinite(v) & np.isfinite(t)
        order = np.argsort(t[ok], kind="stable")
        v, t = v[ok][order], t[ok][order]
        pre = v[t < fault.t_start][-100:]
        post = v[t >= fault.t_start][:100]
        out["arrival_floor_step_ms"] = float(post.min() - pre.min()) if pre.size and post.size else None
    if len(lat) and math.isfinite(t_end):
        after = lat[lat["last_arrival"] > t_end + 0.5]
        v = (after["estimate_time"] - after["trigger_time"]) * 1e3
        v = v[np.isfinite(v)]
        out["latency_after_p50_ms"] = float(np.percentile(v, 50)) if v.size else None
        out["latency_after_p99_ms"] = float(np.percentile(v, 99)) if v.size else None
        # The host's own part: from the frame's arrival (kernel stamp) to its estimate.
        a = (after["first_arrival"] - after["trigger_time"]) * 1e3
        a = a[np.isfinite(a)]
        out["arrival_after_min_ms"] = float(a.min()) if a.size else None  # the floor: no pause left in it
        h = (after["estimate_time"] - after["last_arrival"]) * 1e3
        h = h[np.isfinite(h)]
        out["host_delay_after_p99_ms"] = float(np.percentile(h, 99)) if h.size else None
    return out
