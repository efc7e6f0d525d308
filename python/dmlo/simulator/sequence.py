"""Simulates a drive and writes it as a KITTI odometry sequence (plus SemanticKITTI labels) or an Argoverse 1
log (see `dmlo.simulator.layouts`)."""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import dmlo_rs
import numpy as np
import numpy.typing as npt

from dmlo.simulator.layouts import LAYOUTS, make_layout
from dmlo.simulator.primitives import SceneAttributes
from dmlo.simulator.reflectance import REFLECTANCE_MODELS, ReflectanceModel, kitti_hdl64e
from dmlo.simulator.scene import SCENES, TRAFFIC, StreetScene, generate_street
from dmlo.simulator.sensor import SENSORS, LidarModel, measure_rays
from dmlo.simulator.trajectory import (
    FRAME_RATE_HZ,
    KITTI_TR,
    camera_to_lidar_poses,
    generate_drive,
    generate_stop_and_go,
    orthonormalize,
    read_kitti_calib_tr,
    read_kitti_poses,
    sweep_column_poses,
)


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
    layout: str | None = None,
    traffic: str = "lanes",
    scene: str = "street",
    laser_gain_spread: float = 0.0,
    escorts: bool = False,
    reflectance: str | ReflectanceModel = "simple",
) -> SimulationResult:
    """Simulates `frames` scans of a street drive with the `sensor` preset (`"hdl64e"`: KITTI's HDL-64E;
    `"argoverse"`: Argoverse 1's two stacked VLP-32C, sweeps in the ego frame) and writes them into
    `out_dir` in `layout` (`"kitti"` or `"argoverse"`, by default the sensor's own; see
    `dmlo.simulator.layouts`) with per-point SemanticKITTI labels (class | instance << 16, moving cars class
    252) and `simulation.json` (seed and parameters). KITTI layout: `velodyne/NNNNNN.bin`,
    `labels/NNNNNN.label`, `poses.txt` (camera frame, `Tr · T_world_lidar · Tr⁻¹`, frame 0 identity),
    `calib.txt`, `times.txt`.

    `traffic`: `"lanes"` (moving cars only in the lanes beside the ego's, along its path: what earlier
    versions simulated, byte for byte) or `"mixed"` (also cross streets with cars crossing the ego's path
    and cars turning into and out of it, each on its own path; see `dmlo.simulator.traffic`). `scene`:
    `"street"`, `"narrow"` (a residential street: kerbs 3.5–5.5 m away, no lanes beside the ego's) or
    `"highway"` (guard rails, sparse sign poles, fast lanes; `dmlo.simulator.highway`; drive it
    along a highway trajectory such as KITTI 01's) or `"stop-and-go"` (a street in a traffic jam: the
    queue around the ego stops and goes with it while the oncoming lane flows; without a `trajectory` the
    ego crawls and stands, `generate_stop_and_go`). `laser_gain_spread`: each laser's reflectance scaled by a
    gain of its own, drawn uniformly from 1 ± the spread (0: all equal, as earlier versions): a real sensor's
    lasers differ in their intensity calibration, so the road's rings differ in brightness, and those
    stripes move with the sensor, not with the road (with 0.6 on a highway the rings lock as on real scans).
    `escorts`: six cars keep pace with the ego — a lead car and a follower in its lane, two in each lane
    beside it — as in a traffic jam (labelled moving; `dmlo.simulator.scene.EscortCar`).
    `reflectance`: `"simple"` (the sensor's own measurement model, `dmlo.simulator.sensor`: what earlier
    versions wrote, byte for byte) or `"kitti"` (that value passed through a real KITTI HDL-64E's per-laser
    gains and offsets, fade with range and at grazing incidence and 0.01 steps, calibrated on the shared real
    scans' statistics: `dmlo.simulator.reflectance`; the HDL-64E only), or a `ReflectanceModel` of one's own.
    Only the reflectance differs: the points, labels and the random stream are the same with any of them.

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
    layout_name = model.default_layout if layout is None else layout
    if layout_name not in LAYOUTS:
        raise ValueError(f"layout: unknown {layout_name!r}; known: {', '.join(LAYOUTS)}")
    if traffic not in TRAFFIC:
        raise ValueError(f"traffic: unknown {traffic!r}; known: {', '.join(TRAFFIC)}")
    if scene not in SCENES:
        raise ValueError(f"scene: unknown {scene!r}; known: {', '.join(SCENES)}")
    if not 0.0 <= laser_gain_spread < 1.0:
        raise ValueError(f"laser_gain_spread: must be in [0, 1), got {laser_gain_spread}")
    reflectance_model = _reflectance_model(reflectance, model)
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
        lidar_poses = generate_stop_and_go(frames, seed) if scene == "stop-and-go" else generate_drive(frames, seed)

    out = Path(out_dir)
    writer = make_layout(layout_name, model, tr)
    old_scans = sorted(
        {path for name in LAYOUTS for path in make_layout(name, model, tr).existing_scans(out)}
    )
    if old_scans and not overwrite and not (out / "simulation.json").is_file():
        raise ValueError(
            f"out: {out} already holds scans not written by the simulator ({len(old_scans)} files); "
            "pass overwrite=True (--overwrite) to replace them"
        )
    for old in old_scans:
        old.unlink()
    if old_scans or (out / "simulation.json").is_file():
        for name in LAYOUTS:
            make_layout(name, model, tr).remove_leftovers(out)
    writer.prepare(out)
    result = SimulationResult(out_dir=out, lidar_poses=lidar_poses)

    began = time.perf_counter()
    street = generate_street(lidar_poses, seed, model.mount_height, traffic=traffic, scene=scene, escorts=escorts)
    static_scene, static_attributes = street.static.build()
    result.scene_seconds = time.perf_counter() - began
    result.static_primitives = len(static_scene)

    elevations = model.elevations()
    directions = dmlo_rs.lidar_scan_directions(elevations, model.azimuth_count)
    times = np.arange(frames) / FRAME_RATE_HZ

    # Their own stream, so that the rest of a seed's drive is the same with any spread.
    laser_gains = np.random.default_rng([seed, 0x6A15]).uniform(
        1.0 - laser_gain_spread, 1.0 + laser_gain_spread, model.beams
    ) if laser_gain_spread > 0 else None
    indices = range(frames)
    if progress:
        from tqdm import tqdm  # type: ignore[import-untyped]

        indices = tqdm(indices, desc="simulate", unit="scan")
    for k in indices:
        frame_began, frame_cpu_began = time.perf_counter(), time.process_time()
        sweep_poses = (
            sweep_column_poses(lidar_poses, k, model.azimuth_count) if motion_distortion else lidar_poses[k]
        )
        points, labels, lasers, cast_seconds = render_frame(
            street,
            static_scene,
            static_attributes,
            model,
            directions,
            sweep_poses,
            float(times[k]),
            np.random.default_rng([seed, 0x5CA7, k]),
            laser_gains,
            reflectance_model,
        )
        writer.write_frame(out, k, points, labels, lasers)
        result.points_per_frame.append(len(points))
        result.cast_seconds.append(cast_seconds)
        result.frame_seconds.append(time.perf_counter() - frame_began)
        result.frame_cpu_seconds.append(time.process_time() - frame_cpu_began)

    writer.finish(out, lidar_poses, times)
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
        "layout": layout_name,
        "traffic": traffic,
        "scene": scene,
        "laser_gain_spread": laser_gain_spread,
        "escorts": bool(street.escort_cars),  # a stop-and-go scene brings its own
        "moving_cars": len(street.moving_cars) + len(street.path_cars) + len(street.escort_cars),
        "motion_distortion": motion_distortion,
    }
    if reflectance_model is not None:  # earlier files, without the key, stay byte for byte the same
        meta["reflectance"] = reflectance if isinstance(reflectance, str) else "custom"
    (out / "simulation.json").write_text(json.dumps(meta, indent=2) + "\n")
    return result


def _reflectance_model(reflectance: str | ReflectanceModel, sensor: LidarModel) -> ReflectanceModel | None:
    """The model `simulate_sequence(reflectance=...)` names (None: the sensor's own), checked against the sensor."""
    if isinstance(reflectance, str):
        if reflectance not in REFLECTANCE_MODELS:
            raise ValueError(f"reflectance: unknown {reflectance!r}; known: {', '.join(REFLECTANCE_MODELS)}")
        if reflectance == "simple":
            return None
        if sensor.name != "hdl64e":
            raise ValueError(f"reflectance: {reflectance!r} is calibrated for the HDL-64E, not {sensor.name!r}")
        return kitti_hdl64e()
    if reflectance.lasers != sensor.beams:
        raise ValueError(f"reflectance: a model of {reflectance.lasers} lasers for a sensor of {sensor.beams}")
    return reflectance


def render_frame(
    street: StreetScene,
    static_scene: dmlo_rs.RayScene,
    static_attributes: SceneAttributes,
    model: LidarModel,
    directions: npt.NDArray[np.float64],
    pose: npt.NDArray[np.float64],
    time_s: float,
    rng: np.random.Generator,
    laser_gains: npt.NDArray[np.float64] | None = None,
    reflectance_model: ReflectanceModel | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint32], npt.NDArray[np.uint16], float]:
    """One scan at `pose` ((4,4), or (W,4,4) per azimuth column; the rig's pose for a multi-unit sensor) and
    `time_s`: static scene plus the moving cars at that time, every unit of the sensor in turn. Returns
    points (in the pose frame), labels, each point's laser number within its unit (the beam row) and the
    seconds spent ray casting."""
    elevations = model.elevations()
    began = time.perf_counter()
    dynamic = street.dynamic(time_s, pose[..., :2, 3].reshape(-1, 2).mean(0))
    dynamic_scene = None
    attributes = static_attributes
    if len(dynamic):
        dynamic_scene, dynamic_attributes = dynamic.build()
        attributes = SceneAttributes.concatenate([static_attributes, dynamic_attributes])
    cast_seconds = time.perf_counter() - began
    parts = []
    for mount in model.unit_mounts():
        unit_pose = pose if mount is None else pose @ mount
        began = time.perf_counter()
        ranges, primitive, cosines = static_scene.cast_scan(
            unit_pose, elevations, model.azimuth_count, model.max_range
        )
        if dynamic_scene is not None:
            d_ranges, d_primitive, d_cosines = dynamic_scene.cast_scan(
                unit_pose, elevations, model.azimuth_count, model.max_range
            )
            closer = d_ranges < ranges
            ranges = np.where(closer, d_ranges, ranges)
            primitive = np.where(closer, d_primitive + len(static_scene), primitive)
            cosines = np.where(closer, d_cosines, cosines)
        cast_seconds += time.perf_counter() - began
        xyz, reflectance, labels, rays = measure_rays(
            model, directions, ranges, primitive, cosines, attributes, rng, unit_pose
        )
        beams = rays // model.azimuth_count
        if laser_gains is not None:
            reflectance = np.clip(reflectance * laser_gains[beams], 0.0, 1.0)
        if reflectance_model is not None:  # a real sensor's reflectance, from the same returns
            reflectance = reflectance_model.apply(
                reflectance, np.linalg.norm(xyz, axis=1), np.asarray(cosines).reshape(-1)[rays], beams
            )
        if mount is not None:
            xyz = xyz @ mount[:3, :3].T + mount[:3, 3]
        parts.append((xyz, reflectance, labels, beams.astype(np.uint16)))
    points = np.empty((sum(len(p[0]) for p in parts), 4), dtype=np.float32)
    points[:, :3] = np.concatenate([p[0] for p in parts])
    points[:, 3] = np.concatenate([p[1] for p in parts])
    labels = np.concatenate([p[2] for p in parts])
    lasers = np.concatenate([p[3] for p in parts])
    return points, labels, lasers, cast_seconds
