"""The tables of a FlyTrack recording: one NumPy structured dtype per kind of row.

The same dtypes are used for the append-only raw files (rows written as raw bytes, so a file cut at
any byte loses at most its last partial row) and for the finalised HDF5 file (one dataset each).
"""

from __future__ import annotations

import numpy as np

# The files of a recording folder: one raw file per table, the text log, the metadata, and the HDF5 file
# that finalising writes.
RAW_SUFFIX = ".bin"
TEXTLOG_NAME = "textlog.jsonl"
META_NAME = "meta.json"
H5_NAME = "recording.h5"
# A recording in parts (recording/parts.py): this file at the top of the folder, and one folder per part
# (part-0001, part-0002, ...), each a whole recording of the layout above.
PARTS_NAME = "parts.json"
PART_PREFIX = "part-"

# Upper triangle of the 6x6 state covariance, row-major: P00 P01 ... P05 P11 ... P55 (21 values).
COV_UPPER = [(i, j) for i in range(6) for j in range(i, 6)]
COV_NAMES = [f"P{i}{j}" for i, j in COV_UPPER]

# Every 2D point of every camera frame, tracked or not. A frame without points is one row with NaN x.
DATA2D = np.dtype(
    [
        ("trigger_frame", "<i8"),  # -1 when the frame could not be mapped to the trigger count
        ("camera_index", "<u2"),
        ("camera_frame", "<u8"),
        ("timestamp", "<f8"),  # trigger time of the frame (host clock, s); NaN if unknown
        ("cam_received_timestamp", "<f8"),  # host clock when the (last part of the) frame arrived
        ("device_timestamp_ns", "<u8"),
        ("edge_recv_ns", "<u8"),
        ("edge_done_ns", "<u8"),
        ("frame_pt_idx", "<u2"),
        ("n_points", "<u2"),  # points of this frame received
        ("total_points", "<u2"),  # points the extractor found (> n_points when truncated)
        ("flags", "u1"),  # bit 0 tracked, bit 1 late, bit 2 truncated, bit 3 incomplete split, bit 4 rejected
        ("x_dist", "<f4"),
        ("y_dist", "<f4"),
        ("x_undist", "<f4"),
        ("y_undist", "<f4"),
        ("area", "<f4"),
        ("peak_diff", "<f4"),
        ("orientation", "<f4"),
        ("eccentricity", "<f4"),
        ("cur_val", "<u2"),
        ("mean_val", "<f4"),
        ("sumsq_val", "<f4"),
    ]
)
FLAG_TRACKED = 1
FLAG_LATE = 2
FLAG_TRUNCATED = 4
FLAG_INCOMPLETE = 8
FLAG_REJECTED = 16  # recorded but never given to the tracker (future-dated, duplicate, unmapped)
FLAG_DVS = 32  # the row is an event (DVS) camera's cluster, placed at this trigger frame (eventcam)

# The position covariance of each event (DVS) camera point of data2d (a FLAG_DVS row, matched on
# trigger_frame, camera_index and frame_pt_idx): the tracker weighs those points by it (SPEC 1.6
# DVS_CLUSTERS var_x, var_y, cov_xy, in distorted px^2, grown by the time since the cluster's slice),
# so a re-track needs it to use them as the live run did.
DVS_COVARIANCE = np.dtype(
    [
        ("trigger_frame", "<i8"),
        ("camera_index", "<u2"),
        ("frame_pt_idx", "<u2"),
        ("var_x", "<f8"),
        ("var_y", "<f8"),
        ("cov_xy", "<f8"),
    ]
)

KALMAN = np.dtype(
    [("obj_id", "<u4"), ("trigger_frame", "<i8"), ("timestamp", "<f8")]
    + [(n, "<f8") for n in ("x", "y", "z", "xvel", "yvel", "zvel")]
    + [(n, "<f8") for n in COV_NAMES]
    + [("n_cameras", "<u2")]
)

ASSOCIATION = np.dtype(
    [("obj_id", "<u4"), ("trigger_frame", "<i8"), ("camera_index", "<u2"), ("pt_idx", "<u2")]
)

CAM_INFO = np.dtype([("camera_index", "<u2"), ("name", "S64"), ("edge", "S64"), ("calibration_id", "S64")])

