"""Motion compensation of skewed sweeps (`dmlo_rs.deskew`, `dmlo_rs.sweep_times`) against scipy and against
the poses the simulator casts its skewed sweeps from."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import dmlo_rs
from dmlo.datasets import open_sequence
from dmlo.simulator import simulate_sequence
from dmlo.simulator.trajectory import sweep_column_poses


def _random_motion(rng: np.random.Generator) -> np.ndarray:
    motion = np.eye(4)
    motion[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix()
    motion[:3, 3] = rng.normal(0, 1.0, 3)
    return motion


def _scipy_deskew(points: np.ndarray, motion: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Reference: the pose at time s turns by s × the motion's rotation vector and moves by s × its translation."""
    rotvec = Rotation.from_matrix(motion[:3, :3]).as_rotvec()
    moved = Rotation.from_rotvec(times[:, None] * rotvec).apply(points[:, :3].astype(np.float64))
    return moved + times[:, None] * motion[:3, 3]


def test_sweep_times_follow_the_azimuth() -> None:
    rng = np.random.default_rng(0)
    points = rng.uniform(-50, 50, (5000, 4)).astype(np.float32)
    azimuth = np.arctan2(points[:, 1].astype(np.float64), points[:, 0])
    assert np.allclose(dmlo_rs.sweep_times(points), -azimuth / (2 * np.pi), atol=1e-12)
    # Counter-clockwise, its reference moment looking left: time grows with the azimuth from there.
    left = np.angle(np.exp(1j * (azimuth - np.pi / 2)))
    times = dmlo_rs.sweep_times(points[:, :3], clockwise=False, reference_azimuth_deg=90.0)
    assert np.allclose(times, left / (2 * np.pi), atol=1e-12)
    assert times.min() >= -0.5 and times.max() <= 0.5


def test_deskew_matches_scipy() -> None:
    rng = np.random.default_rng(1)
    points = rng.uniform(-40, 40, (20000, 4)).astype(np.float32)
    for _ in range(5):
        motion = _random_motion(rng)
        out = dmlo_rs.deskew(points, motion)
        assert out.dtype == np.float32 and out.shape == points.shape
        expected = _scipy_deskew(points, motion, dmlo_rs.sweep_times(points))
        assert np.allclose(out[:, :3], expected, rtol=0, atol=2e-5)  # float32 resolution at 40 m: 4e-6
        assert np.array_equal(out[:, 3], points[:, 3])  # reflectance untouched
        times = rng.uniform(-0.5, 0.5, len(points))
        assert np.allclose(dmlo_rs.deskew(points, motion, times)[:, :3], _scipy_deskew(points, motion, times), rtol=0, atol=2e-5)


def _turning(angle: float) -> np.ndarray:
    motion = np.eye(4)
    motion[:3, :3] = Rotation.from_rotvec([0.0, 0.0, angle]).as_matrix()
    return motion


@pytest.mark.parametrize(
    ("changes", "error", "message"),
    [
        (dict(points=np.zeros((4, 5), np.float32)), ValueError, "points: expected shape"),
        (dict(points=np.zeros((4, 4), np.int32)), TypeError, "points: expected float32 or float64"),
        (dict(motion=np.eye(3)), ValueError, r"motion: expected shape \(4, 4\)"),
        (dict(motion=np.diag([2.0, 1.0, 1.0, 1.0])), ValueError, "motion"),
        (dict(motion=_turning(2.0)), ValueError, "motion: turns 114.6° in one sweep"),
        (dict(times=np.zeros(3)), ValueError, "times: has 3 entries for 4 points"),
        (dict(times=np.array([0.0, np.nan, 0.0, 0.0])), ValueError, "times: element 1 is not finite"),
        (dict(times=np.full(4, 1.6e18)), ValueError, "times: entry 0 is 1.6e18 periods .* expected sweep times in sensor periods"),
    ],
)
def test_bad_input_is_named(changes: dict, error: type[Exception], message: str) -> None:
    arguments = dict(points=np.ones((4, 4), np.float32), motion=np.eye(4), times=None) | changes
    with pytest.raises(error, match=message):
        dmlo_rs.deskew(arguments["points"], arguments["motion"], arguments["times"])


def test_deskewing_a_simulated_sweep_puts_every_point_where_the_simulator_cast_it(tmp_path: Path, shared_data: Path) -> None:
    # The simulator casts column j of a skewed sweep from its own pose (its own numpy code,
    # `sweep_column_poses`); deskewed with the frame's true motion, every point must land where that pose
    # puts it. Along KITTI 04 (the highway, 1.35 m a frame) the raw sweep is up to ~0.7 m off.
    simulate_sequence(tmp_path, frames=2, seed=4, trajectory=shared_data / "kitti_gt_poses" / "04.txt", start=100,
                      motion_distortion=True, progress=False)
    sequence = open_sequence(tmp_path)
    poses = sequence.poses
    assert poses is not None
    points = sequence[0].points
    columns = json.loads((tmp_path / "simulation.json").read_text())["sensor"]["azimuth_count"]
    azimuth = np.arctan2(points[:, 1].astype(np.float64), points[:, 0])
    column = np.rint((np.pi - azimuth) / (2 * np.pi) * columns).astype(int)
    inside = (column > 0) & (column < columns)  # the seam's column is the first and the last one
    cast_from = sweep_column_poses(poses, 0, columns)[column[inside]]
    true_world = np.einsum("nij,nj->ni", cast_from[:, :3, :3], points[inside, :3]) + cast_from[:, :3, 3]

    deskewed = dmlo_rs.deskew(points, np.linalg.inv(poses[0]) @ poses[1])[inside, :3]
    world = deskewed @ poses[0][:3, :3].T + poses[0][:3, 3]
    assert np.abs(world - true_world).max() < 1e-3
    raw_world = points[inside, :3] @ poses[0][:3, :3].T + poses[0][:3, 3]
    assert np.linalg.norm(raw_world - true_world, axis=1).max() > 0.6
