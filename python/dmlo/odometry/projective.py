"""Projective point-to-plane ICP on a scan's point image: the alignment of a pair that barely moved.

NDT compares a scan with the normal distributions of a map's voxels. Between two scans a few centimetres
apart the reference's ground rings lie where the target's own would if the car stood still, so NDT holds
a creeping pair together; and its voxels leave millimetres of bias even for a scan aligned with itself.
A point's distance to the plane of the reference's surface has neither fault: along the road a ring
point slides freely, and a scan aligned with itself has every residual exactly zero. The correspondences
come from the projection (SuMa's projective association: each target point, moved into the reference
frame, meets the reference cell it falls in), so no search structure is needed; they hold while the pair
moved less than the cells' spacing on the surfaces, which is why only slow pairs take this path.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

import dmlo_rs

Matrix4 = npt.NDArray[np.float64]

# A neighbour whose range differs from the cell's by more than this fraction lies across a depth edge.
EDGE_RANGE_RATIO = 0.1
# Correspondences farther apart than this (m) are not the same surface; residuals beyond HUBER_M count less.
MAX_DISTANCE_M = 0.3
HUBER_M = 0.02
# Directions of the update with less than this fraction of the best one's information keep the estimate.
MIN_INFORMATION = 1e-5


def surface_normals(points: npt.NDArray[np.float32]) -> npt.NDArray[np.float64]:
    """The unit normal of the surface at each cell of a point image (`[H, W, 3]`, NaN where empty), from its
    four neighbours (columns wrap round); NaN where a neighbour is missing or across a depth edge."""
    cells = points.astype(np.float64)
    right, left = np.roll(cells, -1, axis=1), np.roll(cells, 1, axis=1)
    below, above = np.full_like(cells, np.nan), np.full_like(cells, np.nan)
    below[:-1], above[1:] = cells[1:], cells[:-1]
    normals = np.cross(right - left, below - above)
    length = np.linalg.norm(normals, axis=2)
    ranges = np.linalg.norm(cells, axis=2)
    valid = np.isfinite(length) & (length > 0)
    for neighbour in (right, left, below, above):
        with np.errstate(invalid="ignore"):
            valid &= np.abs(np.linalg.norm(neighbour, axis=2) - ranges) < EDGE_RANGE_RATIO * ranges
    normals /= np.where(valid, length, 1.0)[..., None]
    normals[~valid] = np.nan
    return normals


def point_to_plane(
    reference: npt.NDArray[np.float32],
    target: npt.NDArray[np.float32],
    T_tgt_ref: Matrix4,
    cylinder: Any,
    iterations: int = 10,
) -> Matrix4 | None:
    """`T_tgt_ref` refined by projective point-to-plane ICP of the `target` point image's points against the
    `reference` point image (both `[H, W, 3]` of `cylinder`, NaN where empty, their own sensor frames).

    Each round moves the target's points into the reference frame, finds the reference cell each falls in
    (`dmlo_rs.point_cells`) and solves the small motion that brings them onto the planes of those cells
    (Gauss-Newton, Huber weights). Directions the planes leave open keep the estimate. None when the first
    round finds fewer than six correspondences.
    """
    normals = surface_normals(reference).reshape(-1, 3)
    surface = reference.reshape(-1, 3).astype(np.float64)
    points = target[np.isfinite(target[..., 0])].astype(np.float64)  # every cell: subsets cost accuracy
    pose = np.linalg.inv(T_tgt_ref)  # the target's pose in the reference frame
    for round_ in range(iterations):
        moved = points @ pose[:3, :3].T + pose[:3, 3]
        cells = dmlo_rs.point_cells(moved.astype(np.float32), cylinder)
        seen = np.flatnonzero(cells >= 0)
        normal, on = normals[cells[seen]], surface[cells[seen]]
        offset = moved[seen] - on
        usable = np.isfinite(normal[:, 0]) & (np.linalg.norm(offset, axis=1) < MAX_DISTANCE_M)
        if np.count_nonzero(usable) < 6:
            if round_ == 0:
                return None
            break
        normal, offset, moved_seen = normal[usable], offset[usable], moved[seen][usable]
        residual = np.einsum("ij,ij->i", normal, offset)
        weight = HUBER_M / np.maximum(np.abs(residual), HUBER_M)
        jacobian = np.hstack([np.cross(moved_seen, normal), normal])  # d residual / d (rotation, translation)
        information = jacobian.T @ (jacobian * weight[:, None])
        values, vectors = np.linalg.eigh(information)
        kept = values > MIN_INFORMATION * values[-1]
        step = -(vectors[:, kept] @ ((vectors[:, kept].T @ (jacobian.T @ (weight * residual))) / values[kept]))
        pose = _exp(step) @ pose
        if np.linalg.norm(step[3:]) < 1e-7 and np.linalg.norm(step[:3]) < 1e-8:
            break
    return np.asarray(np.linalg.inv(pose), dtype=np.float64)


def _exp(step: npt.NDArray[np.float64]) -> Matrix4:
    """The rigid motion of a small (rotation vector, translation) step, rotation by Rodrigues' formula."""
    rotation_vector, translation = step[:3], step[3:]
    angle = float(np.linalg.norm(rotation_vector))
    skew = np.array([
        [0.0, -rotation_vector[2], rotation_vector[1]],
        [rotation_vector[2], 0.0, -rotation_vector[0]],
        [-rotation_vector[1], rotation_vector[0], 0.0],
    ])
    rotation = np.eye(3) + skew if angle < 1e-12 else (
        np.eye(3) + np.sin(angle) / angle * skew + (1.0 - np.cos(angle)) / angle**2 * skew @ skew
    )
    transform = np.eye(4)
    transform[:3, :3], transform[:3, 3] = rotation, translation
    return transform
