"""Braid's .braidz names: its schema number, the tables' column names, FlyTrack's own DVS table beside
them, and Braid's tracking parameters as FlyTrack's map to them (used by braidz.py to read and by
braidz_export.py to write)."""

from __future__ import annotations

BRAID_SCHEMA = 3
KALMAN_COLUMNS = ["obj_id", "frame", "timestamp", "x", "y", "z", "xvel", "yvel", "zvel",
                  "P00", "P01", "P02", "P11", "P12", "P22", "P33", "P44", "P55"]
DATA2D_COLUMNS = ["camn", "frame", "timestamp", "cam_received_timestamp", "device_timestamp", "block_id",
                  "x", "y", "area", "slope", "eccentricity", "frame_pt_idx", "cur_val", "mean_val", "sumsqf_val"]
ASSOC_COLUMNS = ["obj_id", "frame", "cam_num", "pt_idx"]
CAM_INFO_COLUMNS = ["camn", "cam_id"]
CLOCK_COLUMNS = ["start_timestamp", "framecount", "tcnt", "stop_timestamp"]
TEXTLOG_COLUMNS = ["mainbrain_timestamp", "cam_id", "host_timestamp", "message"]
# FlyTrack's own table beside Braid's: which data2d rows are event (DVS) cameras' clusters, with their
# covariance (px^2). Braid's data2d has no place for either; without it a re-track of the .braidz would
# take those points as frame cameras' (weighed at 1 px^2, able to start targets).
DVS_POINTS = "flytrack_dvs_points"
DVS_POINTS_COLUMNS = ["frame", "camn", "frame_pt_idx", "var_x", "var_y", "cov_xy"]


class BraidzError(Exception):
    pass


def _rust_f64(v: float) -> str:
    """A float as Rust's `{}` prints an f64 (and braidz-parser reads it back): 100.0 -> "100"."""
    text = repr(float(v))
    return text[:-2] if text.endswith(".0") else text


def braid_tracking_params(params: dict | None) -> dict:
    """FlyTrack TrackingParams -> Braid's TrackingParams (the JSON in textlog)."""
    p = params or {}
    return {
        "motion_noise_scale": p.get("motion_noise_scale", 0.1),
        "initial_position_std_meters": p.get("initial_position_std_m", 0.1),
        "initial_vel_std_meters_per_sec": p.get("initial_velocity_std_m_s", 1.0),
        "accept_observation_min_likelihood": 1e-8,
        # Braid's R is this value times I: a variance (px^2), where FlyTrack keeps a standard deviation.
        "ekf_observation_covariance_pixels": float(p.get("measurement_noise_px", 1.0)) ** 2,
        "max_position_std_meters": p.get("death_position_std_m", 0.01212),
        "hypothesis_test_params": {
            "minimum_number_of_cameras": p.get("birth_min_cameras", 2),
            "hypothesis_test_max_acceptable_error": p.get("birth_max_reproj_px", 5.0),
            "minimum_pixel_abs_zscore": 0.0,
        },
        "num_observations_to_visibility": int(min(max(p.get("confirm_min_frames", 3), 0), 255)),  # u8
        # No `mini_arena_config`: Braid leaves it out when there is none (an internally tagged enum, so a
        # plain string would not parse).
    }
