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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dmlo.simulator.primitives import VEGETATION, SceneAttributes


def hdl64e_elevations() -> npt.NDArray[np.float64]:
    """64 beam elevations (degrees, top first) of a Velodyne HDL-64E S2 as in KITTI: an upper block of 32
    lasers from +2.0° to −8.33° (~1/3° apart) and a lower block of 32 from −8.83° to −24.8° (~1/2° apart)."""
    upper = np.linspace(2.0, -8.33, 32)
    lower = np.linspace(-8.83, -24.8, 32)
    return np.concatenate([upper, lower])


@dataclass(frozen=True)
class LidarModel:
    """A spinning multi-beam LiDAR and its noise model."""

    name: str
    elevations_deg: tuple[float, ...]
    azimuth_count: int
    max_range: float
    min_range: float
    range_noise_std: float
    dropout_probability: float
    mount_height: float

    @property
    def beams(self) -> int:
        return len(self.elevations_deg)

    def elevations(self) -> npt.NDArray[np.float64]:
        return np.asarray(self.elevations_deg, dtype=np.float64)


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

SENSORS = {"hdl64e": HDL64E}


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

    points = np.empty((int(keep.sum()), 4), dtype=np.float32)
    points[:, :3] = directions[keep] * measured[keep, None]
    points[:, 3] = reflectance[keep]
    labels = (semantic[keep] & 0xFFFF) | (attributes.instance[safe][keep] << 16)
    return points, labels.astype(np.uint32)


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
