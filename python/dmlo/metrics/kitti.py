"""KITTI odometry benchmark metrics, with the semantics of the devkit's ``evaluate_odometry.cpp``.

For every start frame ``0, 10, 20, …`` and every length ``100, 200, …, 800`` m, the segment ends at the
first frame whose ground-truth path distance is strictly greater than the start's plus the length
(segments running past the end are dropped). The error of a segment is ``inv(ΔEst) · ΔGT`` with
``Δ = inv(P[first]) · P[last]``; its translation error is the norm of that transform's translation divided
by the length, its rotation error the angle ``acos(clamp((trace(R) − 1) / 2))`` divided by the length.
``t_rel`` and ``r_rel`` are plain means over all segments, reported in % and in °/100 m.

As in the devkit, path distances are accumulated in float32 (this decides which frame ends a segment) and
a segment's rotation angle is taken from a float32 cosine; the rest of the pose algebra is in float64.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from dmlo.poses import as_poses

__all__ = ["KITTI_LENGTHS", "KittiOdometryErrors", "kitti_odometry_errors", "trajectory_distances"]

KITTI_LENGTHS: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
KITTI_STEP = 10  # a new start every 10 frames (one second at 10 Hz)


@dataclass(frozen=True)
class KittiOdometryErrors:
    """Result of :func:`kitti_odometry_errors`.

    ``t_rel`` (%) and ``r_rel`` (°/100 m) are None when no segment fits (a path shorter than the shortest
    length). Per-segment arrays are in devkit order (start frame, then length) and in the devkit's units:
    ``segment_t_err`` as a fraction (m/m) and ``segment_r_err`` in rad/m.
    """

    t_rel: float | None
    r_rel: float | None
    segments: int
    path_length: float
    segment_first: NDArray[np.int64] = field(repr=False)
    segment_last: NDArray[np.int64] = field(repr=False)
    segment_length: NDArray[np.float64] = field(repr=False)
    segment_t_err: NDArray[np.float64] = field(repr=False)
    segment_r_err: NDArray[np.float64] = field(repr=False)

    def by_length(self) -> dict[float, tuple[float, float, int]]:
        """Per segment length: ``(t_rel %, r_rel °/100 m, segment count)`` for lengths with segments."""
        result = {}
        for length in np.unique(self.segment_length):
            chosen = self.segment_length == length
            result[float(length)] = (
                float(self.segment_t_err[chosen].mean() * 100.0),
                float(np.degrees(self.segment_r_err[chosen].mean()) * 100.0),
                int(chosen.sum()),
            )
        return result


def trajectory_distances(poses: ArrayLike) -> NDArray[np.float32]:
    """Cumulative path length at every pose, accumulated in float32 like the devkit."""
    array = as_poses(poses)
    steps = np.diff(array[:, :3, 3], axis=0).astype(np.float32)
    step_lengths = np.sqrt(np.sum(steps * steps, axis=1, dtype=np.float32), dtype=np.float32)
    distances = np.zeros(len(array), dtype=np.float32)
    # np.cumsum accumulates sequentially in the array's dtype: the same float32 rounding as the devkit.
    distances[1:] = np.cumsum(step_lengths, dtype=np.float32)
    return distances


def _rotation_angles(rotations: NDArray[np.float64]) -> NDArray[np.float64]:
    """The devkit's ``rotationError`` with its float arithmetic: the diagonal read into ``float a, b, c``,
    ``float d = 0.5*(a+b+c-1.0)`` (the sum in float32, the rest in double, stored as float32) and ``acos`` of
    the clamped float. Near a cosine of 1 float32 steps are ~6e-8, i.e. several 1e-5 rad of angle, which
    moves the 6th printed digit of ``r_rel``; with this rounding KITTI 00 gives the devkit's digits."""
    a, b, c = (rotations[:, i, i].astype(np.float32) for i in range(3))
    cosine = (0.5 * ((a + b + c).astype(np.float64) - 1.0)).astype(np.float32)
    return np.arccos(np.clip(cosine, np.float32(-1.0), np.float32(1.0))).astype(np.float64)


def kitti_odometry_errors(
    poses_gt: ArrayLike,
    poses_est: ArrayLike,
    lengths: tuple[float, ...] = KITTI_LENGTHS,
    step: int = KITTI_STEP,
) -> KittiOdometryErrors:
    """KITTI ``t_rel`` (%) and ``r_rel`` (°/100 m) of estimated against ground-truth poses.

    Both are ``(N, 4, 4)`` in the same frame convention (the devkit uses camera-frame poses; the
    numbers depend slightly on the frame because segment errors are measured in the first pose's frame).
    """
    gt = as_poses(poses_gt, "poses_gt")
    est = as_poses(poses_est, "poses_est")
    if len(gt) != len(est):
        raise ValueError(f"poses_gt has {len(gt)} poses but poses_est has {len(est)}")
    if step < 1:
        raise ValueError(f"step must be ≥ 1, got {step}")

    distances = trajectory_distances(gt)
    firsts = np.arange(0, len(gt), step)
    first_list, last_list, length_list = [], [], []
    for length in lengths:  # devkit order is (start, length); sorted below
        targets = distances[firsts] + np.float32(length)
        lasts = np.searchsorted(distances, targets, side="right")  # first index with distance > target
        fits = lasts < len(gt)
        first_list.append(firsts[fits])
        last_list.append(lasts[fits])
        length_list.append(np.full(int(fits.sum()), length))
    first = np.concatenate(first_list).astype(np.int64)
    last = np.concatenate(last_list).astype(np.int64)
    seg_length = np.concatenate(length_list)
    order = np.lexsort((np.searchsorted(np.asarray(lengths), seg_length), first))
    first, last, seg_length = first[order], last[order], seg_length[order]

    if len(first) == 0:
        empty = np.zeros(0)
        return KittiOdometryErrors(
            None, None, 0, float(distances[-1]), first, last, empty, empty, empty
        )

    delta_gt = np.linalg.inv(gt[first]) @ gt[last]
    delta_est = np.linalg.inv(est[first]) @ est[last]
    error = np.linalg.inv(delta_est) @ delta_gt
    t_err = np.linalg.norm(error[:, :3, 3], axis=1) / seg_length
    r_err = _rotation_angles(error[:, :3, :3]) / seg_length
    return KittiOdometryErrors(
        t_rel=float(t_err.mean() * 100.0),
        r_rel=float(np.degrees(r_err.mean()) * 100.0),
        segments=len(first),
        path_length=float(distances[-1]),
        segment_first=first,
        segment_last=last,
        segment_length=seg_length,
        segment_t_err=t_err,
        segment_r_err=r_err,
    )
