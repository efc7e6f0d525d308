"""Real KITTI drives (`../shared/data/kitti_real`): the odometry against an independent GICP reference.

The highway ramp of KITTI 01 is the case that made DMLO report a car standing still: the road's rings look
the same from scan to scan, and their matches outvoted the few posts and signs that see the car move.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dmlo.peers.consensus import gicp_consensus
from dmlo.datasets import open_sequence
from dmlo.odometry import Odometry, OdometryConfig
from support import frame_to_frame

pytest.importorskip("small_gicp")
pytestmark = pytest.mark.slow


def _drive(shared_data: Path, name: str) -> tuple[list[np.ndarray], np.ndarray]:
    """The drive's scans and the multi-scan GICP consensus motion of each consecutive pair (`T_i_{i+1}`)."""
    folder = shared_data / "kitti_real" / name
    if not folder.is_dir():
        pytest.skip(f"{folder} not found")
    sequence = open_sequence(folder)
    scans = [sequence[i].points for i in range(len(sequence))]
    return scans, gicp_consensus(scans, sequence.poses, span=3).motions


def _pair_errors(config: OdometryConfig, scans: list[np.ndarray], reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pair: the distance the odometry moved and its translation error against the reference (m)."""
    odometry = Odometry.from_default(config)
    poses = np.stack([odometry.register(points) for points in scans])
    deltas = np.linalg.inv(poses[:-1]) @ poses[1:]
    errors = np.linalg.norm((np.linalg.inv(reference) @ deltas)[:, :3, 3], axis=1)
    return np.linalg.norm(deltas[:, :3, 3], axis=1), errors


@pytest.fixture(scope="module")
def highway(shared_data: Path) -> tuple[list[np.ndarray], np.ndarray]:
    return _drive(shared_data, "odometry_01")


def test_on_the_highway_ramp_pure_dmlo_sees_the_car_move(highway: tuple[list[np.ndarray], np.ndarray]) -> None:
    scans, reference = highway
    assert np.linalg.norm(reference[:, :3, 3], axis=1).min() > 0.9  # about a metre a frame
    moved, errors = _pair_errors(frame_to_frame(), scans, reference)
    assert moved.min() > 0.5
    assert errors.max() < 0.15, errors


def test_counted_one_vote_each_the_road_rings_report_the_car_standing_still(
    highway: tuple[list[np.ndarray], np.ndarray],
) -> None:
    """The failure the votes remove, so that the test above can fail."""
    scans, reference = highway
    config = frame_to_frame()
    config.ransac.vote_by_tilt, config.ransac.vote_voxel = False, None
    moved, _ = _pair_errors(config, scans[:4], reference[:3])
    assert moved.max() < 0.2


def test_on_the_highway_ramp_dmlo_with_mapping_is_centimetre_accurate(
    highway: tuple[list[np.ndarray], np.ndarray],
) -> None:
    scans, reference = highway
    config = frame_to_frame()
    config.mapping.enabled = True
    _, errors = _pair_errors(config, scans, reference)
    assert errors.mean() < 0.015 and errors.max() < 0.03, errors
