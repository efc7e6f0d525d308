"""All trajectory metrics in one JSON-ready dict: what ``dmlo eval``, ``dmlo run`` and the benchmark report."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from dmlo.metrics.kitti import kitti_odometry_errors
from dmlo.metrics.trajectory import Alignment, absolute_trajectory_error, relative_pose_error
from dmlo.poses import as_poses

__all__ = ["MAX_COORDINATE", "evaluate_trajectory"]

# Largest position (m) the metrics take: beyond any trajectory measured in metres, while sums of squares
# of it stay far from float64's overflow (a translation of 1e308 in a pose file made the alignment's SVD
# spin forever on infinities).
MAX_COORDINATE = 1e12


def _check_magnitude(name: str, poses: Any) -> None:
    beyond = np.flatnonzero(np.abs(poses[:, :3, 3]).max(axis=1) > MAX_COORDINATE)
    if beyond.size:
        first = int(beyond[0])
        raise ValueError(
            f"{name}: pose {first} lies {np.abs(poses[first, :3, 3]).max():.3g} m from the origin, beyond the "
            f"{MAX_COORDINATE:.0e} m the metrics take ({beyond.size} such poses)"
        )


def evaluate_trajectory(
    poses_gt: ArrayLike, poses_est: ArrayLike, alignment: Alignment = "se3", delta: int = 1
) -> dict[str, Any]:
    """KITTI ``t_rel`` (%) / ``r_rel`` (°/100 m), ATE (m) and RPE (m, °) of an estimate, as a dict.

    Keys: ``poses``, ``path_length`` (m of ground-truth path), ``t_rel``, ``r_rel``, ``segments``,
    ``ate_rmse``, ``ate_mean``, ``ate_max``, ``ate_alignment``, ``ate_scale``, ``rpe_delta``,
    ``rpe_t_mean``, ``rpe_t_max``, ``rpe_r_mean``, ``rpe_r_max``, ``note``. Undefined values are None
    (``t_rel``/``r_rel`` for paths shorter than 100 m, RPE for ``delta`` ≥ the number of poses) and
    ``note`` says why. Raises ``ValueError`` for mismatched or malformed inputs.
    """
    gt = as_poses(poses_gt, "poses_gt")
    est = as_poses(poses_est, "poses_est")
    for name, poses in (("poses_gt", gt), ("poses_est", est)):
        _check_magnitude(name, poses)
    if len(gt) != len(est):
        raise ValueError(f"poses_gt has {len(gt)} poses but poses_est has {len(est)}")
    if delta < 1:
        raise ValueError(f"delta must be ≥ 1, got {delta}")
    kitti = kitti_odometry_errors(gt, est)
    ate = absolute_trajectory_error(gt, est, alignment=alignment)
    rpe = relative_pose_error(gt, est, delta=delta) if len(gt) > delta else None
    notes = []
    if kitti.segments == 0:
        notes.append(
            f"ground-truth path is {kitti.path_length:.1f} m, shorter than the 100 m KITTI segments: "
            "t_rel and r_rel are undefined"
        )
    if rpe is None:
        notes.append(f"RPE over {delta} frame(s) needs more than {delta} poses")
    return {
        "poses": len(gt),
        "path_length": kitti.path_length,
        "t_rel": kitti.t_rel,
        "r_rel": kitti.r_rel,
        "segments": kitti.segments,
        "ate_rmse": ate.rmse,
        "ate_mean": ate.mean,
        "ate_max": ate.max,
        "ate_alignment": alignment or "none",
        "ate_scale": ate.scale,
        "rpe_delta": delta,
        "rpe_t_mean": None if rpe is None else rpe.t_mean,
        "rpe_t_max": None if rpe is None else rpe.t_max,
        "rpe_r_mean": None if rpe is None else rpe.r_mean,
        "rpe_r_max": None if rpe is None else rpe.r_max,
        "note": "; ".join(notes) or None,
    }
