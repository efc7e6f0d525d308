"""Simulates a drive and writes it as a KITTI odometry sequence (plus SemanticKITTI labels)."""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import dmlo_rs
import numpy as np
import numpy.typing as npt

from dmlo.simulator.primitives import SceneAttributes
from dmlo.simulator.scene import StreetScene, generate_street
from dmlo.simulator.sensor import SENSORS, LidarModel, measure
from dmlo.simulator.trajectory import (
    FRAME_RATE_HZ,
    KITTI_TR,
    camera_to_lidar_poses,
    generate_drive,
    lidar_to_camera_poses,
    orthonormalize,
    read_kitti_calib_tr,
    read_kitti_poses,
    sweep_column_poses,
)

# Camera matrices of KITTI sequences 00–02, written as placeholders so readers expecting P0..P3 work.
_KITTI_P = {
    "P0": [718.856, 0.0, 607.1928, 0.0, 0.0, 718.856, 185.2157, 0.0, 0.0, 0.0, 1.0, 0.0],
    "P1": [718.856, 0.0, 607.1928, -386.1448, 0.0, 718.856, 185.2157, 0.0, 0.0, 0.0, 1.0, 0.0],
    "P2": [718.856, 0.0, 607.1928, 45.38225, 0.0, 718.856, 185.2157, -0.1130887, 0.0, 0.0, 1.0, 0.003779761],
    "P3": [718.856, 0.0, 607.1928, -337.2877, 0.0, 718.856, 185.2157, 2.369057, 0.0, 0.0, 1.0, 0.004915215],
}


@dataclass
class SimulationResult:
    """What `simulate_sequence` wrote and how long it took."""

    out_dir: Path
    lidar_poses: npt.NDArray[np.float64]  # (N,4,4) T_world_lidar, frame 0 = identity
    points_per_frame: list[int] = field(default_factory=list)
    cast_seconds: list[float] = field(default_factory=list)
    frame_seconds: list[float] = field(default_factory=list)
    frame_cpu_seconds: list[float] = field(default_factory=list)  # all threads, robust to a busy machine
    scene_seconds: float = 0.0
    static_primitives: int = 0


