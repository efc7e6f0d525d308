"""Generated from the crate's schema by `python -m dmlo.odometry.config`; do not edit."""

from pathlib import Path
from typing import Any, Literal

import dmlo_rs

ConfigError = dmlo_rs.ConfigError
SCHEMA: dict[str, Any]
SECTIONS: dict[str, type]

def class_name(section_key: str) -> str: ...
def stub_text() -> str: ...

class MatchingConfig:
    min_confidence: float
    nms_radius: int
    max_matches: int
    symmetric: bool
    consistency_px: float | None
    coherence_px: float | None
    coherence_radius: int
    def __init__(self, min_confidence: float = ..., nms_radius: int = ..., max_matches: int = ..., symmetric: bool = ..., consistency_px: float | None = ..., coherence_px: float | None = ..., coherence_radius: int = ...) -> None: ...

class RansacConfig:
    threshold: float
    confidence: float
    max_iterations: int
    seed: int
    refit: Literal["point_to_point", "ray_noise"]
    ray_range_ratio: float
    ray_bearing_threshold_deg: float
    vote_by_tilt: bool
    min_vote: float
    vote_voxel: float | None
    def __init__(self, threshold: float = ..., confidence: float = ..., max_iterations: int = ..., seed: int = ..., refit: Literal["point_to_point", "ray_noise"] = ..., ray_range_ratio: float = ..., ray_bearing_threshold_deg: float = ..., vote_by_tilt: bool = ..., min_vote: float = ..., vote_voxel: float | None = ...) -> None: ...

class MotionModelConfig:
    min_inliers: int
    min_inlier_votes: float
    max_deviation: float
    max_deviation_deg: float
    guided_fraction: float
    rematch_gap: int | None
    prediction_horizon: int
    match_from_prediction_m: float | None
    prediction_rounds: int | None
    guided_windows: bool | None
    start_check_m: float | None
    start_max_reverse_m: float | None
    def __init__(self, min_inliers: int = ..., min_inlier_votes: float = ..., max_deviation: float = ..., max_deviation_deg: float = ..., guided_fraction: float = ..., rematch_gap: int | None = ..., prediction_horizon: int = ..., match_from_prediction_m: float | None = ..., prediction_rounds: int | None = ..., guided_windows: bool | None = ..., start_check_m: float | None = ..., start_max_reverse_m: float | None = ...) -> None: ...

class DeskewConfig:
    enabled: bool
    clockwise: bool
    reference_azimuth_deg: float
    def __init__(self, enabled: bool = ..., clockwise: bool = ..., reference_azimuth_deg: float = ...) -> None: ...

class MappingConfig:
    enabled: bool
    voxel_size: float
    max_scans: int
    keyframe_distance: float
    keyframe_angle_deg: float
    ring_lock_distance: float
    motion_model_start_distance: float
    motion_model_start_angle_deg: float
    downsample: float
    downsample_far: float
    far_range: float
    level_without_far_upright: bool
    max_iterations: int
    degeneracy_threshold: float
    rotation_degeneracy_threshold: float
    def __init__(self, enabled: bool = ..., voxel_size: float = ..., max_scans: int = ..., keyframe_distance: float = ..., keyframe_angle_deg: float = ..., ring_lock_distance: float = ..., motion_model_start_distance: float = ..., motion_model_start_angle_deg: float = ..., downsample: float = ..., downsample_far: float = ..., far_range: float = ..., level_without_far_upright: bool = ..., max_iterations: int = ..., degeneracy_threshold: float = ..., rotation_degeneracy_threshold: float = ...) -> None: ...

class LargeMotionConfig:
    search_ahead_m: tuple[float, ...]
    search_yaw_deg: tuple[float, ...]
    max_rounds: int
    min_step: float
    min_step_deg: float
    def __init__(self, search_ahead_m: tuple[float, ...] = ..., search_yaw_deg: tuple[float, ...] = ..., max_rounds: int = ..., min_step: float = ..., min_step_deg: float = ...) -> None: ...

class MovingObjectsConfig:
    detect: bool
    threshold: float
    def __init__(self, detect: bool = ..., threshold: float = ...) -> None: ...

class OdometryConfig:
    matching: MatchingConfig
    ransac: RansacConfig
    motion_model: MotionModelConfig
    deskew: DeskewConfig
    mapping: MappingConfig
    large_motion: LargeMotionConfig
    moving_objects: MovingObjectsConfig
    threads: int
    matching_stage: Literal["auto", "crate", "graph"]
    min_points: int
    reflectance: Literal["auto", "unit", "0-255", "0-65535", "none"]
    def __init__(self, matching: MatchingConfig = ..., ransac: RansacConfig = ..., motion_model: MotionModelConfig = ..., deskew: DeskewConfig = ..., mapping: MappingConfig = ..., large_motion: LargeMotionConfig = ..., moving_objects: MovingObjectsConfig = ..., threads: int = ..., matching_stage: Literal["auto", "crate", "graph"] = ..., min_points: int = ..., reflectance: Literal["auto", "unit", "0-255", "0-65535", "none"] = ...) -> None: ...
    def to_dict(self) -> dict[str, Any]: ...
    @classmethod
    def from_dict(cls, data: Any) -> OdometryConfig: ...
    def validate(self) -> None: ...
    def save(self, path: Path) -> None: ...
    @classmethod
    def load(cls, path: Path) -> OdometryConfig: ...
