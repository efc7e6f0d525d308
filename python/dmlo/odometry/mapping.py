"""Scan-to-map NDT beyond the local map's own alignment: near a keyframe, and for a single pair of scans.

Near a keyframe (`align_near_keyframe`), the keyframe's ground rings would hold a creeping car in place, so
the horizontal motion and heading come from the scan's upright surfaces alone (`upright_points`).

`Odometry.register` refines every pose by NDT against its local map of recent scans. A pair given to
`Odometry.register_pair` has no drive behind it, so its map is the reference scan (`refine_pair`): the
target is aligned to it by NDT from the motion DMLO found (a standing pair by `dmlo_rs.point_to_plane`
instead). The network's matches bring the pair within NDT's basin with no initial guess; NDT, fitting every
point of both scans rather than a few hundred matches, then takes the error the matches leave (their
bearing error grows with range).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

import dmlo_rs
from dmlo.metrics.trajectory import pose_difference
from dmlo.odometry.config import MappingConfig

Matrix4 = npt.NDArray[np.float64]

# The horizontal part of a surface's normal from which it counts as upright, and how close to the keyframe
# (m, °) the upright surfaces must put the scan to call the car standing (`align_near_keyframe`).
UPRIGHT_VOTE = 0.5
STANDING_DISTANCE = 0.02
STANDING_ANGLE_DEG = 0.1


@dataclass
class NearKeyframe:
    """`align_near_keyframe`'s result: the pose, the directions the map left open, and whether the
    horizontal motion and heading came from the upright surfaces alone (False: the car stands)."""

    pose: Matrix4
    degenerate_directions: int
    split: bool


def align_to_map(ndt_map: Any, points: npt.NDArray[np.float32], start: Matrix4, config: MappingConfig) -> Any:
    """NDT of `points` (N×3 or more columns, sensor frame) against `ndt_map` (`dmlo_rs.NdtMap`) from the pose
    `start`, with the mapping settings of `config` → `NdtResult` (raises `dmlo_rs.RegistrationError`)."""
    return ndt_map.align(
        np.ascontiguousarray(points[:, :3]),
        start,
        max_iterations=config.max_iterations,
        source_voxel_size=config.downsample,
        degeneracy_threshold=config.degeneracy_threshold,
        rotation_degeneracy_threshold=config.rotation_degeneracy_threshold,
    )


def near_keyframe(keyframe: Matrix4, pose: Matrix4, config: MappingConfig) -> bool:
    """Whether `pose` lies within `config.ring_lock_distance` of the `keyframe` pose."""
    return pose_difference(keyframe, pose)[0] < config.ring_lock_distance


def standing(keyframe: Matrix4, pose: Matrix4) -> bool:
    """Whether `pose` lies within `STANDING_DISTANCE` and `STANDING_ANGLE_DEG` of the `keyframe` pose: a car
    that has not moved."""
    moved, turned = pose_difference(keyframe, pose)
    return moved < STANDING_DISTANCE and turned < STANDING_ANGLE_DEG


def near_keyframe_alignment(keyframe: Matrix4, pose: Matrix4, config: MappingConfig) -> Literal["standing", "near"] | None:
    """How a scan at `pose` is aligned next to a keyframe (or a pair's reference) at `keyframe`, one decision for
    the drive and the single pair: "standing" (`standing`: projective point-to-plane ICP against the keyframe's
    point image), "near" (`near_keyframe`: `align_near_keyframe`'s split), None beyond `config.ring_lock_distance`
    (NDT of the whole scan). A `ring_lock_distance` of 0 turns both off."""
    if not near_keyframe(keyframe, pose, config):
        return None
    return "standing" if standing(keyframe, pose) else "near"


def upright_points(points: npt.NDArray[np.float32], cylinder: Any, voxel: float) -> npt.NDArray[np.float32]:
    """The upright surfaces of a scan's point image `points` (`[H, W, 3]`, NaN where empty): each kept point
    whose surface's normal is mostly horizontal (`dmlo_rs.horizontal_votes`: walls, poles, trunks, car
    bodies), one cell per `voxel` (m; 0: every cell), the voxel NDT aligns at: a plane fit for every cell
    would cost more than NDT."""
    rows, cols = np.nonzero(np.isfinite(points[..., 0]))
    if voxel > 0:
        keys = np.floor(points[rows, cols] / voxel).astype(np.int64) + (1 << 20)
        # One integer a voxel (a sort of rows is many times slower); voxels a million apart may share it.
        _, first = np.unique((keys[:, 0] << 42) + (keys[:, 1] << 21) + keys[:, 2], return_index=True)
        rows, cols = rows[first], cols[first]
    votes = dmlo_rs.horizontal_votes(points, rows, cols, cylinder, floor=UPRIGHT_VOTE / 2)
    upright = votes >= UPRIGHT_VOTE
    return points[rows[upright], cols[upright]]


def align_near_keyframe(
    align: Callable[[npt.NDArray[np.float32], Matrix4], Any],
    cloud: npt.NDArray[np.float32],
    upright: npt.NDArray[np.float32],
    start: Matrix4,
    keyframe: Matrix4,
) -> NearKeyframe | None:
    """NDT near a keyframe, whose ground rings would hold a creeping car in place. `align(points, start)`
    aligns to the map (`NdtMap.align` with its settings); poses are in the map's frame.

    The rings sit at fixed ranges from the sensor, so a keyframe taken where the car still is shows its
    rings where the scan's own lie if the car stood still (in a stop-and-go queue, with the cars around it
    left out, the road is most of what remains). The `upright` surfaces alone give the horizontal motion and
    the heading; the whole `cloud`, aligned from there, gives the height, roll and pitch, which the road
    pins and the upright surfaces barely do (LeGO-LOAM's split). A scan that the DMLO estimate `start` or the
    upright surfaces put at the keyframe stands, and takes the whole scan's alignment, rings and all: they
    are right then. None when an alignment fails or does not converge.
    """

    try:
        # The upright surfaces alone fix the pose less well than the whole scan (fewer points, a
        # corridor's walls): a car the DMLO estimate already puts at the keyframe is not moved by them.
        horizontal = None if standing(keyframe, start) else align(upright, start)
        if horizontal is not None and not horizontal.converged:
            return None
        horizontal_pose = start if horizontal is None else np.asarray(horizontal.transform, dtype=np.float64)
        whole = align(cloud, horizontal_pose)
    except dmlo_rs.RegistrationError:
        return None
    if not whole.converged:
        return None
    whole_pose = np.asarray(whole.transform, dtype=np.float64)
    if standing(keyframe, horizontal_pose):
        return NearKeyframe(whole_pose, int(whole.degenerate_directions), split=False)
    return NearKeyframe(heading_and_level(horizontal_pose, whole_pose), int(whole.degenerate_directions), split=True)


def heading_and_level(horizontal: Matrix4, level: Matrix4) -> Matrix4:
    """A pose with the horizontal position and the heading (yaw) of `horizontal` and the height, roll and
    pitch (Z-Y-X angles) of `level`."""

    def angles(rotation: npt.NDArray[np.float64]) -> tuple[float, float, float]:
        yaw = np.arctan2(rotation[1, 0], rotation[0, 0])
        pitch = -np.arcsin(np.clip(rotation[2, 0], -1.0, 1.0))
        roll = np.arctan2(rotation[2, 1], rotation[2, 2])
        return yaw, pitch, roll

    yaw, _, _ = angles(horizontal[:3, :3])
    _, pitch, roll = angles(level[:3, :3])
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    pose = np.eye(4)
    pose[:3, :3] = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array(
        [[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]]) @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    pose[:3, 3] = (horizontal[0, 3], horizontal[1, 3], level[2, 3])
    return pose


def refine_pair(
    reference: npt.NDArray[np.float32], target: npt.NDArray[np.float32], T_tgt_ref: Matrix4, config: MappingConfig,
    target_upright: npt.NDArray[np.float32] | None = None,
) -> Matrix4 | None:
    """`T_tgt_ref` refined by NDT of `target` against a map of `reference` (both N×3 or N×4, their own sensor
    frames), with the local map's settings; None when NDT finds too few correspondences or does not converge.
    With the target's upright surfaces given (`target_upright`, `upright_points`: the caller found the pair
    near, `near_keyframe_alignment`), the reference's rings would hold the pair together: `align_near_keyframe`."""
    one_scan = dmlo_rs.NdtMap(voxel_size=config.voxel_size, max_scans=1)
    one_scan.insert(np.ascontiguousarray(reference[:, :3]))

    def align(points: npt.NDArray[np.float32], start: Matrix4) -> Any:
        return align_to_map(one_scan, points, start, config)

    # The map is the reference's frame: the target's pose in it.
    start: Matrix4 = np.asarray(np.linalg.inv(T_tgt_ref), dtype=np.float64)
    if target_upright is not None:
        near = align_near_keyframe(align, target, target_upright, start, np.eye(4))
        return None if near is None else np.asarray(np.linalg.inv(near.pose), dtype=np.float64)
    try:
        result = align(target, start)
    except dmlo_rs.RegistrationError:
        return None
    if not result.converged:
        return None
    return np.asarray(np.linalg.inv(np.asarray(result.transform, dtype=np.float64)), dtype=np.float64)
