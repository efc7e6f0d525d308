"""The peers `dmlo bench` runs beside DMLO, each behind the same small odometry interface.

Every peer is an optional extra (`pip install dmlo[bench]`): a peer whose package is missing is reported
as unavailable, never an import error for `dmlo` itself. Scan-to-scan peers start each pair from a
constant-velocity guess, as an odometry would; KISS-ICP keeps its own local map and motion model.
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from dmlo.poses import midpoint_motion

Matrix4 = npt.NDArray[np.float64]
Points = npt.NDArray[np.float32]


class FrameOdometry(Protocol):
    """Feeds scans in order; returns `T_world_lidar` of each (the first scan is the world frame)."""

    def register(self, points: Points) -> Matrix4: ...


class ScanToScanOdometry:
    """Chains pairwise registrations; each pair starts from the previous motion (constant velocity)."""

    def __init__(self, align: Callable[[np.ndarray, np.ndarray, Matrix4], Matrix4]) -> None:
        # align(target_xyz, source_xyz, initial T_target_source) -> T_target_source
        self._align = align
        self._previous: np.ndarray | None = None
        self._pose = np.eye(4)
        self._motion = np.eye(4)  # T_prev_cur of the last pair

    def register(self, points: Points) -> Matrix4:
        xyz = np.ascontiguousarray(points[:, :3], dtype=np.float64)
        if self._previous is not None:
            self._motion = self._align(self._previous, xyz, self._motion)
            self._pose = self._pose @ self._motion
        self._previous = xyz
        return self._pose.copy()


class KissIcpOdometry:
    """KISS-ICP with its default configuration for a 100 m sensor, deskewing off unless asked for.

    ``voxel_size`` overrides its map voxel (default 1 m = max range / 100). Measured on simulated drives
    starting from standstill (0.1–0.7 m per frame), the default errs 10–20 cm per frame in the ground plane
    for the first tens of frames and 0.25 m voxels about 5 cm; over 300 frames along KITTI 07 both reach
    t_rel ≈ 0.05–0.06 %, the finer map 12× slower. ``deskew`` turns on its motion compensation with
    per-point times from the azimuth (a clockwise sweep, `dmlo_rs.sweep_times` + 0.5 in [0, 1]). KISS-ICP
    deskews to the end of the sweep (its `exp((t − 1) ω)`), half a period after the forward-looking moment
    the ground truth (KITTI's, the simulator's) and DMLO refer to; its poses are moved back by half its own
    last motion so that all are compared at the same moment (without it, half a frame of motion on every
    pose: t_rel 1.19 instead of 0.33 % on a skewed drive).
    """

    def __init__(self, voxel_size: float | None = None, deskew: bool = False) -> None:
        from kiss_icp.config import load_config
        from kiss_icp.kiss_icp import KissICP

        config = load_config(None)
        config.data.deskew = deskew
        if voxel_size is not None:
            config.mapping.voxel_size = voxel_size
        self._kiss = KissICP(config)
        self._deskew = deskew

    def register(self, points: Points) -> Matrix4:
        import dmlo_rs

        xyz = np.ascontiguousarray(points[:, :3], dtype=np.float64)
        if not self._deskew:
            self._kiss.register_frame(xyz, np.empty(0))
            return np.asarray(self._kiss.last_pose, dtype=np.float64).copy()
        self._kiss.register_frame(xyz, 0.5 + np.asarray(dmlo_rs.sweep_times(xyz)))
        end_of_sweep = np.asarray(self._kiss.last_pose, dtype=np.float64)
        half_motion = midpoint_motion(np.eye(4), np.asarray(self._kiss.last_delta, dtype=np.float64))
        return end_of_sweep @ np.linalg.inv(half_motion)


def small_gicp_align(registration_type: str) -> Callable[[np.ndarray, np.ndarray, Matrix4], Matrix4]:
    import small_gicp

    def align(target: np.ndarray, source: np.ndarray, initial: Matrix4) -> Matrix4:
        result = small_gicp.align(
            target,
            source,
            init_T_target_source=initial,
            registration_type=registration_type,
            downsampling_resolution=0.25,
            max_correspondence_distance=1.0,
            num_threads=2,
        )
        return np.asarray(result.T_target_source, dtype=np.float64)

    return align


def _open3d_cloud(xyz: np.ndarray, voxel: float, normals: bool):  # type: ignore[no-untyped-def]
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz)).voxel_down_sample(voxel)
    if normals:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * voxel, max_nn=30))
    return cloud


def open3d_icp_align(kind: str) -> Callable[[np.ndarray, np.ndarray, Matrix4], Matrix4]:
    import open3d as o3d

    reg = o3d.pipelines.registration
    estimation = {
        "point_to_point": reg.TransformationEstimationPointToPoint,
        "point_to_plane": reg.TransformationEstimationPointToPlane,
        "gicp": reg.TransformationEstimationForGeneralizedICP,
    }[kind]()
    criteria = reg.ICPConvergenceCriteria(max_iteration=30)
    run = reg.registration_generalized_icp if kind == "gicp" else reg.registration_icp
    needs_normals = kind != "point_to_point"

    def align(target: np.ndarray, source: np.ndarray, initial: Matrix4) -> Matrix4:
        tgt = _open3d_cloud(target, 0.25, needs_normals)
        src = _open3d_cloud(source, 0.25, needs_normals)
        result = run(src, tgt, 1.0, initial, estimation, criteria)
        return np.asarray(result.transformation, dtype=np.float64)

    return align


def fpfh_ransac_align(target: np.ndarray, source: np.ndarray, voxel: float = 0.5, seed: int = 0) -> Matrix4:
    """Open3D's global registration (FPFH features + RANSAC), no initial guess: T_target_source.

    Seeded, so that a benchmark run can be repeated (unseeded, the same pair moved by up to 0.26 m
    between three calls; seeded, identical on this 2-core machine)."""
    import open3d as o3d

    o3d.utility.random.seed(seed)
    reg = o3d.pipelines.registration
    clouds = [_open3d_cloud(xyz, voxel, normals=True) for xyz in (source, target)]
    features = [
        reg.compute_fpfh_feature(c, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))  # type: ignore[call-arg]
        for c in clouds
    ]
    result = reg.registration_ransac_based_on_feature_matching(
        clouds[0],
        clouds[1],
        features[0],
        features[1],
        True,
        1.5 * voxel,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
        reg.RANSACConvergenceCriteria(100000, 0.999),
    )
    return np.asarray(result.transformation, dtype=np.float64)


@dataclass(frozen=True)
class Peer:
    name: str
    package: str  # the importable module the peer needs
    make: Callable[[], FrameOdometry]
    by_default: bool = True  # run when no peers are named (slow or special-purpose ones are not)

    @property
    def available(self) -> bool:
        return self.unavailable_reason is None

    @property
    def unavailable_reason(self) -> str | None:
        """Why the peer cannot run here (its package is missing or does not load), or None."""
        return _import_problem(self.package)


@functools.cache
def _import_problem(package: str) -> str | None:
    # An installed package can still fail to load, e.g. Open3D's wheel without the system's libusb.
    if importlib.util.find_spec(package) is None:
        return f"{package} is not installed (pip install 'dmlo[bench]')"
    try:
        importlib.import_module(package)
    except (ImportError, OSError) as err:
        return f"{package} is installed but does not load: {err}"
    return None


PEERS: tuple[Peer, ...] = (
    Peer("KISS-ICP", "kiss_icp", KissIcpOdometry),
    Peer("KISS-ICP deskewed", "kiss_icp", lambda: KissIcpOdometry(deskew=True), by_default=False),
    Peer("KISS-ICP 0.25 m voxels", "kiss_icp", lambda: KissIcpOdometry(voxel_size=0.25)),
    Peer("small_gicp GICP", "small_gicp", lambda: ScanToScanOdometry(small_gicp_align("GICP"))),
    Peer("Open3D ICP p2p", "open3d", lambda: ScanToScanOdometry(open3d_icp_align("point_to_point"))),
    Peer("Open3D ICP p2pl", "open3d", lambda: ScanToScanOdometry(open3d_icp_align("point_to_plane"))),
    Peer("Open3D GICP", "open3d", lambda: ScanToScanOdometry(open3d_icp_align("gicp"))),
    Peer(
        "Open3D FPFH+RANSAC",
        "open3d",
        lambda: ScanToScanOdometry(lambda tgt, src, _initial: fpfh_ransac_align(tgt, src)),
        by_default=False,
    ),
)
