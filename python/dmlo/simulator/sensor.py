"""The simulated LiDAR: beam pattern, and the measurement model turning ray hits into KITTI points.

Measurement model (per ray that hits within `max_range`):

- range noise: Gaussian, `range_noise_std` (2 cm for the HDL-64E); vegetation adds a one-sided
  penetration term (|N(0, 0.15 m)|) since a real beam enters a canopy before it returns;
- reflectance: `albedo · (0.3 + 0.7·cos θ)` with θ the incidence angle, plus N(0, 0.02), clipped to [0, 1];
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
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint32]]:
    """Points (N,4) float32 `x y z reflectance` in the LiDAR frame and SemanticKITTI labels (N,) uint32
    for the rays (flattened, beam-major) that return.

    `directions` (R,3) are the LiDAR-frame unit rays; `ranges`, `primitive`, `cos_incidence` (R,) are the
    ray-casting result and `attributes` the per-primitive class, instance and albedo.
    """
    ranges = ranges.reshape(-1)
    primitive = primitive.reshape(-1)
    cos_incidence = cos_incidence.reshape(-1).astype(np.float64)
    count = len(ranges)
    # Draw every random number for every ray, hit or not, so the stream does not depend on the scene.
    range_noise = rng.normal(0.0, sensor.range_noise_std, count)
    penetration = np.abs(rng.normal(0.0, 0.15, count))
    reflect_noise = rng.normal(0.0, 0.02, count)
    uniform = rng.random(count)

    hit = primitive >= 0
    safe = np.where(hit, primitive, 0)
    semantic = attributes.semantic[safe]
    albedo = attributes.albedo[safe].astype(np.float64)
    vegetation = semantic == VEGETATION
    measured = ranges + range_noise + np.where(vegetation, penetration, 0.0)
    reflectance = np.clip(albedo * (0.3 + 0.7 * cos_incidence) + reflect_noise, 0.0, 1.0)
    weak = np.clip((ranges / sensor.max_range) ** 2 * (1.0 - reflectance), 0.0, 1.0)
    drop_probability = sensor.dropout_probability + 0.3 * weak + np.where(vegetation, 0.12, 0.0)
    keep = hit & (uniform >= drop_probability) & (measured >= sensor.min_range) & (measured <= sensor.max_range)

    points = np.empty((int(keep.sum()), 4), dtype=np.float32)
    points[:, :3] = directions[keep] * measured[keep, None]
    points[:, 3] = reflectance[keep]
    labels = (semantic[keep] & 0xFFFF) | (attributes.instance[safe][keep] << 16)
    return points, labels.astype(np.uint32)
