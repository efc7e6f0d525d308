"""The simulated highway (`scene="highway"`), per-laser reflectance gains (`laser_gain_spread`) and cars that
keep pace with the ego (`escorts`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dmlo.datasets import open_sequence
from dmlo.simulator import simulate_sequence
from dmlo.simulator.primitives import BUILDING, CAR, FENCE, POLE, ROAD, TRAFFIC_SIGN
from support import REPO

HIGHWAY_POSES = REPO.parent / "shared" / "data" / "kitti_gt_poses" / "01.txt"


def _drive(out: Path, **options: object) -> tuple[np.ndarray, np.ndarray]:
    simulate_sequence(out, frames=2, seed=5, progress=False, **options)  # type: ignore[arg-type]
    frame = open_sequence(out)[1]
    assert frame.labels is not None
    return frame.points, frame.labels & 0xFFFF


def test_a_highway_is_road_rails_and_sparse_poles_without_buildings_or_parked_cars(tmp_path: Path) -> None:
    trajectory = HIGHWAY_POSES if HIGHWAY_POSES.is_file() else None
    points, classes = _drive(tmp_path, scene="highway", trajectory=trajectory)
    assert not np.isin(classes, [BUILDING, CAR]).any()
    assert (classes == ROAD).mean() > 0.3
    rails = points[classes == FENCE]
    assert len(rails) > 500  # on both sides, all along
    assert (rails[:, 1] > 0).any() and (rails[:, 1] < 0).any()
    assert np.isin(classes, [POLE, TRAFFIC_SIGN]).sum() < 0.05 * len(classes)
    with pytest.raises(ValueError, match="scene"):
        simulate_sequence(tmp_path / "x", frames=1, seed=5, scene="motorway", progress=False)
    with pytest.raises(ValueError, match="traffic"):
        simulate_sequence(tmp_path / "y", frames=1, seed=5, scene="highway", traffic="mixed", progress=False)


def test_laser_gains_scale_each_lasers_reflectance_and_leave_the_rest_of_the_drive_alone(tmp_path: Path) -> None:
    plain, plain_classes = _drive(tmp_path / "plain")
    gained, gained_classes = _drive(tmp_path / "gained", laser_gain_spread=0.5)
    np.testing.assert_array_equal(plain[:, :3], gained[:, :3])
    np.testing.assert_array_equal(plain_classes, gained_classes)
    ratio = gained[:, 3] / np.maximum(plain[:, 3], 1e-6)
    unclipped = (plain[:, 3] > 0.05) & (gained[:, 3] < 1.0)
    assert ratio[unclipped].min() > 0.5 - 1e-4 and ratio[unclipped].max() < 1.5 + 1e-4
    assert ratio[unclipped].std() > 0.1  # the lasers differ
    with pytest.raises(ValueError, match="laser_gain_spread"):
        simulate_sequence(tmp_path / "bad", frames=1, seed=5, laser_gain_spread=1.0, progress=False)


def test_escorts_keep_pace_with_the_ego(tmp_path: Path) -> None:
    from dmlo.simulator.primitives import MOVING_CAR

    simulate_sequence(tmp_path, frames=3, seed=5, escorts=True, progress=False)
    sequence = open_sequence(tmp_path)
    ahead = []
    for k in (0, 2):
        frame = sequence[k]
        assert frame.labels is not None
        cars = frame.points[(frame.labels & 0xFFFF) == MOVING_CAR, :3]
        lead = cars[(cars[:, 0] > 3) & (cars[:, 0] < 15) & (np.abs(cars[:, 1]) < 1.5)]
        assert len(lead) > 50
        ahead.append(lead[:, 0].min())
    moved = np.linalg.norm((np.linalg.inv(sequence.poses[0]) @ sequence.poses[2])[:3, 3])
    assert moved > 0.1 and abs(ahead[1] - ahead[0]) < 0.1  # the ego moved; its lead car stayed as far ahead


def test_a_narrow_street_has_its_kerbs_close_and_no_lanes_beside_the_egos(tmp_path: Path) -> None:
    from dmlo.simulator import generate_street
    from dmlo.simulator.primitives import SIDEWALK

    poses = np.repeat(np.eye(4)[None], 20, axis=0)
    poses[:, 0, 3] = np.arange(20) * 0.8
    for seed in range(6):
        narrow = generate_street(poses, seed, scene="narrow", escorts=True)
        assert 3.5 <= narrow.layout.road_left <= 5.5 and 3.5 <= narrow.layout.road_right <= 5.5
        assert narrow.moving_cars == []  # no lane beside the ego's
        assert narrow.escort_cars and all(abs(car.lateral) < 1.0 for car in narrow.escort_cars)  # ahead, behind
        street = generate_street(poses, seed, escorts=True)
        assert street.layout.road_left >= 7.0 and street.moving_cars and len(street.escort_cars) == 6
    points, classes = _drive(tmp_path, scene="narrow")
    sidewalk = points[classes == SIDEWALK]
    assert np.abs(sidewalk[:, 1]).min() < 5.6  # a sidewalk within the narrow street's reach
