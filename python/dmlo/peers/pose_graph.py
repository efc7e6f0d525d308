"""Poses that agree best with many measured relative motions: a least-squares pose graph.

The multi-scan reference (`dmlo.peers.consensus`) aligns each scan with the next few, not only the next; no
chain of poses satisfies every such alignment exactly, and the poses that fit them all best average out the
error of each single alignment. Solved by GTSAM (Levenberg–Marquardt on its sparse factor graph, one
between-factor an alignment) with a robust loss, twice: a Huber loss first, which bounds the pull of a large
residual and, being convex, leaves the start's chain wherever the alignments say; then a Cauchy loss from
there, whose pull fades for residuals far beyond its scale, so that an alignment that failed outright
(metres off) does not drag the others along.
"""

from __future__ import annotations

import gtsam
import numpy as np
import numpy.typing as npt
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

Poses = npt.NDArray[np.float64]

# Metres a radian of rotation residual weighs as: an angle error at this distance from the sensor displaces
# the scene as much as this translation error, about the depth most points of a street scan lie at.
LEVER_ARM_M = 10.0
# Residuals (m, and radians times the lever arm) well beyond this pull less the larger they are.
ROBUST_SCALE_M = 0.05


def edge_residuals(poses: Poses, edges: npt.NDArray[np.intp], motions: Poses) -> npt.NDArray[np.float64]:
    """Per edge `(i, j)` with measured motion `T_i_j`: how far `inv(P_i) P_j` lies from it, as (E, 6)
    (rotation vector in radians, then translation in metres)."""
    error = np.linalg.inv(motions) @ np.linalg.inv(poses[edges[:, 0]]) @ poses[edges[:, 1]]
    return np.concatenate([Rotation.from_matrix(error[:, :3, :3]).as_rotvec(), error[:, :3, 3]], axis=1)


def _check_edges(count: int, edges: npt.NDArray[np.intp], motions: Poses) -> None:
    if len(edges) != len(motions):
        raise ValueError(f"{len(edges)} edges but {len(motions)} motions")
    if edges.size and (edges.min() < 0 or edges.max() >= count or np.any(edges[:, 0] == edges[:, 1])):
        raise ValueError(f"edges must join two different scans of the {count}")
    adjacency = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(count, count))
    _, component = connected_components(adjacency, directed=False)
    apart = np.flatnonzero(component != component[0])
    if apart.size:
        raise ValueError(f"scan(s) {apart.tolist()} not joined to the first by the edges")


def _rigid(matrix: npt.NDArray[np.float64]) -> gtsam.Pose3:
    """GTSAM's pose of a 4×4 matrix whose rotation carries the last bits of float error (gtsam takes the
    3×3 as given; products of many motions drift off orthonormal)."""
    rotation = Rotation.from_matrix(matrix[:3, :3]).as_matrix()
    return gtsam.Pose3(gtsam.Rot3(rotation), np.asarray(matrix[:3, 3], dtype=np.float64))


def solve_pose_graph(initial: Poses, edges: npt.ArrayLike, motions: Poses) -> Poses:
    """The poses (N, 4, 4) that fit the measured motions best, the first held at `initial[0]`.

    `edges` (E, 2) pairs scan indices `(i, j)`, `motions` (E, 4, 4) the motion `T_i_j` measured between them
    (`inv(P_i) P_j` of the true poses); `initial` is where the solve starts (a chain of motions). The edges
    must join every scan to the first, through others or directly, or it could not be placed.
    """
    edges = np.asarray(edges, dtype=np.intp).reshape(-1, 2)
    count = len(initial)
    _check_edges(count, edges, motions)
    if count < 2:
        return initial.copy()
    # GTSAM's pose tangent is rotation (rad) then translation (m): a radian weighs the lever arm's metres.
    weights = gtsam.noiseModel.Diagonal.Sigmas(np.array([1.0 / LEVER_ARM_M] * 3 + [1.0] * 3))
    measured = [_rigid(motion) for motion in motions]
    values = gtsam.Values()
    for index, pose in enumerate(initial):
        values.insert(index, _rigid(pose))
    first = values.atPose3(0)
    parameters = gtsam.LevenbergMarquardtParams()
    # Tolerances well below the alignments' millimetres; GTSAM's defaults stop at 1e-5 relative.
    parameters.setRelativeErrorTol(1e-10)
    parameters.setAbsoluteErrorTol(1e-12)
    parameters.setMaxIterations(100)
    for loss in (gtsam.noiseModel.mEstimator.Huber, gtsam.noiseModel.mEstimator.Cauchy):
        noise = gtsam.noiseModel.Robust.Create(loss.Create(ROBUST_SCALE_M), weights)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.NonlinearEqualityPose3(0, first))
        for (i, j), motion in zip(edges, measured):
            graph.add(gtsam.BetweenFactorPose3(int(i), int(j), motion, noise))
        values = gtsam.LevenbergMarquardtOptimizer(graph, values, parameters).optimize()
    return np.stack([values.atPose3(index).matrix() for index in range(count)])
