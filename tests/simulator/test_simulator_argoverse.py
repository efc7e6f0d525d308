"""The Argoverse 1 sensor preset (two stacked VLP-32C) and the Argoverse 1 output layout: beam table and
mounts against a real AV1 sweep, the round trip through `dmlo.datasets.open_sequence`, projection with
`CylinderConfig.argoverse()`, ground-truth consistency, determinism and bad input."""

from __future__ import annotations

import json
from pathlib import Path

import dmlo_rs
import numpy as np
import pytest
from dmlo.datasets import detect_format, moving_mask, open_sequence
from dmlo.simulator import (
    ARGOVERSE_VLP32C_PAIR,
    SimulationResult,
    reflectance_to_intensity,
    simulate_sequence,
    vlp32c_elevations,
)
from dmlo.simulator.sensor import HDL64E
from support import assert_simulation_reproducible, gicp_departure_from_truth

FRAMES = 4
REAL_SWEEP = "argoverse1_layout/real_sweep_PC_315971347819783000.ply"
_PLY_RECORD = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "u1"), ("laser", "<u2")])


def _read_av1_ply(path: Path) -> np.ndarray:
    """The records of an AV1 sweep (float x y z, uchar intensity, ushort laser_number), parsed here."""
    data = path.read_bytes()
    header_end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:header_end].decode("ascii").splitlines()
    assert header[3:8] == [
        "property float x",
        "property float y",
        "property float z",
        "property uchar intensity",
        "property ushort laser_number",
    ]
    count = int(header[2].split()[2])
    records = np.frombuffer(data, dtype=_PLY_RECORD, offset=header_end)
    assert len(records) == count
    return records


