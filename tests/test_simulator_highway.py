"""The simulated highway (`scene="highway"`) and per-laser reflectance gains (`laser_gain_spread`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dmlo.datasets import open_sequence
from dmlo.simulator import simulate_sequence
from dmlo.simulator.primitives import BUILDING, CAR, FENCE, POLE, ROAD, TRAFFIC_SIGN

HIGHWAY_POSES = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti_gt_poses" / "01.txt"


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
