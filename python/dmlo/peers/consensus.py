"""A per-pair reference motion for real scans: the consensus of two independent GICPs.

KITTI's ground truth is good to only 1–3 cm a frame, too coarse to judge centimetre odometry pair by
pair. Two GICP implementations written independently (small_gicp and Open3D) that agree on a pair are a
tighter reference; their mean is the consensus, their disagreement its own error bar. Each pair is
aligned coarse to fine (1 m voxels and 3 m correspondences, then 0.25 m and 1 m) from the ground truth's
motion when there is one, else from the previous pair's consensus, so neither GICP needs a good guess.

Two GICPs can agree on a pair and still share its error: scan-to-scan alignments of the same two sparse
scans see the same sampling of the same surfaces. With `span` above 1 each GICP also aligns every scan
with the next `span` scans, and the poses that fit all those alignments best (`dmlo.peers.pose_graph`)
give the multi-scan consensus, whose error of one alignment is averaged with its neighbours'.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from dmlo.peers.peers import _import_problem
from dmlo.peers.pose_graph import edge_residuals, solve_pose_graph
from dmlo.poses import accumulate_motions, midpoint_motion

Matrix4 = npt.NDArray[np.float64]
Align = Callable[[npt.NDArray[np.float64], npt.NDArray[np.float64], Matrix4], Matrix4]

# (voxel, max correspondence distance) in metres, coarse to fine.
STAGES = ((1.0, 3.0), (0.25, 1.0))


@dataclass
class ConsensusReference:
    """Per consecutive pair i → i+1: the sensor's motion `T_i_{i+1}` (the pose delta), and how far the GICPs
    behind it disagree on that pair (m, °). With `span` > 1 the motions are the multi-scan consensus's, and
    `residual_m` says how far each alignment behind it lies from the poses that fit them all."""

    motions: npt.NDArray[np.float64]  # (N-1, 4, 4)
    disagreement_m: npt.NDArray[np.float64]  # (N-1,); 0 with a single GICP
    disagreement_deg: npt.NDArray[np.float64]
    sources: tuple[str, ...]  # the GICPs averaged
    span: int = 1  # scans apart the aligned pairs reach; 1: consecutive pairs only
    residual_m: npt.NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))  # per alignment, span > 1
    consecutive_motions: npt.NDArray[np.float64] | None = None  # span > 1: the consecutive pairs' consensus


def _small_gicp() -> Align:
    import small_gicp

    def align(target: npt.NDArray[np.float64], source: npt.NDArray[np.float64], initial: Matrix4) -> Matrix4:
        transform = initial
        for voxel, distance in STAGES:
            result = small_gicp.align(
                target, source, init_T_target_source=transform, registration_type="GICP",
                downsampling_resolution=voxel, max_correspondence_distance=distance, num_threads=2,
            )
            transform = np.asarray(result.T_target_source, dtype=np.float64)
        return transform

    return align


def _open3d_gicp() -> Align:
    import open3d as o3d

    reg = o3d.pipelines.registration
    criteria = reg.ICPConvergenceCriteria(relative_fitness=1e-9, relative_rmse=1e-9, max_iteration=100)

    def cloud(xyz: npt.NDArray[np.float64], voxel: float):  # type: ignore[no-untyped-def]
        # Covariances left to Open3D's GICP itself: estimated beforehand from 20 neighbours of the
        # downsampled cloud, they pulled its alignment decimetres away from small_gicp's on real scans.
        return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz)).voxel_down_sample(voxel)

    def align(target: npt.NDArray[np.float64], source: npt.NDArray[np.float64], initial: Matrix4) -> Matrix4:
        transform = initial
        for voxel, distance in STAGES:
            result = reg.registration_generalized_icp(
                cloud(source, voxel), cloud(target, voxel), distance, transform,
                reg.TransformationEstimationForGeneralizedICP(), criteria,
            )
            transform = np.asarray(result.transformation, dtype=np.float64)
        return transform

    return align


GICPS: tuple[tuple[str, str, Callable[[], Align]], ...] = (
    ("small_gicp", "small_gicp", _small_gicp),
    ("Open3D", "open3d", _open3d_gicp),
)


def available_gicps() -> list[str]:
    """The GICPs that can run here (their packages load)."""
    return [name for name, package, _ in GICPS if _import_problem(package) is None]


def missing_gicps() -> dict[str, str]:
    """The GICPs that cannot run here, each with why (not installed, or installed but not loading)."""
    return {name: problem for name, package, _ in GICPS if (problem := _import_problem(package)) is not None}


def gicp_consensus(
    scans: Sequence[npt.NDArray[np.float32]],
    ground_truth: npt.NDArray[np.float64] | None = None,
    span: int = 1,
) -> ConsensusReference:
    """The consensus motion of every consecutive pair of `scans` (N×4 or N×3, sensor frame).

    `ground_truth` (N, 4, 4) `T_world_lidar`, when known, only seeds each alignment. `span` > 1 aligns every
    scan with the next `span` scans too and returns the multi-scan consensus (module docs). Raises
    RuntimeError when neither small_gicp nor Open3D is installed, ValueError for a span below 1.
    """
    if isinstance(span, bool) or not isinstance(span, (int, np.integer)) or span < 1:
        raise ValueError(f"span must be an integer ≥ 1, got {span!r}")
    aligners = [(name, make()) for name, package, make in GICPS if _import_problem(package) is None]
    if not aligners:
        raise RuntimeError("the GICP consensus needs small_gicp or open3d (pip install 'dmlo[bench]')")
    clouds = [np.ascontiguousarray(scan[:, :3], dtype=np.float64) for scan in scans]
    clouds = [cloud[np.isfinite(cloud).all(axis=1)] for cloud in clouds]
    motions, spread_m, spread_deg, pair_estimates = [], [], [], []
    previous = np.eye(4)
    for i in range(1, len(clouds)):
        initial = previous if ground_truth is None else np.linalg.inv(ground_truth[i - 1]) @ ground_truth[i]
        estimates = [align(clouds[i - 1], clouds[i], initial) for _, align in aligners]
        consensus = estimates[0] if len(estimates) == 1 else midpoint_motion(estimates[0], estimates[1])
        step = np.linalg.inv(estimates[0]) @ estimates[-1]
        spread_m.append(float(np.linalg.norm(step[:3, 3])))
        spread_deg.append(float(np.degrees(np.arccos(np.clip((np.trace(step[:3, :3]) - 1) / 2, -1.0, 1.0)))))
        motions.append(consensus)
        pair_estimates.append(estimates)
        previous = consensus
    reference = ConsensusReference(
        motions=np.stack(motions) if motions else np.empty((0, 4, 4)),
        disagreement_m=np.asarray(spread_m),
        disagreement_deg=np.asarray(spread_deg),
        sources=tuple(name for name, _ in aligners),
    )
    if span == 1 or len(clouds) < 3:
        return reference
    return _multi_scan(reference, pair_estimates, clouds, [align for _, align in aligners], span)


def _multi_scan(
    consecutive: ConsensusReference,
    pair_estimates: list[list[Matrix4]],
    clouds: list[npt.NDArray[np.float64]],
    aligners: list[Align],
    span: int,
) -> ConsensusReference:
    """`consecutive` made the multi-scan consensus: each GICP's alignments of every pair up to `span` scans
    apart (`pair_estimates` those of the consecutive pairs, per pair one a GICP), the others seeded by the
    consecutive consensus, solved jointly."""
    chain = accumulate_motions(np.linalg.inv(consecutive.motions))  # it chains T_tgt_ref, the inverses
    edges = [(i, i + 1) for i, estimates in enumerate(pair_estimates) for _ in estimates]
    measured = [estimate for estimates in pair_estimates for estimate in estimates]
    for i in range(len(clouds)):
        for j in range(i + 2, min(len(clouds), i + span + 1)):
            initial = np.linalg.inv(chain[i]) @ chain[j]
            for align in aligners:
                edges.append((i, j))
                measured.append(align(clouds[i], clouds[j], initial))
    edge_array, motions = np.asarray(edges, dtype=np.intp), np.stack(measured)
    poses = solve_pose_graph(chain, edge_array, motions)
    residual = np.linalg.norm(edge_residuals(poses, edge_array, motions)[:, 3:], axis=1)
    return replace(
        consecutive,
        motions=np.linalg.inv(poses[:-1]) @ poses[1:],
        span=span,
        residual_m=residual,
        consecutive_motions=consecutive.motions,
    )