def _unit_elevations(records: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """(elevation in degrees, range) of every point seen from each unit of the rig, in the unit's frame."""
    xyz = np.stack([records["x"], records["y"], records["z"]], axis=1).astype(np.float64)
    views = []
    for mount in ARGOVERSE_VLP32C_PAIR.unit_mounts():
        assert mount is not None
        local = (xyz - mount[:3, 3]) @ mount[:3, :3]  # R^T (p - t)
        ranges = np.linalg.norm(local, axis=1)
        views.append((np.degrees(np.arcsin(local[:, 2] / ranges)), ranges))
    return views


def _beam_errors(records: np.ndarray) -> np.ndarray:
    """(units, 32) median elevation error of each laser number against the VLP-32C table, from the unit
    whose beam it is (points beyond 10 m within 0.6° of the beam); NaN where a beam has no such points."""
    errors = np.full((2, 32), np.nan)
    for unit, (elevation, ranges) in enumerate(_unit_elevations(records)):
        for laser, expected in enumerate(vlp32c_elevations()):
            near = (records["laser"] == laser) & (ranges > 10.0) & (np.abs(elevation - expected) < 0.6)
            if near.sum() > 20:
                errors[unit, laser] = np.median(elevation[near]) - expected
    return errors


@pytest.fixture(scope="module")
def av1_drive(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> tuple[Path, SimulationResult]:
    """Four frames along KITTI 00 from frame 300 (straight, ~10 m/s), Argoverse rig, mixed traffic."""
    out = tmp_path_factory.mktemp("sim_av1")
    result = simulate_sequence(
        out,
        FRAMES,
        seed=4,
        trajectory=shared_data / "kitti_gt_poses" / "00.txt",
        start=300,
        sensor="argoverse",
        traffic="mixed",
        progress=False,
    )
    return out, result


def test_vlp32c_table_and_mounts_match_a_real_argoverse_sweep(shared_data: Path) -> None:
    elevations = vlp32c_elevations()
    assert elevations.shape == (32,) and (np.diff(elevations) < 0).all()
    assert elevations[0] == pytest.approx(15.0) and elevations[-1] == pytest.approx(-25.0)
    gaps = -np.diff(elevations)
    assert gaps[6:23].max() < 0.34 < gaps[:3].min()  # 1/3° from +1.67° to −4°, sparse towards the ends
    # The real sweep: each laser number is seen by both units; from the unit owning it the beam sits at the
    # table's elevation (the lower unit is mounted upside down, so it looks at −table from the upper one).
    real = _read_av1_ply(shared_data / REAL_SWEEP)
    errors = _beam_errors(real)
    assert (
        np.isfinite(errors).sum() >= 60
    )  # +15° of the upper unit / −25° of the lower see little beyond 10 m
    assert np.nanmax(np.abs(errors)) < 0.3, np.round(errors, 2)
    assert ARGOVERSE_VLP32C_PAIR.units == 2 and ARGOVERSE_VLP32C_PAIR.azimuth_count == 1800


def test_round_trip_through_the_argoverse_reader(av1_drive: tuple[Path, SimulationResult]) -> None:
    out, result = av1_drive
    assert detect_format(out) == "argoverse"
    sequence = open_sequence(out)
    assert len(sequence) == FRAMES
    poses = sequence.poses
    assert poses is not None
    np.testing.assert_allclose(poses, result.lidar_poses, atol=1e-12)
    assert np.linalg.norm(poses[-1, :3, 3] - poses[0, :3, 3]) > 2.0
    np.testing.assert_allclose(sequence.timestamps, np.arange(FRAMES) * 0.1, atol=1e-12)
    calibration = json.loads((out / "vehicle_calibration_info.json").read_text())
    assert set(calibration) == {"vehicle_SE3_up_lidar_", "vehicle_SE3_down_lidar_"}
    for k in range(FRAMES):
        frame = sequence[k]
        records = _read_av1_ply(out / "lidar" / f"PC_{k * 100_000_000}.ply")
        assert len(frame.points) == len(records) == result.points_per_frame[k]
        np.testing.assert_array_equal(frame.points[:, 0], records["x"])
        np.testing.assert_array_equal(frame.points[:, 3], records["intensity"] / np.float32(255.0))
        assert frame.labels is not None and len(frame.labels) == len(frame.points)
        assert records["laser"].max() == 31
        # The sweep's own elevation pattern: every laser number at its table elevation, from its unit.
        errors = _beam_errors(records)
        assert np.nanmax(np.abs(errors)) < 0.05 and np.isfinite(errors).sum() >= 60


@pytest.fixture(scope="module")
def street_sweeps(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> list[np.ndarray]:
    """One sweep of three different streets (seeds) along KITTI 00, lane traffic only."""
    sweeps = []
    for seed in (1, 4, 9):
        out = tmp_path_factory.mktemp(f"sim_av1_street{seed}")
        trajectory = shared_data / "kitti_gt_poses" / "00.txt"
        simulate_sequence(
            out, 1, seed=seed, trajectory=trajectory, start=300, sensor="argoverse", progress=False
        )
        sweeps.append(open_sequence(out)[0].points)
    return sweeps


def test_point_count_elevations_and_projection_are_like_the_real_sweep(
    street_sweeps: list[np.ndarray], shared_data: Path
) -> None:
    real = open_sequence(shared_data / "argoverse1_layout" / "tracking", format="argoverse")  # layout check
    assert len(real) == 3
    real_points = _points_of(_read_av1_ply(shared_data / REAL_SWEEP))
    for simulated in street_sweeps:  # real: 91,083; the VLP-32C pair gives at most 115,200
        assert 0.8 < len(simulated) / len(real_points) < 1.3

    def elevation(points: np.ndarray) -> np.ndarray:  # from the ego origin, as the cylinder image sees it
        return np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))

    quantiles = [5, 25, 50, 75, 95]
    real_q = np.percentile(elevation(real_points), quantiles)
    simulated_q = np.mean([np.percentile(elevation(points), quantiles) for points in street_sweeps], axis=0)
    np.testing.assert_allclose(simulated_q, real_q, atol=1.0)
    config = dmlo_rs.CylinderConfig.argoverse()
    fills = []
    for points in [real_points, *street_sweeps]:
        projection = dmlo_rs.project(points, config)
        image = np.asarray(projection.range)
        filled = np.isfinite(image) & (image > 0)
        fills.append(filled.mean(axis=1).reshape(8, 8).mean(1))  # bands of 8 rows
        assert projection.num_out_of_view < 0.1 * len(points)  # most of it is in the −5°…+15° band
    # Band by band the image fills alike: densest just above the horizon, sparse at the top. (The band
    # just below the horizon, the far ground, is emptier in the simulated streets: 0.47 against 0.63.)
    simulated_fill = np.mean(fills[1:], axis=0)
    assert abs(simulated_fill.mean() - fills[0].mean()) < 0.05
    assert np.argmax(simulated_fill) == np.argmax(fills[0]) == 4
    np.testing.assert_allclose(simulated_fill, fills[0], atol=0.2)


def _points_of(records: np.ndarray) -> np.ndarray:
    points = np.empty((len(records), 4), dtype=np.float32)
    for axis, key in enumerate("xyz"):
        points[:, axis] = records[key]
    points[:, 3] = records["intensity"] / np.float32(255.0)
    return points


def test_ground_truth_aligns_the_static_points(av1_drive: tuple[Path, SimulationResult]) -> None:
    """GICP started at the written ground truth between consecutive ego-frame sweeps stays within 1 cm /
    0.05° on the static points (mixed traffic removed by the moving-class labels)."""
    out, _ = av1_drive
    sequence = open_sequence(out)
    poses = sequence.poses
    assert poses is not None
    for k in range(FRAMES - 1):
        source, target = sequence[k], sequence[k + 1]
        assert source.labels is not None and target.labels is not None
        static_source = source.points[~moving_mask(source.labels), :3].astype(np.float64)
        static_target = target.points[~moving_mask(target.labels), :3].astype(np.float64)
        truth = np.linalg.inv(poses[k + 1]) @ poses[k]
        translation_error, angle = gicp_departure_from_truth(static_target, static_source, truth)
        assert translation_error < 0.01, (k, translation_error)
        assert angle < 0.05, (k, angle)


def test_ground_lies_below_the_ego_origin_at_the_mount_height(
    av1_drive: tuple[Path, SimulationResult],
) -> None:
    out, _ = av1_drive
    frame = open_sequence(out)[1]
    assert frame.labels is not None
    road = ((frame.labels & 0xFFFF) == 40) & (np.hypot(frame.points[:, 0], frame.points[:, 1]) < 8.0)
    road &= np.abs(frame.points[:, 1]) < 2.0
    # A real AV1 sweep's road lies at z ≈ −0.34 m in the ego frame (origin at the rear axle).
    assert abs(np.median(frame.points[road, 2]) + ARGOVERSE_VLP32C_PAIR.mount_height) < 0.05


def test_same_seed_same_bytes_and_one_thread(tmp_path: Path) -> None:
    names = [
        "lidar/PC_100000000.ply",
        "labels/PC_100000000.label",
        "poses/city_SE3_egovehicle_100000000.json",
    ]
    assert_simulation_reproducible(
        tmp_path,
        same=[*names, "vehicle_calibration_info.json"],
        differing=names[:1],
        sensor="argoverse",
        traffic="mixed",
    )


def test_kitti_layout_of_the_argoverse_rig_and_switching_layouts(tmp_path: Path) -> None:
    out = tmp_path / "seq"
    result = simulate_sequence(out, 2, seed=2, sensor="argoverse", progress=False)
    simulate_sequence(out, 2, seed=2, sensor="argoverse", layout="kitti", progress=False)
    # The Argoverse files of the previous simulation are gone: the folder reads as KITTI only.
    assert not (out / "lidar").exists() and not (out / "poses").exists()
    assert not (out / "vehicle_calibration_info.json").exists()
    sequence = open_sequence(out)
    assert detect_format(out) == "kitti" and len(sequence) == 2
    np.testing.assert_allclose(sequence.poses, result.lidar_poses, atol=1e-9)
    # Same rig, same seed: the same points whichever layout (KITTI keeps float32 reflectance).
    simulate_sequence(tmp_path / "av1", 2, seed=2, sensor="argoverse", progress=False)
    kitti_points = sequence[1].points
    av1_points = open_sequence(tmp_path / "av1")[1].points
    np.testing.assert_array_equal(kitti_points[:, :3], av1_points[:, :3])
    np.testing.assert_array_equal(
        reflectance_to_intensity(kitti_points[:, 3]) / np.float32(255.0), av1_points[:, 3]
    )
    # And back to the Argoverse layout in the first folder: no KITTI leftovers.
    simulate_sequence(out, 1, seed=2, sensor="argoverse", progress=False)
    assert detect_format(out) == "argoverse" and not (out / "velodyne").exists()


def test_reflectance_to_intensity_is_velodyne_like() -> None:
    intensity = reflectance_to_intensity(np.array([0.0, 0.123, 0.5, 0.89, 0.9, 0.95, 1.0, 1.7, -0.2]))
    assert intensity.dtype == np.uint8
    np.testing.assert_array_equal(intensity, [0, 12, 50, 89, 101, 178, 255, 255, 0])


def test_bad_input_names_the_argument(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="layout: unknown 'nuscenes'"):
        simulate_sequence(tmp_path, 1, seed=1, layout="nuscenes", progress=False)
    with pytest.raises(ValueError, match="traffic: unknown 'chaos'"):
        simulate_sequence(tmp_path, 1, seed=1, traffic="chaos", progress=False)
    with pytest.raises(ValueError, match="sensor: unknown preset 'vlp16'"):
        simulate_sequence(tmp_path, 1, seed=1, sensor="vlp16", progress=False)
    from dmlo.cli import main

    with pytest.raises(SystemExit):
        main(["simulate", "--sensor", "vlp16", "--out", str(tmp_path / "x")])
    assert not any(tmp_path.iterdir())
    assert HDL64E.units == 1 and HDL64E.default_layout == "kitti"


def test_motion_distortion_of_the_rig_skews_the_rear_but_not_the_front(
    tmp_path: Path, shared_data: Path
) -> None:
    """Each unit fires its forward column at the frame's pose (the lower, upside-down unit looks forward
    12° to the left there), so the front of a skewed sweep stays put and the rear moves."""
    from scipy.spatial import cKDTree

    trajectory = shared_data / "kitti_gt_poses" / "00.txt"
    sweeps = []
    for distortion in (False, True):
        out = tmp_path / str(distortion)
        simulate_sequence(
            out,
            2,
            seed=3,
            trajectory=trajectory,
            start=300,
            sensor="argoverse",
            motion_distortion=distortion,
            progress=False,
        )
        sweeps.append(open_sequence(out)[0].points)

    def sector(points: np.ndarray, center_deg: float) -> np.ndarray:
        azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0] - 1.35))  # around the units' axis
        gap = np.abs((azimuth - center_deg + 180.0) % 360.0 - 180.0)
        return points[(gap < 2.0) & (points[:, 2] > 0.5), :3]  # above the ground: vertical structure

    still, skewed = sweeps
    front = cKDTree(sector(still, 5.0)).query(sector(skewed, 5.0))[0]
    rear = cKDTree(sector(still, 185.0)).query(sector(skewed, 185.0))[0]
    assert np.median(front) < 0.1
    assert np.median(rear) > 0.15  # ~1 m a frame: the rear columns fire half a frame before or after