# Samples of the trigger clock: host time before/after the query, frame count and fraction of frame.
TRIGGER_CLOCK = np.dtype(
    [("start_timestamp", "<f8"), ("framecount", "<i8"), ("fraction", "<f8"), ("stop_timestamp", "<f8")]
)

# One row per tracked frame: where the time from trigger to estimate went.
LATENCY = np.dtype(
    [
        ("trigger_frame", "<i8"),
        ("trigger_time", "<f8"),
        ("first_arrival", "<f8"),
        ("last_arrival", "<f8"),
        ("estimate_time", "<f8"),
        ("n_cameras", "<u2"),
        ("n_missing", "<u2"),
    ]
)

# STATUS heartbeats of the edges.
CAMERA_STATUS = np.dtype(
    [
        ("host_time", "<f8"),
        ("camera_index", "<u2"),
        ("state", "u1"),
        ("frames_seen", "<u8"),
        ("frames_dropped", "<u8"),
        ("fps", "<f4"),
        ("proc_us_mean", "<f4"),
        ("proc_us_max", "<f4"),
    ]
)

# One row per action of each rule firing (flytrack_host.actuation). For a high-speed camera on a trigger
# pulse output, `scheduled_frame` of a row with FIRING_FRAME_EXACT is the trigger frame of its buffer's
# trigger point (the firmware started the pulse with that frame), which aligns its video with the tracks.
FIRINGS = np.dtype(
    [
        ("rule", "S32"),
        ("output", "S32"),
        ("kind", "S16"),
        ("obj_id", "<u4"),
        ("condition_frame", "<i8"),  # trigger frame whose estimate made the rule fire
        ("scheduled_frame", "<i8"),  # trigger frame the action was meant for (-1: unknown)
        ("frame_time", "<f8"),  # trigger time (host clock) of condition_frame
        ("estimate_time", "<f8"),  # host time the estimate of condition_frame was made
        ("time_sent", "<f8"),  # host time the command left for the device
        ("time_ack", "<f8"),  # host time the device acknowledged (NaN: no acknowledgement)
        ("x", "<f4"),  # the (predicted) position the condition was true at
        ("y", "<f4"),
        ("z", "<f4"),
        ("flags", "u1"),  # FIRING_* bits
        ("error", "S96"),  # empty when the action succeeded
    ]
)
FIRING_DRY_RUN = 1  # the rule is a dry run: nothing was sent
FIRING_PREDICTED = 2  # evaluated on the state predicted to scheduled_frame
FIRING_FRAME_EXACT = 4  # the device placed the action at scheduled_frame exactly (trigger pulse, acked)
FIRING_FAILED = 8

TABLES: dict[str, np.dtype] = {
    "data2d_distorted": DATA2D,
    "kalman_estimates": KALMAN,
    "data_association": ASSOCIATION,
    "cam_info": CAM_INFO,
    "trigger_clock_info": TRIGGER_CLOCK,
    "latency": LATENCY,
    "camera_status": CAMERA_STATUS,
    "actuation_firings": FIRINGS,
    "dvs_point_covariance": DVS_COVARIANCE,
}


# Tables that describe the run rather than happen in it: a recording in parts repeats their rows at the
# start of every part (so that each part reads alone), and a reader of the whole recording keeps them once.
HEADER_TABLES = ("cam_info",)


def dtype_to_json(dt: np.dtype) -> list[list[str]]:
    return [[name, dt.fields[name][0].str] for name in dt.names]


def dtype_from_json(desc: list[list[str]]) -> np.dtype:
    return np.dtype([(name, code) for name, code in desc])


def cov_upper(cov: np.ndarray) -> np.ndarray:
    """(6,6) covariance -> the 21 upper-triangle values in COV_NAMES order."""
    iu = np.triu_indices(6)
    return np.asarray(cov, dtype=np.float64)[iu]


def cov_full(row: np.void | np.ndarray) -> np.ndarray:
    """A KALMAN row (or rows) -> (…, 6, 6) symmetric covariance."""
    vals = np.stack([np.asarray(row[n], dtype=np.float64) for n in COV_NAMES], axis=-1)
    out = np.zeros(vals.shape[:-1] + (6, 6))
    iu = np.triu_indices(6)
    out[..., iu[0], iu[1]] = vals
    out[..., iu[1], iu[0]] = vals
    return out
