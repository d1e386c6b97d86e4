"""Tracking parameters with their documented defaults (seed 000 appendix A and Braid's defaults)."""

from __future__ import annotations

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
    death_position_std_m: float = Field(
        0.01212, gt=0, description="A target dies when its position std passes this, metres (Braid: 0.01212)."
    )
    min_eccentricity_for_orientation: float = Field(
        1.4, ge=1, description="Only points at least this elongated contribute to body orientation."
    )
