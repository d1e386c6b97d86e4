"""The recording's reference page: every table of a recording and its columns (flytrack_host.recording.schema),
with what each table holds and notes on its columns (TABLE_NOTES)."""

from __future__ import annotations

from typing import Any

from .common import GENERATED_NOTE, _cell

# table -> (what it holds, {column: note}). Columns without a note are listed with their type only.
TABLE_NOTES: dict[str, tuple[str, dict[str, str]]] = {
    "data2d_distorted": (
        "Every 2D point of every camera frame, tracked or not, as the edge sent it (pixel coordinates "
        "with the lens distortion, and undistorted). A frame without points is one row with `x_dist` NaN.",
        {"trigger_frame": "the trigger pulse the frame belongs to; -1 when it could not be mapped",
         "camera_index": "the camera's `index` in the rig file",
         "camera_frame": "the camera's own frame counter",
         "timestamp": "trigger time of the frame, host clock, s; NaN when unknown",
         "cam_received_timestamp": "host clock when the frame (its last part) arrived, s",
         "device_timestamp_ns": "the camera's own timestamp, ns",
         "edge_recv_ns": "edge clock when the frame reached the edge, ns",
         "edge_done_ns": "edge clock when its points were extracted, ns",
         "frame_pt_idx": "the point's index within its frame",
         "n_points": "points of this frame received",
         "total_points": "points the edge found (more than n_points when the frame was truncated)",
         "flags": "bits: 1 tracked, 2 late, 4 truncated, 8 incomplete split, 16 rejected (recorded, never "
                  "tracked), 32 an event camera's cluster",
         "x_dist": "x, distorted pixels", "y_dist": "y, distorted pixels",
         "x_undist": "x, undistorted pixels", "y_undist": "y, undistorted pixels",
         "area": "pixels in the region", "peak_diff": "largest difference from the background",
         "orientation": "angle of the region's long axis, radians",
         "eccentricity": "elongation of the region (1: round)"}),
    "kalman_estimates": (
        "The 3D estimates: one row per object per tracked frame. Positions in metres, velocities in m/s, in "
        "the calibration's world frame; P00 ... P55 the upper triangle of the 6 x 6 state covariance.",
        {"obj_id": "the object's identity, kept from birth to death",
         "trigger_frame": "the trigger pulse of the estimate",
         "timestamp": "trigger time of that pulse, host clock, s",
         "n_cameras": "cameras whose points updated the estimate"}),
    "data_association": (
        "Which 2D point of which camera each estimate used (`pt_idx` is `frame_pt_idx` of data2d_distorted).",
        {}),
    "cam_info": ("The rig's cameras: index, name, edge address and name in the calibration.", {}),
    "trigger_clock_info": (
        "Every sample of the trigger box's clock: host time before and after the query, the pulse count and "
        "the fraction of a frame period. The clock model is fitted from these.", {}),
    "latency": (
        "One row per tracked frame: where the time from the trigger pulse to the 3D estimate went "
        "(host clock, s).",
        {"first_arrival": "first camera's datagram of the frame arrived",
         "last_arrival": "last camera's datagram of the frame arrived",
         "estimate_time": "the 3D estimate was made",
         "n_missing": "cameras whose frame had not arrived when the frame was tracked"}),
    "camera_status": ("The edges' STATUS heartbeats (one a second per camera).", {}),
    "actuation_firings": (
        "One row per action of each rule firing (closed-loop experiments).",
        {"condition_frame": "trigger frame whose estimate made the rule fire",
         "scheduled_frame": "trigger frame the action was aimed at (-1: unknown); for a frame-exact "
                            "high-speed camera pulse, the frame of its trigger point",
         "frame_time": "trigger time of condition_frame, host clock, s",
         "estimate_time": "host time the estimate of condition_frame was made",
         "time_sent": "host time the command left for the device",
         "time_ack": "host time the device acknowledged it (NaN: no acknowledgement)",
         "x": "the (predicted) position the condition held at, m",
         "flags": "bits: 1 dry run, 2 predicted, 4 frame exact, 8 failed",
         "error": "empty when the action succeeded"}),
    "dvs_point_covariance": (
        "For each event-camera point of data2d_distorted (flag 32), its position covariance in distorted "
        "px²; a re-track weighs the point by it, as the live run did.", {}),
}


def recording_page() -> str:
    from flytrack_host.recording.schema import H5_NAME, META_NAME, RAW_SUFFIX, TABLES, TEXTLOG_NAME

    lines = [GENERATED_NOTE, "# A recording's tables", "",
             f"A recording is a folder (`*.flytrack`). While the host runs, each table below is an append-only "
             f"file `TABLE{RAW_SUFFIX}` of fixed-size rows, so a run killed at any moment loses at most the "
             f"rows not yet written; `{TEXTLOG_NAME}` holds the run's log lines and `{META_NAME}` the format, "
             f"every table's row layout, the start time and the writer's settings. At the end of a run (or "
             f"with `flytrack recording recover FOLDER` after a crash) the tables are copied into one HDF5 "
             f"file, `{H5_NAME}`, one dataset per table with the same columns; the rig file and the "
             f"calibration the run used are kept with it. `flytrack recording info FOLDER` lists the tables, "
             f"`flytrack export` writes them as CSV or as Braid's `.braidz`.", "",
             "Times called *host clock* are seconds on the host's one monotonic timeline, offset to read like "
             "Unix time (it never steps when the wall clock does).", ""]
    for name, dt in TABLES.items():
        intro, notes = TABLE_NOTES.get(name, ("", {}))
        lines += [f"## `{name}` {{#{name}}}", "", intro, "", "| column | type | meaning |", "|---|---|---|"]
        for col in dt.names:
            base, _shape = dt.fields[col][0], None
            lines.append(f"| `{col}` | {_dtype_text(base)} | {_cell(notes.get(col, ''))} |")
        lines.append("")
    return "\n".join(lines)


def _dtype_text(dt: Any) -> str:
    kind = {"i": "int", "u": "uint", "f": "float", "S": "bytes"}.get(dt.kind, dt.kind)
    return f"{kind}{dt.itemsize * 8}" if kind in ("int", "uint", "float") else f"{kind}[{dt.itemsize}]"
