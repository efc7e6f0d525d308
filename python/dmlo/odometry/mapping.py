"""Scan-to-map NDT for a single pair of scans: DMLO + mapping (§III-D-c) when the map is the reference scan
alone, and where a pose is near enough to a keyframe for its ground rings to hold it (`near_keyframe`).

`Odometry.register` refines every pose by NDT against its local map of recent scans. A pair given to
`Odometry.register_pair` has no drive behind it, so its map is the reference scan (`refine_pair`): the
target is aligned to it by NDT from the motion DMLO found (a slow pair by `dmlo_rs.point_to_plane`
instead). The network's matches bring the pair within NDT's basin with no initial guess; NDT, fitting
every point of both scans rather than a few hundred matches, then takes the error the matches leave (their
bearing error grows with range).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

import dmlo_rs
from dmlo.metrics.trajectory import pose_difference
from dmlo.odometry.config import MappingConfig

Matrix4 = npt.NDArray[np.float64]


def near_keyframe(keyframe: Matrix4, pose: Matrix4, config: MappingConfig) -> bool:
    """Whether `pose` lies within `config.ring_lock_distance` of the `keyframe` pose, where the keyframe's
    ground rings would hold a creeping car in place in NDT."""
    return bool(pose_difference(keyframe, pose)[0] < config.ring_lock_distance)


def refine_pair(
    reference: npt.NDArray[np.float32], target: npt.NDArray[np.float32], T_tgt_ref: Matrix4, config: MappingConfig
) -> Matrix4 | None:
    """`T_tgt_ref` refined by NDT of `target` against a map of `reference` (both N×3 or N×4, their own sensor
    frames), with the local map's settings; None when NDT finds too few correspondences or does not converge."""
    one_scan = dmlo_rs.NdtMap(voxel_size=config.voxel_size, max_scans=1)
    one_scan.insert(np.ascontiguousarray(reference[:, :3]))
    try:
        result = one_scan.align(
            np.ascontiguousarray(target[:, :3]),
            np.linalg.inv(T_tgt_ref),  # the map is the reference's frame: the target's pose in it
            max_iterations=config.max_iterations,
            source_voxel_size=config.downsample,
            degeneracy_threshold=config.degeneracy_threshold,
            rotation_degeneracy_threshold=config.rotation_degeneracy_threshold,
        )
    except dmlo_rs.RegistrationError:
        return None
    if not result.converged:
        return None
    return np.asarray(np.linalg.inv(np.asarray(result.transform, dtype=np.float64)), dtype=np.float64)
