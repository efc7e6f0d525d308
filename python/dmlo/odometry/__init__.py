"""The DMLO odometry: `Odometry` registers scans one by one (the crate's loop, the network in onnxruntime);
`dmlo.run.run_sequence` runs it over a dataset."""

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
