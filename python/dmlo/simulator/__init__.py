"""The LiDAR simulator: procedural street scenes along a drive (with mixed traffic on request), an
HDL-64E-like sensor or Argoverse 1's pair of VLP-32C, KITTI-layout or Argoverse-1-layout output.

`simulate_sequence` is the entry point (also `dmlo simulate`). Ray casting runs in `dmlo_rs.RayScene`.
"""

from dmlo.simulator.layouts import LAYOUTS, reflectance_to_intensity
from dmlo.simulator.scene import SCENES, TRAFFIC, StreetScene, generate_street
from dmlo.simulator.sensor import (
    ARGOVERSE_VLP32C_PAIR,
    HDL64E,
    SENSORS,
    LidarModel,
    hdl64e_elevations,
    vlp32c_elevations,
)
from dmlo.simulator.sequence import SimulationResult, simulate_sequence
from dmlo.simulator.trajectory import (
    KITTI_TR,
    camera_to_lidar_poses,
    generate_drive,
    generate_stop_and_go,
    lidar_to_camera_poses,
    read_kitti_calib_tr,
    read_kitti_poses,
)

__all__ = [
    "ARGOVERSE_VLP32C_PAIR",
    "HDL64E",
    "KITTI_TR",
    "LAYOUTS",
    "SENSORS",
    "SCENES",
    "TRAFFIC",
    "LidarModel",
    "SimulationResult",
    "StreetScene",
    "camera_to_lidar_poses",
    "generate_drive",
    "generate_stop_and_go",
    "generate_street",
    "hdl64e_elevations",
    "lidar_to_camera_poses",
    "read_kitti_calib_tr",
    "read_kitti_poses",
    "reflectance_to_intensity",
    "simulate_sequence",
    "vlp32c_elevations",
]