def simulate_sequence(
    out_dir: str | Path,
    frames: int,
    seed: int,
    trajectory: str | Path | None = None,
    start: int = 0,
    calib: str | Path | None = None,
    sensor: str | LidarModel = "hdl64e",
    progress: bool = True,
    motion_distortion: bool = False,
    overwrite: bool = False,
) -> SimulationResult:
    """Simulates `frames` scans of a street drive and writes a KITTI-layout sequence into `out_dir`:
    `velodyne/NNNNNN.bin` (float32 x y z reflectance), `labels/NNNNNN.label` (uint32, class | instance << 16,
    moving cars class 252), `poses.txt` (camera frame, `Tr · T_world_lidar · Tr⁻¹`, frame 0 identity),
    `calib.txt` (`Tr:` and placeholder P0..P3), `times.txt` and `simulation.json` (seed and parameters).

    The ego motion is frames `start … start+frames−1` of the KITTI camera-frame pose file `trajectory`
    (converted with `Tr` from `calib`, or the built-in KITTI 00–02 `Tr`), or else a generated drive.
    With `motion_distortion`, every azimuth column is cast from the pose of the moment it fires (constant
    velocity within a sweep, the frame pose at the forward-looking column) and points stay in the sensor
    frame of their firing time, as in raw KITTI scans; by default a sweep is instantaneous.
    The same arguments always give byte-identical files. A previous simulation in `out_dir` is replaced
    (its old `.bin`/`.label` files deleted first, so no stale frame survives); other scans there are refused
    unless `overwrite`.
    """
    if frames < 1:
        raise ValueError(f"frames: must be at least 1, got {frames}")
    if start < 0:
        raise ValueError(f"start: must be non-negative, got {start}")
    if isinstance(sensor, str):
        if sensor not in SENSORS:
            raise ValueError(f"sensor: unknown preset {sensor!r}; known: {', '.join(sorted(SENSORS))}")
        model = SENSORS[sensor]
    else:
        model = sensor
    tr = read_kitti_calib_tr(calib) if calib is not None else KITTI_TR
    if trajectory is not None:
        camera_poses = read_kitti_poses(trajectory)
        if start + frames > len(camera_poses):
            raise ValueError(
                f"trajectory {trajectory} has {len(camera_poses)} poses; "
                f"start {start} + frames {frames} exceeds it"
            )
        lidar_poses = orthonormalize(camera_to_lidar_poses(camera_poses[start : start + frames], tr))
    else:
        if start != 0:
            raise ValueError("start: only meaningful with a trajectory file")
        lidar_poses = generate_drive(frames, seed)

    out = Path(out_dir)
    old_scans = sorted((out / "velodyne").glob("*.bin")) + sorted((out / "labels").glob("*.label"))
    if old_scans and not overwrite and not (out / "simulation.json").is_file():
        raise ValueError(
            f"out: {out} already holds scans not written by the simulator ({len(old_scans)} files); "
            "pass overwrite=True (--overwrite) to replace them"
        )
    for old in old_scans:
        old.unlink()
    (out / "velodyne").mkdir(parents=True, exist_ok=True)
    (out / "labels").mkdir(parents=True, exist_ok=True)
    result = SimulationResult(out_dir=out, lidar_poses=lidar_poses)

    began = time.perf_counter()
    street = generate_street(lidar_poses, seed, model.mount_height)
    static_scene, static_attributes = street.static.build()
    result.scene_seconds = time.perf_counter() - began
    result.static_primitives = len(static_scene)

    elevations = model.elevations()
    directions = dmlo_rs.lidar_scan_directions(elevations, model.azimuth_count)
    times = np.arange(frames) / FRAME_RATE_HZ

    indices = range(frames)
    if progress:
        from tqdm import tqdm  # type: ignore[import-untyped]

        indices = tqdm(indices, desc="simulate", unit="scan")
    for k in indices:
        frame_began, frame_cpu_began = time.perf_counter(), time.process_time()
        sweep_poses = (
            sweep_column_poses(lidar_poses, k, model.azimuth_count) if motion_distortion else lidar_poses[k]
        )
        points, labels, cast_seconds = render_frame(
            street,
            static_scene,
            static_attributes,
            model,
            directions,
            sweep_poses,
            float(times[k]),
            np.random.default_rng([seed, 0x5CA7, k]),
        )
        points.tofile(out / "velodyne" / f"{k:06d}.bin")
        labels.tofile(out / "labels" / f"{k:06d}.label")
        result.points_per_frame.append(len(points))
        result.cast_seconds.append(cast_seconds)
        result.frame_seconds.append(time.perf_counter() - frame_began)
        result.frame_cpu_seconds.append(time.process_time() - frame_cpu_began)

    camera_poses_out = lidar_to_camera_poses(lidar_poses, tr)
    with open(out / "poses.txt", "w") as f:
        for pose in camera_poses_out:
            f.write(" ".join(f"{v:.12e}" for v in pose[:3, :].ravel()) + "\n")
    with open(out / "calib.txt", "w") as f:
        for name, values in _KITTI_P.items():
            f.write(f"{name}: " + " ".join(f"{v:.12e}" for v in values) + "\n")
        f.write("Tr: " + " ".join(f"{v:.12e}" for v in tr[:3, :].ravel()) + "\n")
    with open(out / "times.txt", "w") as f:
        for t in times:
            f.write(f"{t:.6e}\n")
    meta = {
        "generator": "dmlo simulate",
        "dmlo_version": dmlo_rs.__version__,
        "seed": seed,
        "frames": frames,
        "start": start,
        "trajectory": str(trajectory) if trajectory is not None else None,
        "calib": str(calib) if calib is not None else None,
        "frame_rate_hz": FRAME_RATE_HZ,
        "sensor": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(model).items()},
        "street": asdict(street.layout),
        "static_primitives": result.static_primitives,
        "moving_cars": len(street.moving_cars),
        "motion_distortion": motion_distortion,
    }
    (out / "simulation.json").write_text(json.dumps(meta, indent=2) + "\n")
    return result


def render_frame(
    street: StreetScene,
    static_scene: dmlo_rs.RayScene,
    static_attributes: SceneAttributes,
    model: LidarModel,
    directions: npt.NDArray[np.float64],
    pose: npt.NDArray[np.float64],
    time_s: float,
    rng: np.random.Generator,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint32], float]:
    """One scan at `pose` ((4,4), or (W,4,4) per azimuth column) and `time_s`: static scene plus the moving
    cars at that time. Returns points, labels and the seconds spent ray casting."""
    elevations = model.elevations()
    began = time.perf_counter()
    ranges, primitive, cosines = static_scene.cast_scan(
        pose, elevations, model.azimuth_count, model.max_range
    )
    dynamic = street.dynamic(time_s, pose[..., :2, 3].reshape(-1, 2).mean(0))
    attributes = static_attributes
    if len(dynamic):
        dynamic_scene, dynamic_attributes = dynamic.build()
        d_ranges, d_primitive, d_cosines = dynamic_scene.cast_scan(
            pose, elevations, model.azimuth_count, model.max_range
        )
        closer = d_ranges < ranges
        offset = len(static_scene)
        ranges = np.where(closer, d_ranges, ranges)
        primitive = np.where(closer, d_primitive + offset, primitive)
        cosines = np.where(closer, d_cosines, cosines)
        attributes = SceneAttributes.concatenate([static_attributes, dynamic_attributes])
    cast_seconds = time.perf_counter() - began
    points, labels = measure(model, directions, ranges, primitive, cosines, attributes, rng, pose)
    return points, labels, cast_seconds
