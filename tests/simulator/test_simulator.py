"""The LiDAR simulator end to end: KITTI layout, ground-truth consistency (GICP), determinism, labels,
moving objects, trajectories and bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from dmlo.simulator import (
    HDL64E,
    KITTI_TR,
    camera_to_lidar_poses,
    generate_drive,
    hdl64e_elevations,
    read_kitti_calib_tr,
    read_kitti_poses,
    simulate_sequence,
)
from support import assert_simulation_reproducible, gicp_departure_from_truth

FRAMES = 6
MOVING_CAR = 252


def _read_scan(folder: Path, k: int) -> tuple[np.ndarray, np.ndarray]:
    points = np.fromfile(folder / "velodyne" / f"{k:06d}.bin", dtype=np.float32).reshape(-1, 4)
    labels = np.fromfile(folder / "labels" / f"{k:06d}.label", dtype=np.uint32)
    return points, labels


def _lidar_poses_from_files(folder: Path) -> np.ndarray:
    return camera_to_lidar_poses(
        read_kitti_poses(folder / "poses.txt"), read_kitti_calib_tr(folder / "calib.txt")
    )


@pytest.fixture(scope="module")
def kitti_drive(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> tuple[Path, Path]:
    """Six frames along KITTI 00 from frame 300 (a straight stretch driven at ~10 m/s)."""
    out = tmp_path_factory.mktemp("sim_kitti")
    trajectory = shared_data / "kitti_gt_poses" / "00.txt"
    simulate_sequence(out, FRAMES, seed=3, trajectory=trajectory, start=300, progress=False)
    return out, trajectory


@pytest.fixture(scope="module")
def generated_drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sim_generated")
    simulate_sequence(out, FRAMES, seed=11, progress=False)
    return out


def test_beam_table_is_hdl64e_like() -> None:
    elevations = hdl64e_elevations()
    assert elevations.shape == (64,)
    assert elevations[0] == pytest.approx(2.0) and elevations[-1] == pytest.approx(-24.8)
    gaps = -np.diff(elevations)
    assert (gaps > 0).all()
    assert gaps[:31].mean() < 0.4 < gaps[32:].mean()  # denser upper block, as on the real sensor
    assert HDL64E.azimuth_count >= 2000 and HDL64E.max_range == pytest.approx(120.0)


def test_kitti_layout(generated_drive: Path) -> None:
    out = generated_drive
    assert sorted(p.name for p in (out / "velodyne").iterdir()) == [f"{k:06d}.bin" for k in range(FRAMES)]
    assert sorted(p.name for p in (out / "labels").iterdir()) == [f"{k:06d}.label" for k in range(FRAMES)]
    camera_poses = read_kitti_poses(out / "poses.txt")
    assert camera_poses.shape == (FRAMES, 4, 4)
    np.testing.assert_allclose(camera_poses[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(read_kitti_calib_tr(out / "calib.txt"), KITTI_TR, atol=1e-12)
    calib_keys = [line.split(":")[0] for line in (out / "calib.txt").read_text().splitlines()]
    assert calib_keys == ["P0", "P1", "P2", "P3", "Tr"]
    times = np.loadtxt(out / "times.txt")
    np.testing.assert_allclose(times, np.arange(FRAMES) * 0.1)
    for k in range(FRAMES):
        points, labels = _read_scan(out, k)
        assert len(points) == len(labels)
        assert 90_000 < len(points) < 64 * 2083
        assert np.isfinite(points).all()
        ranges = np.linalg.norm(points[:, :3], axis=1)
        assert ranges.min() >= HDL64E.min_range and ranges.max() <= HDL64E.max_range
        assert 0.0 <= points[:, 3].min() and points[:, 3].max() <= 1.0 and points[:, 3].std() > 0.05


def test_scene_has_street_structure(generated_drive: Path) -> None:
    points, labels = _read_scan(generated_drive, 0)
    classes = labels & 0xFFFF
    counts = {c: int((classes == c).sum()) for c in np.unique(classes)}
    for needed in (40, 48, 50, 70, 71, 80, 10):  # road, sidewalk, building, vegetation, trunk, pole, car
        assert counts.get(needed, 0) > 50, f"class {needed} missing from a street scan: {counts}"
    # Ground below the sensor lies at the mount height; vertical structure reaches above the sensor.
    near_road = (classes == 40) & (np.abs(points[:, 0]) < 8) & (np.abs(points[:, 1]) < 3)
    assert abs(np.median(points[near_road, 2]) + HDL64E.mount_height) < 0.1
    assert (points[classes == 50, 2] > 0.0).sum() > 1000  # the top beam looks up only 2°
    ranges = np.linalg.norm(points[:, :3], axis=1)
    assert (ranges > 40).sum() > 1000  # structure at long range too
    # Only things (cars, persons) carry instance ids; every such point has one.
    instance = labels >> 16
    things = (classes == 10) | (classes == 30) | (classes == MOVING_CAR)
    assert (instance[things] > 0).all() and (instance[~things] == 0).all()


def test_reflectance_follows_materials(generated_drive: Path) -> None:
    points, labels = _read_scan(generated_drive, 0)
    classes = labels & 0xFFFF
    road, marking = points[classes == 40, 3], points[classes == 60, 3]
    assert len(marking) > 30
    assert np.median(marking) > np.median(road) + 0.2  # painted lines stand out as in real scans


def test_measurement_model_noise_and_dropouts() -> None:
    """A wall 20 m ahead seen head-on: range error σ ≈ 2 cm, ~2 % dropouts, reflectance = albedo."""
    import dmlo_rs
    from dmlo.simulator.primitives import BUILDING, PrimitiveSet, yaw_pitch_rotation
    from dmlo.simulator.sensor import measure

    prims = PrimitiveSet()
    prims.add_box([20.5, 0, 0], [0.5, 500, 500], yaw_pitch_rotation(0.0), BUILDING, 0, 0.5)
    scene, attributes = prims.build()
    elevations = np.linspace(-5, 5, 64)
    directions = dmlo_rs.lidar_scan_directions(elevations, 4000)
    ranges, primitive, cosines = scene.cast_scan(np.eye(4), elevations, 4000, 120.0)
    front = (directions[:, 0] > 0.999).reshape(ranges.shape)
    points, labels = measure(
        HDL64E,
        directions[front.ravel()],
        ranges[front],
        primitive[front],
        cosines[front],
        attributes,
        np.random.default_rng(0),
    )
    assert (labels == BUILDING).all()
    kept = len(points) / front.sum()
    assert 0.96 < kept < 0.995
    error = points[:, 0] - 20.0  # x of a point on the plane x = 20 is exact; noise moves it along the ray
    assert abs(error.mean()) < 0.002 and 0.017 < error.std() < 0.023
    assert abs(np.median(points[:, 3]) - 0.5) < 0.01


def test_labels_align_with_geometry(generated_drive: Path) -> None:
    """Points labelled pole are on thin vertical cylinders; road points lie flat below the sensor."""
    points, labels = _read_scan(generated_drive, 2)
    classes = labels & 0xFFFF
    road = points[classes == 40]
    assert np.percentile(np.abs(road[:, 2] + HDL64E.mount_height), 95) < 0.35
    building = points[classes == 50]
    assert np.percentile(building[:, 2], 90) > 0.0


def test_ground_truth_motion_is_consistent_with_scans(kitti_drive: tuple[Path, Path]) -> None:
    """GICP started at the written ground truth between consecutive scans stays within 1 cm / 0.05°."""
    out, _ = kitti_drive
    poses = _lidar_poses_from_files(out)
    for k in range(FRAMES - 1):
        source, source_labels = _read_scan(out, k)
        target, target_labels = _read_scan(out, k + 1)
        static_source = source[(source_labels & 0xFFFF) != MOVING_CAR, :3].astype(np.float64)
        static_target = target[(target_labels & 0xFFFF) != MOVING_CAR, :3].astype(np.float64)
        truth = np.linalg.inv(poses[k + 1]) @ poses[k]  # T_target_source: p_{k+1} = T p_k
        assert np.linalg.norm(truth[:3, 3]) > 0.5  # the car really moves here
        translation_error, angle_error = gicp_departure_from_truth(static_target, static_source, truth)
        assert translation_error < 0.01, (k, translation_error)
        assert angle_error < 0.05, (k, angle_error)


def test_moving_cars_move_and_parked_cars_do_not(kitti_drive: tuple[Path, Path]) -> None:
    out, _ = kitti_drive
    poses = _lidar_poses_from_files(out)

    def centroids(k: int) -> dict[tuple[int, int], tuple[np.ndarray, int]]:
        points, labels = _read_scan(out, k)
        world = points[:, :3] @ poses[k][:3, :3].T + poses[k][:3, 3]
        found = {}
        for label in np.unique(labels[(labels >> 16) > 0]):
            mask = labels == label
            found[(int(label & 0xFFFF), int(label >> 16))] = (world[mask].mean(0), int(mask.sum()))
        return found

    first, last = centroids(0), centroids(FRAMES - 1)
    both = [key for key in first if key in last and first[key][1] > 50 and last[key][1] > 50]
    moving = [np.linalg.norm(first[key][0] - last[key][0]) for key in both if key[0] == MOVING_CAR]
    parked = [np.linalg.norm(first[key][0] - last[key][0]) for key in both if key[0] == 10]
    assert moving and parked, (first.keys(), last.keys())
    # 0.5 s apart at 3–17 m/s: every moving car travels metres; parked cars' centroids shift only
    # with the changing view.
    assert min(moving) > 1.0
    assert np.median(parked) < 0.5


def test_trajectory_poses_are_the_kitti_relative_motion(kitti_drive: tuple[Path, Path]) -> None:
    out, trajectory = kitti_drive
    written = read_kitti_poses(out / "poses.txt")
    original = read_kitti_poses(trajectory)[300 : 300 + FRAMES]
    # Re-basing to frame 0 in the LiDAR frame and converting back gives inv(P_300) · P_k in the camera frame.
    # The rotations are re-orthonormalised (pose files keep ~7 digits), hence the 1e-6 tolerance.
    np.testing.assert_allclose(written, np.linalg.inv(original[0]) @ original, atol=1e-6)


def test_same_seed_gives_identical_bytes_even_with_one_thread(tmp_path: Path) -> None:
    assert_simulation_reproducible(
        tmp_path,
        same=["velodyne/000000.bin", "velodyne/000001.bin", "labels/000001.label", "poses.txt", "calib.txt"],
        differing=["velodyne/000001.bin", "poses.txt"],
    )


def test_generated_drive_is_kitti_like() -> None:
    poses = generate_drive(1200, seed=4)
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-12)
    rotations = poses[:, :3, :3]
    np.testing.assert_allclose(
        rotations @ rotations.transpose(0, 2, 1), np.tile(np.eye(3), (1200, 1, 1)), atol=1e-9
    )
    speed = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) * 10.0
    assert speed.max() <= 20.5 and speed.mean() > 3.0
    assert (speed < 0.01).any()  # it stops
    acceleration = np.diff(speed) * 10.0
    assert np.abs(acceleration).max() < 3.0
    yaw = np.unwrap(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    assert np.ptp(yaw) > np.radians(60)  # it turns
    assert np.abs(poses[:, 2, 3]).max() < 0.05 * 1200  # gentle grades
    assert not np.array_equal(generate_drive(50, seed=4)[:, :3, 3], generate_drive(50, seed=5)[:, :3, 3])


def test_bad_input_is_reported(tmp_path: Path, shared_data: Path) -> None:
    with pytest.raises(ValueError, match="frames"):
        simulate_sequence(tmp_path, 0, seed=1, progress=False)
    with pytest.raises(FileNotFoundError, match="trajectory"):
        simulate_sequence(tmp_path, 2, seed=1, trajectory=tmp_path / "missing.txt", progress=False)
    with pytest.raises(ValueError, match="exceeds"):
        simulate_sequence(
            tmp_path, 2, seed=1, trajectory=shared_data / "kitti_gt_poses" / "04.txt", start=270
        )
    bad = tmp_path / "bad.txt"
    bad.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(ValueError, match="line 2 has 11 values"):
        simulate_sequence(tmp_path, 2, seed=1, trajectory=bad, progress=False)
    bad.write_text("1 0 0 0 0 1 0 0 0 0 1 x\n")
    with pytest.raises(ValueError, match="line 1 is not numeric"):
        read_kitti_poses(bad)
    with pytest.raises(ValueError, match="start"):
        simulate_sequence(tmp_path, 2, seed=1, start=3, progress=False)
    with pytest.raises(ValueError, match="sensor: unknown preset 'hdl32'"):
        simulate_sequence(tmp_path, 2, seed=1, sensor="hdl32", progress=False)


def test_existing_output_is_refused_or_replaced_without_stale_frames(tmp_path: Path) -> None:
    simulate_sequence(tmp_path, 3, seed=1, progress=False)
    simulate_sequence(tmp_path, 2, seed=1, progress=False)  # a previous simulation is simply replaced
    assert sorted(p.name for p in (tmp_path / "velodyne").iterdir()) == ["000000.bin", "000001.bin"]
    assert sorted(p.name for p in (tmp_path / "labels").iterdir()) == ["000000.label", "000001.label"]
    (tmp_path / "simulation.json").unlink()  # now it looks like somebody's real recording
    with pytest.raises(ValueError, match="not written by the simulator"):
        simulate_sequence(tmp_path, 2, seed=1, progress=False)
    assert (tmp_path / "velodyne" / "000001.bin").is_file()
    simulate_sequence(tmp_path, 2, seed=1, progress=False, overwrite=True)
    assert len(read_kitti_poses(tmp_path / "poses.txt")) == 2


def test_command_line(tmp_path: Path) -> None:
    from dmlo.cli import main

    assert main(["simulate", "--frames", "1", "--seed", "2", "--out", str(tmp_path / "seq"), "--quiet"]) == 0
    assert (tmp_path / "seq" / "velodyne" / "000000.bin").stat().st_size > 1_000_000
    with pytest.raises(SystemExit) as refused:  # argparse refuses it, naming --frames
        main(["simulate", "--frames", "0", "--out", str(tmp_path / "x"), "--quiet"])
    assert refused.value.code == 2


def test_sweep_column_poses_interpolate_the_frame_motion() -> None:
    from dmlo.simulator.primitives import yaw_pitch_rotation
    from dmlo.simulator.trajectory import sweep_column_poses

    poses = np.tile(np.eye(4), (3, 1, 1))
    for k in range(3):
        poses[k, :3, :3] = yaw_pitch_rotation(0.1 * k)
        poses[k, :3, 3] = [2.0 * k, 0.3 * k, 0.0]
    columns = sweep_column_poses(poses, 1, 100)
    assert columns.shape == (100, 4, 4)
    np.testing.assert_allclose(columns[50], poses[1], atol=1e-12)
    yaw = np.unwrap(np.arctan2(columns[:, 1, 0], columns[:, 0, 0]))
    np.testing.assert_allclose(yaw, 0.1 + 0.1 * (np.arange(100) - 50) / 100, atol=1e-12)
    motion = np.linalg.inv(poses[1]) @ poses[2]
    np.testing.assert_allclose(
        columns[0, :3, 3], poses[1, :3, 3] - 0.5 * poses[1, :3, :3] @ motion[:3, 3], atol=1e-12
    )
    # The last frame extrapolates with the previous motion.
    np.testing.assert_allclose(sweep_column_poses(poses, 2, 100)[50], poses[2], atol=1e-12)


def test_motion_distortion_skews_the_rear_but_not_the_front(tmp_path: Path, shared_data: Path) -> None:
    from scipy.spatial import cKDTree

    trajectory = shared_data / "kitti_gt_poses" / "00.txt"
    simulate_sequence(tmp_path / "still", 2, seed=3, trajectory=trajectory, start=300, progress=False)
    simulate_sequence(
        tmp_path / "skewed",
        2,
        seed=3,
        trajectory=trajectory,
        start=300,
        progress=False,
        motion_distortion=True,
    )
    still, _ = _read_scan(tmp_path / "still", 0)
    skewed, _ = _read_scan(tmp_path / "skewed", 0)

    def sector(points: np.ndarray, center_deg: float) -> np.ndarray:
        azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
        gap = np.abs((azimuth - center_deg + 180.0) % 360.0 - 180.0)
        return points[(gap < 3.0) & (points[:, 2] > -1.0), :3]  # above the ground: vertical structure

    front = cKDTree(sector(still, 0.0)).query(sector(skewed, 0.0))[0]
    rear = cKDTree(sector(still, 180.0)).query(sector(skewed, 180.0))[0]
    assert np.median(front) < 0.05
    assert np.median(rear) > 0.15  # ~0.8 m a frame: the rear columns fire half a frame before or after


def test_facade_windows_return_from_the_room_behind() -> None:
    """A facade with a window grid: window rays drop or return `depth` behind the facade, darker."""
    import dmlo_rs
    from dmlo.simulator.primitives import BUILDING, PrimitiveSet, yaw_pitch_rotation
    from dmlo.simulator.sensor import measure

    prims = PrimitiveSet()
    # Facade plane x = 10 (box 10..30 deep), 40 m wide, from z = -2 (box bottom) to 30.
    prims.add_box(
        [20.0, 0, 14.0], [10.0, 20.0, 16.0], yaw_pitch_rotation(0.0), BUILDING, 0, 0.5, (3.0, 3.0, 2.0)
    )
    scene, attributes = prims.build()
    elevations = np.linspace(-10, 30, 200)
    directions = dmlo_rs.lidar_scan_directions(elevations, 2000)
    ranges, primitive, cosines = scene.cast_scan(np.eye(4), elevations, 2000, 120.0)
    front = (directions[:, 0] > 0.95).reshape(ranges.shape)
    points, _ = measure(
        HDL64E,
        directions[front.ravel()],
        ranges[front],
        primitive[front],
        cosines[front],
        attributes,
        np.random.default_rng(0),
        np.eye(4),
    )
    depth_behind = points[:, 0] - 10.0
    room = depth_behind > 1.0
    assert 0.01 < room.mean() < 0.3
    np.testing.assert_allclose(np.median(depth_behind[room]), 2.0, atol=0.05)
    assert np.median(points[room, 3]) < 0.5 * np.median(points[~room, 3])
    # Windows sit on the grid: none in the lowest floor band (height above the box bottom < 3 m).
    assert (points[room, 2] + 2.0 > 3.0).all()
