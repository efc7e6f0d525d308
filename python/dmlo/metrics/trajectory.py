"""Absolute trajectory error (ATE) and relative pose error (RPE), as the paper's Argoverse table uses them.

- **ATE**: the estimate is first aligned to the ground truth (``"se3"``: rotation + translation,
  ``"sim3"``: also scale, ``None``: as is) by Umeyama's closed form on the positions; the error of frame
  ``i`` is ``‖p_gt[i] − p_aligned[i]‖``. This is evo's ``evo_ape --align`` (``--correct_scale`` for Sim(3))
  with the translation part.
- **RPE** over a frame ``delta``: ``E_i = inv(inv(G_i) G_{i+δ}) · inv(E_i) E_{i+δ}`` for ground truth ``G``
  and estimate ``E``, for every ``i`` (overlapping pairs); translation error ``‖t(E_i)‖`` (m) and rotation
  error ``angle(R(E_i))`` (degrees), as evo's ``evo_rpe --delta δ --delta_unit f --all_pairs`` (the same as
  without ``--all_pairs`` for the default ``δ = 1``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from dmlo.poses import as_poses

__all__ = [
    "AteResult",
    "RpeResult",
    "Alignment",
    "absolute_trajectory_error",
    "pose_difference",
    "relative_pose_error",
    "rotation_angle_deg",
    "umeyama_alignment",
]

Alignment = Literal["se3", "sim3"] | None


def rotation_angle_deg(rotations: ArrayLike) -> NDArray[np.float64]:
    """Rotation angle in degrees of each ``(…, 3, 3)`` rotation, accurate for small angles.

    ``atan2(sin θ, cos θ)`` with ``sin θ`` from the skew part and ``cos θ`` from the trace.
    """
    r = np.asarray(rotations, dtype=np.float64)
    skew = np.stack(
        [r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], axis=-1
    )
    sine = 0.5 * np.linalg.norm(skew, axis=-1)
    cosine = 0.5 * (np.trace(r, axis1=-2, axis2=-1) - 1.0)
    return np.degrees(np.arctan2(sine, cosine))


def pose_difference(a: ArrayLike, b: ArrayLike) -> tuple[float, float]:
    """Distance (m) and angle (°) between two 4×4 poses: of the motion ``a⁻¹·b``."""
    step = np.linalg.inv(np.asarray(a, dtype=np.float64)) @ np.asarray(b, dtype=np.float64)
    return float(np.linalg.norm(step[:3, 3])), float(rotation_angle_deg(step[:3, :3]))


def umeyama_alignment(
    source: ArrayLike, target: ArrayLike, with_scale: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Least-squares ``(R, t, s)`` with ``target ≈ s R source + t`` (Umeyama 1991) for ``(N, 3)`` points.

    For collinear positions (a straight drive) the rotation about the line is not determined; any of the
    optimal solutions is returned, all of which give the same residuals. Raises ``ValueError`` for no
    points, different shapes, or a scale asked for points that are all identical.
    """
    src = np.asarray(source, dtype=np.float64)
    dst = np.asarray(target, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise ValueError(f"source and target must both be (N, 3), got {src.shape} and {dst.shape}")
    if len(src) == 0:
        raise ValueError("alignment needs at least one position")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise ValueError("alignment positions contain NaN or infinite values")
    mean_src, mean_dst = src.mean(axis=0), dst.mean(axis=0)
    centred_src, centred_dst = src - mean_src, dst - mean_dst
    covariance = centred_dst.T @ centred_src / len(src)
    if not np.all(np.isfinite(covariance)):  # LAPACK's SVD may never return on infinities
        raise ValueError("alignment positions are too large: their covariance overflows")
    u, singular, vt = np.linalg.svd(covariance)
    reflection = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        reflection[2, 2] = -1.0
    rotation = u @ reflection @ vt
    scale = 1.0
    if with_scale:
        variance = np.mean(np.sum(centred_src**2, axis=1))
        if variance <= 0.0:
            raise ValueError("Sim(3) alignment is undefined: the estimated positions are all identical")
        scale = float(np.trace(np.diag(singular) @ reflection) / variance)
    translation = mean_dst - scale * rotation @ mean_src
    return rotation, translation, scale


@dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error in metres, after ``alignment``; ``errors`` per frame."""

    rmse: float
    mean: float
    median: float
    std: float
    max: float
    alignment: Alignment
    scale: float
    errors: NDArray[np.float64] = field(repr=False)
    aligned_poses: NDArray[np.float64] = field(repr=False)


def _check_pair(poses_gt: ArrayLike, poses_est: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    gt = as_poses(poses_gt, "poses_gt")
    est = as_poses(poses_est, "poses_est")
    if len(gt) != len(est):
        raise ValueError(f"poses_gt has {len(gt)} poses but poses_est has {len(est)}")
    if len(gt) == 0:
        raise ValueError("no poses")
    return gt, est


def absolute_trajectory_error(
    poses_gt: ArrayLike, poses_est: ArrayLike, alignment: Alignment = "se3"
) -> AteResult:
    """ATE (translation) of ``poses_est`` against ``poses_gt`` after an SE(3), Sim(3) or no alignment."""
    gt, est = _check_pair(poses_gt, poses_est)
    if alignment not in ("se3", "sim3", None):
        raise ValueError(f"alignment must be 'se3', 'sim3' or None, got {alignment!r}")
    aligned = est.copy()
    scale = 1.0
    if alignment is not None:
        rotation, translation, scale = umeyama_alignment(
            est[:, :3, 3], gt[:, :3, 3], with_scale=alignment == "sim3"
        )
        transform = np.eye(4)
        transform[:3, :3] = rotation
        transform[:3, 3] = translation
        aligned = transform @ est
        # A similarity scales positions only; rotations stay orthonormal.
        aligned[:, :3, 3] = scale * (rotation @ est[:, :3, 3].T).T + translation
    errors = np.linalg.norm(gt[:, :3, 3] - aligned[:, :3, 3], axis=1)
    return AteResult(
        rmse=float(np.sqrt(np.mean(errors**2))),
        mean=float(errors.mean()),
        median=float(np.median(errors)),
        std=float(errors.std()),
        max=float(errors.max()),
        alignment=alignment,
        scale=scale,
        errors=errors,
        aligned_poses=aligned,
    )


@dataclass(frozen=True)
class RpeResult:
    """Relative pose error over ``delta`` frames: translation in metres, rotation in degrees."""

    delta: int
    t_mean: float
    t_rmse: float
    t_max: float
    r_mean: float
    r_rmse: float
    r_max: float
    t_errors: NDArray[np.float64] = field(repr=False)
    r_errors: NDArray[np.float64] = field(repr=False)


def relative_pose_error(poses_gt: ArrayLike, poses_est: ArrayLike, delta: int = 1) -> RpeResult:
    """RPE between frames ``i`` and ``i + delta`` for every ``i`` (no alignment needed)."""
    gt, est = _check_pair(poses_gt, poses_est)
    if delta < 1:
        raise ValueError(f"delta must be ≥ 1, got {delta}")
    if len(gt) <= delta:
        raise ValueError(f"RPE with delta {delta} needs more than {delta} poses, got {len(gt)}")
    delta_gt = np.linalg.inv(gt[:-delta]) @ gt[delta:]
    delta_est = np.linalg.inv(est[:-delta]) @ est[delta:]
    error = np.linalg.inv(delta_gt) @ delta_est
    t_errors = np.linalg.norm(error[:, :3, 3], axis=1)
    r_errors = rotation_angle_deg(error[:, :3, :3])
    return RpeResult(
        delta=delta,
        t_mean=float(t_errors.mean()),
        t_rmse=float(np.sqrt(np.mean(t_errors**2))),
        t_max=float(t_errors.max()),
        r_mean=float(r_errors.mean()),
        r_rmse=float(np.sqrt(np.mean(r_errors**2))),
        r_max=float(r_errors.max()),
        t_errors=t_errors,
        r_errors=r_errors,
    )
