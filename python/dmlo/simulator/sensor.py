"""The simulated LiDAR: beam pattern, and the measurement model turning ray hits into KITTI points.

Measurement model (per ray that hits within `max_range`):

- range noise: Gaussian, `range_noise_std` (2 cm for the HDL-64E); vegetation adds a one-sided
  penetration term (|N(0, 0.15 m)|) since a real beam enters a canopy before it returns;
- reflectance: `albedo · (0.55 + 0.45·cos θ)` with θ the incidence angle (the HDL-64E's calibrated
  intensity depends only weakly on incidence), plus N(0, 0.03), clipped to [0, 1];
- dropouts: a base probability, more for weak returns (far and dark), and more in vegetation;
- no returns closer than `min_range` (the ego car's body) or beyond `max_range`.

By default all rays of a revolution leave from the pose of the frame (no motion distortion within a
sweep); `simulate_sequence(..., motion_distortion=True)` casts each azimuth column from its own pose.

A sensor may be a rig of several spinning units (`LidarModel.mounts`, each `T_rig_unit`): every unit
casts its own revolution from `T_world_rig · T_rig_unit` and its points are returned in the rig frame,
as Argoverse gives the sweep of its two stacked VLP-32C in the ego-vehicle frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dmlo.poses import quaternion_to_matrix
from dmlo.simulator.primitives import VEGETATION, SceneAttributes


def hdl64e_elevations() -> npt.NDArray[np.float64]:
    """64 beam elevations (degrees, top first) of a Velodyne HDL-64E S2 as in KITTI: an upper block of 32
    lasers from +2.0° to −8.33° (~1/3° apart) and a lower block of 32 from −8.83° to −24.8° (~1/2° apart)."""
    upper = np.linspace(2.0, -8.33, 32)
    lower = np.linspace(-8.83, -24.8, 32)
    return np.concatenate([upper, lower])


def vlp32c_elevations() -> npt.NDArray[np.float64]:
    """32 beam elevations (degrees, top first) of a Velodyne VLP-32C: +15° … −25°, 1/3° apart from
    +1.67° to −4° and sparser beyond. Argoverse numbers the lasers 0–31 in this order."""
    return np.array(
        [15.0, 10.333, 7.0, 4.667, 3.333, 2.333, 1.667, 1.333, 1.0, 0.667, 0.333, 0.0, -0.333, -0.667,
         -1.0, -1.333, -1.667, -2.0, -2.333, -2.667, -3.0, -3.333, -3.667, -4.0, -4.667, -5.333, -6.148,
         -7.254, -8.843, -11.31, -15.639, -25.0]
    )  # fmt: skip


def mount_matrix(
    quaternion_wxyz: tuple[float, float, float, float], translation: tuple[float, float, float]
) -> tuple[float, ...]:
    """A mount `T_rig_unit` as a row-major 16-tuple from a `w x y z` quaternion and a translation."""
    w, x, y, z = quaternion_wxyz
    matrix = np.eye(4)
    matrix[:3, :3] = quaternion_to_matrix([x, y, z, w])[0]
    matrix[:3, 3] = translation
    return tuple(float(v) for v in matrix.ravel())


@dataclass(frozen=True)
class LidarModel:
    """A spinning multi-beam LiDAR (or a rig of identical units, see `mounts`) and its noise model.

    `mount_height` is the height of the pose frame above the ground: the sensor's own for a single unit,
    the ego-vehicle origin's for a rig. `mounts` holds each unit's `T_rig_unit` (row-major 4×4); empty
    means one unit at the pose frame. `default_layout` is the output layout `simulate_sequence` writes
    unless told otherwise.
    """

    name: str
    elevations_deg: tuple[float, ...]
    azimuth_count: int
    max_range: float
    min_range: float
    range_noise_std: float
    dropout_probability: float
    mount_height: float
    mounts: tuple[tuple[float, ...], ...] = ()
    default_layout: str = "kitti"

    @property
    def beams(self) -> int:
        """Beams of one unit."""
        return len(self.elevations_deg)

    @property
    def units(self) -> int:
        return max(1, len(self.mounts))

    def elevations(self) -> npt.NDArray[np.float64]:
        return np.asarray(self.elevations_deg, dtype=np.float64)

    def unit_mounts(self) -> list[npt.NDArray[np.float64] | None]:
        """`T_rig_unit` (4×4) of every unit; None for the single unit of a plain sensor (no transform)."""
        if not self.mounts:
            return [None]
        return [np.asarray(m, dtype=np.float64).reshape(4, 4) for m in self.mounts]


HDL64E = LidarModel(
    name="hdl64e",
    elevations_deg=tuple(float(e) for e in hdl64e_elevations()),
    azimuth_count=2083,
    max_range=120.0,
    min_range=2.5,
    range_noise_std=0.02,
    dropout_probability=0.02,
    mount_height=1.73,
)

# Argoverse 1: two VLP-32C stacked on the roof, the lower one upside down, so the rig sees −25° … +25°
# with the beams densest near the horizon. Mounts (`vehicle_SE3_up_lidar_`, `vehicle_SE3_down_lidar_`) as in the
# `vehicle_calibration_info.json` of an AV1 tracking log; the ego frame's origin (rear axle centre) is
# 0.34 m above the road, as the ground of a real AV1 sweep shows. 0.2° azimuth steps at 10 Hz, 200 m range,
# ±3 cm accuracy.
ARGOVERSE_VLP32C_PAIR = LidarModel(
    name="argoverse",
    elevations_deg=tuple(float(e) for e in vlp32c_elevations()),
    azimuth_count=1800,
    max_range=200.0,
    min_range=1.0,
    range_noise_std=0.025,
    dropout_probability=0.02,
    mount_height=0.34,
    mounts=(
        mount_matrix((0.999885, 0.001139, -0.001077, -0.015095), (1.3505, -0.0040, 1.5701)),
        mount_matrix((0.000057, -0.994250, -0.107082, -0.000305), (1.3503, -0.0020, 1.4772)),
    ),
    default_layout="argoverse",
)

SENSORS = {"hdl64e": HDL64E, "argoverse": ARGOVERSE_VLP32C_PAIR}


def measure(
    sensor: LidarModel,
    directions: npt.NDArray[np.float64],
    ranges: npt.NDArray[np.float64],
    primitive: npt.NDArray[np.int64],
    cos_incidence: npt.NDArray[np.float32],
    attributes: SceneAttributes,
    rng: np.random.Generator,
    pose: npt.NDArray[np.float64] | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint32]]:
    """Points (N,4) float32 `x y z reflectance` in the LiDAR frame and SemanticKITTI labels (N,) uint32
    for the rays (flattened, beam-major) that return.

    `directions` (R,3) are the LiDAR-frame unit rays; `ranges`, `primitive`, `cos_incidence` (R,) are the
    ray-casting result and `attributes` the per-primitive class, instance and albedo. With the scan's `pose`
    ((4,4) or (W,4,4) per azimuth column) facades get windows: glass drops half of its returns, the rest
    come from the room behind (a plane `depth` behind the facade) with a dimmer reflectance.
    """
    xyz, reflectance, labels, _ = measure_rays(
        sensor, directions, ranges, primitive, cos_incidence, attributes, rng, pose
    )
    points = np.empty((len(xyz), 4), dtype=np.float32)
    points[:, :3] = xyz
    points[:, 3] = reflectance
    return points, labels


def measure_rays(
    sensor: LidarModel,
    directions: npt.NDArray[np.float64],
    ranges: npt.NDArray[np.float64],
    primitive: npt.NDArray[np.int64],
    cos_incidence: npt.NDArray[np.float32],
    attributes: SceneAttributes,
    rng: np.random.Generator,
    pose: npt.NDArray[np.float64] | None = None,
) -> tuple[
    npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.uint32], npt.NDArray[np.int64]
]:
    """`measure` before the float32 packing: points (N,3) and reflectance (N,) in float64, labels, and the
    index of the ray each point comes from (beam = index // azimuth_count)."""
    ranges = ranges.reshape(-1)
    primitive = primitive.reshape(-1)
    cos_incidence = cos_incidence.reshape(-1).astype(np.float64)
    count = len(ranges)
    # Draw every random number for every ray, hit or not, so the stream does not depend on the scene.
    range_noise = rng.normal(0.0, sensor.range_noise_std, count)
    penetration = np.abs(rng.normal(0.0, 0.15, count))
    reflect_noise = rng.normal(0.0, 0.03, count)
    uniform = rng.random(count)

    hit = primitive >= 0
    safe = np.where(hit, primitive, 0)
    semantic = attributes.semantic[safe]
    albedo = attributes.albedo[safe].astype(np.float64)
    vegetation = semantic == VEGETATION
    window = np.zeros(count, dtype=bool)
    if pose is not None:
        window = _window_hits(directions, ranges, primitive, hit, attributes, pose)
    depth = attributes.windows[safe, 2]
    behind = np.where(window, depth / np.maximum(cos_incidence, 0.2), 0.0)
    measured = ranges + behind + range_noise + np.where(vegetation, penetration, 0.0)
    reflectance = albedo * (0.55 + 0.45 * cos_incidence) * np.where(window, 0.4, 1.0)
    reflectance = np.clip(reflectance + reflect_noise, 0.0, 1.0)
    weak = np.clip((ranges / sensor.max_range) ** 2 * (1.0 - reflectance), 0.0, 1.0)
    drop_probability = (
        sensor.dropout_probability + 0.3 * weak + np.where(vegetation, 0.12, 0.0) + np.where(window, 0.5, 0.0)
    )
    keep = (
        hit & (uniform >= drop_probability) & (measured >= sensor.min_range) & (measured <= sensor.max_range)
    )

    xyz = directions[keep] * measured[keep, None]
    labels = (semantic[keep] & 0xFFFF) | (attributes.instance[safe][keep] << 16)
    return xyz, reflectance[keep], labels.astype(np.uint32), np.nonzero(keep)[0]


def _window_hits(
    directions: npt.NDArray[np.float64],
    ranges: npt.NDArray[np.float64],
    primitive: npt.NDArray[np.int64],
    hit: npt.NDArray[np.bool_],
    attributes: SceneAttributes,
    pose: npt.NDArray[np.float64],
) -> npt.NDArray[np.bool_]:
    """Which rays hit a window of a box's side face (the grid lives in the face's own coordinates)."""
    window = np.zeros(len(ranges), dtype=bool)
    candidates = np.nonzero(hit & (attributes.windows[np.where(hit, primitive, 0), 0] > 0))[0]
    if len(candidates) == 0:
        return window
    local_points = directions[candidates] * ranges[candidates, None]
    if pose.ndim == 2:
        world = local_points @ pose[:3, :3].T + pose[:3, 3]
    else:
        column = pose[candidates % len(pose)]
        world = np.einsum("nij,nj->ni", column[:, :3, :3], local_points) + column[:, :3, 3]
    box = attributes.boxes[primitive[candidates]]
    rotation = box[:, 3:12].reshape(-1, 3, 3)
    half = box[:, 12:15]
    local = np.einsum("nji,nj->ni", rotation, world - box[:, :3])  # Rᵀ (p − c)
    relative = np.abs(local) / half
    side_face = relative[:, 2] < relative[:, :2].max(1)
    along = np.where(relative[:, 0] >= relative[:, 1], local[:, 1] + half[:, 1], local[:, 0] + half[:, 0])
    height = local[:, 2] + half[:, 2]
    spacing, floor = (
        attributes.windows[primitive[candidates], 0],
        attributes.windows[primitive[candidates], 1],
    )
    u = np.mod(along, spacing) / spacing
    v = np.mod(height, floor) / floor
    inside = side_face & (u > 0.25) & (u < 0.75) & (v > 0.4) & (v < 0.85) & (height > floor)
    window[candidates[inside]] = True
    return window
