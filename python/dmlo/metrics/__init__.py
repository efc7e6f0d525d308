"""Evaluation metrics: KITTI odometry (t_rel, r_rel), ATE/RPE, registration errors, EPE and Fl-all."""

from __future__ import annotations

from dmlo.metrics.flow import FlowErrors, end_point_error, fl_all, flow_errors
from dmlo.metrics.kitti import (
    KITTI_LENGTHS,
    KittiOdometryErrors,
    kitti_odometry_errors,
    trajectory_distances,
)
from dmlo.metrics.registration import (
    RegistrationErrors,
    registration_errors,
    rotation_error_axes_deg,
    rotation_error_deg,
    translation_error,
)
from dmlo.metrics.summary import evaluate_trajectory
from dmlo.metrics.trajectory import (
    AteResult,
    RpeResult,
    absolute_trajectory_error,
    relative_pose_error,
    rotation_angle_deg,
    umeyama_alignment,
)

__all__ = [
    "KITTI_LENGTHS",
    "AteResult",
    "FlowErrors",
    "KittiOdometryErrors",
    "RegistrationErrors",
    "RpeResult",
    "absolute_trajectory_error",
    "end_point_error",
    "evaluate_trajectory",
    "fl_all",
    "flow_errors",
    "kitti_odometry_errors",
    "registration_errors",
    "relative_pose_error",
    "rotation_angle_deg",
    "rotation_error_axes_deg",
    "rotation_error_deg",
    "trajectory_distances",
    "translation_error",
    "umeyama_alignment",
]
