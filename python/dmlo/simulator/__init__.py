"""The LiDAR simulator: procedural street scenes along a drive, an HDL-64E-like sensor, KITTI-layout output.

`simulate_sequence` is the entry point (also `dmlo simulate`). Ray casting runs in `dmlo_rs.RayScene`.
"""

from dmlo.simulator.scene import StreetScene, generate_street
from dmlo.simulator.sensor import HDL64E, LidarModel, hdl64e_elevations
from dmlo.simulator.sequence import SimulationResult, simulate_sequence
from dmlo.simulator.trajectory import (
    KITTI_TR,
    camera_to_lidar_poses,
    generate_drive,
    lidar_to_camera_poses,
    read_kitti_calib_tr,
    read_kitti_poses,
)

__all__ = [
    "HDL64E",
    "KITTI_TR",
    "LidarModel",
    "SimulationResult",
    "StreetScene",
    "camera_to_lidar_poses",
    "generate_drive",
    "generate_street",
    "hdl64e_elevations",
    "lidar_to_camera_poses",
    "read_kitti_calib_tr",
    "read_kitti_poses",
    "simulate_sequence",
]
