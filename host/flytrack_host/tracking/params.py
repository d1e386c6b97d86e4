"""Tracking parameters with their documented defaults (seed 000 appendix A and Braid's defaults)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class TrackingParams(BaseModel):
    """Parameters of the multi-target EKF tracker. Every field is settable in the rig file's
    `[tracking]` table; the defaults are Braid's (flydra's successor) unless noted."""

    model_config = ConfigDict(extra="forbid")

    motion_noise_scale: float = Field(
        0.1, gt=0, description="Scale of the constant-velocity process noise Q(dt) (Braid: 0.1)."
    )
    initial_position_std_m: float = Field(
        0.1, gt=0, description="Position standard deviation of a newborn target, metres (Braid: 0.1)."
    )
    initial_velocity_std_m_s: float = Field(
        1.0, gt=0, description="Velocity standard deviation of a newborn target, m/s (Braid: 1.0)."
    )
    measurement_noise_px: float = Field(
        1.0, gt=0, description="Standard deviation of a 2D observation, pixels: R = s^2 I (Braid: 1 px)."
    )
    own_cov_scale: float = Field(
        16.0, gt=0, description="Points with their own covariance (event cameras, SPEC 1.6) update a target "
        "with R = this x that covariance. The frame cameras' R (measurement_noise_px^2) is far above their "
        "points' real error (0.06 px median in the simulated rig), so an event point at its true covariance "
        "would outweigh better frame points; 16 keeps the simulated rig's RMSE with event cameras within 2 % "
        "of that without (the manual: Event cameras).",
    )
    gate_px: float = Field(
        20.0, gt=0, description="Image-distance gate from the predicted projection to a candidate point, px."
    )
    area_gate_ratio: float = Field(
        10.0, gt=1, description="A point whose area differs from the target's by more than this factor is ignored."
    )
    max_mahalanobis: float = Field(
        20.0, gt=0, description="Mahalanobis distance from prediction to a camera ray beyond which a point is not used."
    )
    birth_max_reproj_px: float = Field(
        5.0, gt=0, description="Mean reprojection error a birth hypothesis must stay under, px (Braid: 5)."
    )
    birth_min_cameras: int = Field(
        2, ge=2, description="Fewest cameras that must see a new target before it is born."
    )
    birth_max_combination: int = Field(
        3, ge=2, description="Largest camera combination tried when triangulating a birth (Braid: 2-3)."
    )
    birth_max_hypotheses: int = Field(
        256,
        ge=1,
        description=(
            "Most birth hypotheses (seed pairs of unclaimed points, best first) evaluated in one frame; "
            "the rest wait for the next frame, their points still unclaimed. Bounds a frame's birth "
            "search (about 1-3 ms at 11 cameras with 10 newcomers and the default)."
        ),
    )
    death_position_std_m: float = Field(
        0.01212, gt=0, description=(
            "A target dies when its position std (the square root of the largest diagonal entry of its "
            "position covariance) passes this, metres (Braid: 0.01212)."
        ),
    )
    death_weak_frames: int = Field(
        10, ge=0, description=(
            "A target dies after this many consecutive frames in which fewer than birth_min_cameras cameras "
            "updated it (0 = off). A target that left, coasting on chance false positives in single "
            "cameras, ends here long before its covariance passes death_position_std_m; a real one seen "
            "by 2 cameras each missing 5 % of frames goes 10 frames so with odds ~1e-10."
        ),
    )
    report_max_coast_frames: int = Field(
        2, ge=0, description=(
            "A confirmed target is left out of the frame's estimates once it has gone this many "
            "consecutive frames without any observation (0 = always reported); it stays alive and is "
            "reported again at its next update."
        ),
    )
    duplicate_distance_m: float = Field(
        0.003, ge=0, description=(
            "Two targets closer than this for duplicate_frames consecutive frames are one animal tracked "
            "twice: the younger dies (0 = off). Below the 6 mm head-on pass the benchmark scenario has."
        ),
    )
    duplicate_frames: int = Field(5, ge=1, description="See duplicate_distance_m.")
    min_eccentricity_for_orientation: float = Field(
        1.4, ge=1, description="Only points at least this elongated contribute to body orientation."
    )
    min_area_px: float = Field(
        0.0, ge=0, description="A point must have an area above this to be used (seed 000 eq. 3.11), px."
    )
    area_smoothing: float = Field(
        0.1, gt=0, le=1, description="Weight of this frame's mean point area in a target's running area estimate."
    )
    exclusive_points: bool = Field(
        True,
        description=(
            "Within one camera a point feeds at most one target: when several targets' nearest neighbours "
            "are the same point, scipy's linear_sum_assignment chooses globally. False gives flydra's "
            "independent per-target choice, where only the merge-prevention rule (seed 000 3.2.1) acts."
        ),
    )
    confirm_min_frames: int = Field(
        3,
        ge=1,
        description=(
            "A newborn target is reported (estimates, born, associations) once it has been updated with "
            "observations in this many frames, its birth frame included. Chance 2-camera matches of false "
            "positives are born and die unseen. 1 reports every birth at once, as Braid does."
        ),
    )
    birth_min_separation_m: float = Field(
        0.0,
        ge=0,
        description=(
            "A birth hypothesis closer than this to an existing target's predicted position is refused, "
            "metres (0 = off, as in flydra)."
        ),
    )
    orientation_min_plane_angle_deg: float = Field(
        10.0,
        gt=0,
        lt=90,
        description=(
            "Body orientation is reported only when at least two of the cameras' planes meet at this "
            "angle or more (nearly parallel planes leave the line of intersection undefined), degrees."
        ),
    )
    kernel: Literal["auto", "numpy", "c"] = Field(
        "auto",
        description=(
            "Which implementation runs the per-frame hot path: 'c' (the compiled tracker kernel, "
            "host/flytrack_host/tracking/kernel/), 'numpy', or 'auto': the environment variable "
            "FLYTRACK_TRACKER_KERNEL (numpy|c) when set, else C when the library is built. Both give the "
            "same estimates and identities."
        ),
    )
