"""A car creeping in a stop-and-go queue (`scene="stop-and-go"`, issue 22): the map's ground rings must not
hold it in place (`mapping.ring_lock_distance`), and it must not drift while it stands."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import dmlo_rs

from dmlo.datasets import open_sequence
from dmlo.odometry import Odometry, OdometryConfig
from dmlo.simulator import simulate_sequence

FRAMES = 60  # seed 41 creeps at 10.8 cm a frame for 1.5 s, stands from frame 23 to 52, then pulls away


@pytest.fixture(scope="module")
def queue(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("stop_and_go") / "drive"
    simulate_sequence(out, frames=FRAMES, seed=41, scene="stop-and-go", traffic="mixed", progress=False)
    return out


def _pair_errors_cm(drive: Path, config: OdometryConfig) -> tuple[np.ndarray, np.ndarray, Odometry]:
    sequence = open_sequence(drive)
    frames = [sequence[k] for k in range(len(sequence))]
    odometry = Odometry.from_default(config)
    for frame in frames:
        odometry.register(frame.points)  # no labels: the moving-object network finds the queue
    truth = np.array([frame.pose for frame in frames])
    estimate = np.array(odometry.poses)
    true_steps = np.linalg.inv(truth[:-1]) @ truth[1:]
    errors = np.linalg.inv(true_steps) @ np.linalg.inv(estimate[:-1]) @ estimate[1:]
    return np.linalg.norm(errors[:, :3, 3], axis=1) * 100, np.linalg.norm(true_steps[:, :3, 3], axis=1) * 100, odometry


def test_the_maps_rings_no_longer_hold_a_creeping_car_in_place(queue: Path) -> None:
    locked_config = OdometryConfig()
    locked_config.mapping.ring_lock_distance = 0.0
    locked, steps, _ = _pair_errors_cm(queue, locked_config)
    creeping = steps > 5.0
    assert creeping[:10].all()
    # Without it, NDT against the first scan reports the creeping car standing: every error is its step.
    assert np.all(locked[creeping][:10] > 0.8 * steps[creeping][:10]), locked

    errors, steps, odometry = _pair_errors_cm(queue, OdometryConfig())
    assert errors.max() < 1.5 and errors.mean() < 0.5, errors
    upright = [d.ndt_upright_only for d in odometry.diagnostics[1:]]
    assert all(upright[:4]) and all(flag is not None for flag in upright)  # within half a metre of the first scan
    standing = steps < 1e-3
    assert standing.sum() >= 5 and errors[standing].max() < 1.0, errors[standing]


def test_a_creeping_pair_is_not_held_together_by_the_reference_scans_rings(queue: Path) -> None:
    """`register_pair`: NDT against the reference alone reports a creeping pair standing; the split near the
    reference (the upright surfaces' split) does not, and a standing pair comes out within a millimetre."""
    sequence = open_sequence(queue)

    def errors_cm(config: OdometryConfig, pairs: tuple[int, ...]) -> list[float]:
        odometry = Odometry.from_default(config)
        errors = []
        for k in pairs:
            reference, target = sequence[k], sequence[k + 1]
            truth = np.linalg.inv(target.pose) @ reference.pose
            result = odometry.register_pair(reference.points, target.points)
            assert result.map_refined
            errors.append(float(np.linalg.norm((np.linalg.inv(truth) @ result.T_tgt_ref)[:3, 3]) * 100))
        return errors

    creeping, standing = (0, 6, 12), (30, 40)  # 10.8 cm a pair; none
    locked = OdometryConfig()
    locked.mapping.ring_lock_distance = 0.0
    assert min(errors_cm(locked, creeping)) > 8.0  # reported as good as standing
    errors = errors_cm(OdometryConfig(), creeping + standing)
    assert max(errors[:3]) < 1.0 and max(errors[3:]) < 0.1, errors


def test_heading_and_level_take_their_angles_and_position_from_either_pose() -> None:
    from scipy.spatial.transform import Rotation

    horizontal, level = np.eye(4), np.eye(4)
    horizontal[:3, :3] = Rotation.from_euler("ZYX", [2.9, 0.01, -0.02]).as_matrix()
    horizontal[:3, 3] = (10.0, -4.0, 0.3)
    level[:3, :3] = Rotation.from_euler("ZYX", [2.8, -0.05, 0.04]).as_matrix()
    level[:3, 3] = (10.2, -4.1, 0.5)
    pose = dmlo_rs.heading_and_level(horizontal, level)
    np.testing.assert_allclose(Rotation.from_matrix(pose[:3, :3]).as_euler("ZYX"), [2.9, -0.05, 0.04], atol=1e-12)
    np.testing.assert_allclose(pose[:3, 3], [10.0, -4.0, 0.5])
    np.testing.assert_allclose(pose[3], [0, 0, 0, 1])
