"""The DMLO odometry pipeline: `Odometry` registers scans one by one; `run_sequence` runs a dataset."""

from dmlo.odometry.config import (
    DeskewConfig,
    LargeMotionConfig,
    MappingConfig,
    MatchingConfig,
    MotionModelConfig,
    MovingObjectsConfig,
    OdometryConfig,
    RansacConfig,
)
from dmlo.odometry.pair import PairResult
from dmlo.odometry.notices import PairWarning, ReflectanceNotice, SensorMismatchWarning, TimestampWarning
from dmlo.odometry.pipeline import FrameDiagnostics, Odometry

__all__ = [
    "DeskewConfig",
    "FrameDiagnostics",
    "LargeMotionConfig",
    "MappingConfig",
    "MatchingConfig",
    "MotionModelConfig",
    "MovingObjectsConfig",
    "Odometry",
    "OdometryConfig",
    "PairResult",
    "PairWarning",
    "RansacConfig",
    "ReflectanceNotice",
    "SensorMismatchWarning",
    "TimestampWarning",
]
