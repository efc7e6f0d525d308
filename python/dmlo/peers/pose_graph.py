"""Poses that agree best with many measured relative motions: a least-squares pose graph.

The multi-scan reference (`dmlo.peers.consensus`) aligns each scan with the next few, not only the next; no
chain of poses satisfies every such alignment exactly, and the poses that fit them all best average out the
error of each single alignment. Solved by scipy's trust-region least squares with a sparse Jacobian (each
edge touches two poses) and a robust loss, twice: a soft L1 loss first, which bounds the pull of a large
residual and, being convex, leaves the start's chain wherever the alignments say; then a Cauchy loss from
there, whose pull fades for residuals far beyond its scale, so that an alignment that failed outright
(metres off) does not drag the others along.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, lil_matrix
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


def solve_pose_graph(initial: Poses, edges: npt.ArrayLike, motions: Poses) -> Poses:
    """The poses (N, 4, 4) that fit the measured motions best, the first held at `initial[0]`.

    `edges` (E, 2) pairs scan indices `(i, j)`, `motions` (E, 4, 4) the motion `T_i_j` measured between them
    (`inv(P_i) P_j` of the true poses); `initial` is where the solve starts (a chain of motions). The edges
    must join every scan to the first, through others or directly, or it could not be placed.
    """
    edges = np.asarray(edges, dtype=np.intp).reshape(-1, 2)
    count = len(initial)
    if len(edges) != len(motions):
        raise ValueError(f"{len(edges)} edges but {len(motions)} motions")
    if edges.size and (edges.min() < 0 or edges.max() >= count or np.any(edges[:, 0] == edges[:, 1])):
        raise ValueError(f"edges must join two different scans of the {count}")
    if count < 2:
        return initial.copy()
    adjacency = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(count, count))
    _, component = connected_components(adjacency, directed=False)
    apart = np.flatnonzero(component != component[0])
    if apart.size:
        raise ValueError(f"scan(s) {apart.tolist()} not joined to the first by the edges")

    def poses(x: npt.NDArray[np.float64]) -> Poses:
        # Small corrections of the initial poses, never an absolute angle near the rotation vector's
        # singularity at 180° (a drive that turns round).
        step = x.reshape(count - 1, 6)
        out = initial.copy()
        out[1:, :3, :3] = initial[1:, :3, :3] @ Rotation.from_rotvec(step[:, :3]).as_matrix()
        out[1:, :3, 3] = initial[1:, :3, 3] + step[:, 3:]
        return out

    scale = np.array([LEVER_ARM_M] * 3 + [1.0] * 3)

    def residuals(x: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        return (edge_residuals(poses(x), edges, motions) * scale).ravel()

    sparsity = lil_matrix((6 * len(edges), 6 * (count - 1)), dtype=np.int8)
    for row, pair in enumerate(edges):
        for index in pair:
            if index > 0:
                sparsity[6 * row : 6 * row + 6, 6 * (index - 1) : 6 * index] = 1
    solution = np.zeros(6 * (count - 1))
    # Steps scaled by the Jacobian's columns: a rotation parameter weighs the lever arm's metres, a translation
    # one a metre; unscaled, a hundred-scan graph took the iteration limit without converging.
    for loss in ("soft_l1", "cauchy"):
        solution = least_squares(
            residuals, solution, jac_sparsity=sparsity, loss=loss, f_scale=ROBUST_SCALE_M,
            x_scale="jac", max_nfev=200,
        ).x
    return poses(solution)
