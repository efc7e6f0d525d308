"""The stop-and-go scene (`scene="stop-and-go"`): the ego crawls and stands in a queue that stops and goes
with it (`generate_stop_and_go`), while the oncoming lane flows past."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dmlo.datasets import open_sequence
from dmlo.simulator import generate_stop_and_go, generate_street, simulate_sequence
from dmlo.simulator.primitives import MOVING_CAR

FRAME_RATE_HZ = 10.0


def _steps(poses: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)


def test_the_ego_crawls_stops_stands_and_pulls_away() -> None:
    for seed in range(8):
        poses = generate_stop_and_go(200, seed)
        np.testing.assert_allclose(poses[0], np.eye(4))
        np.testing.assert_allclose(poses[:, :3, :3].transpose(0, 2, 1) @ poses[:, :3, :3], np.broadcast_to(np.eye(3), (200, 3, 3)), atol=1e-9)
        speed = _steps(poses) * FRAME_RATE_HZ
        assert speed.max() <= 3.0 + 1e-9  # a crawl, never a cruise
        assert np.abs(np.diff(speed)).max() * FRAME_RATE_HZ <= 1.2 + 1e-6  # queue-like braking and pulling away
        standing = speed == 0.0
        assert standing[:60].any(), seed  # a short drive stands too
        # Stops of whole seconds, and moving again after each but perhaps the last.
        edges = np.flatnonzero(np.diff(standing.astype(int)))
        assert len(edges) >= 3, seed
        runs = np.diff(edges)[standing[edges[:-1] + 1]]
        assert runs.min() >= 19, (seed, runs)
        heading = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
        assert np.abs(heading).max() < np.radians(30)  # a gently curving street
    np.testing.assert_array_equal(generate_stop_and_go(50, 3), generate_stop_and_go(50, 3))
    with pytest.raises(ValueError, match="frames"):
        generate_stop_and_go(0, 1)


def test_the_queue_fills_the_egos_lane_and_the_right_one_while_the_oncoming_lane_flows() -> None:
    poses = generate_stop_and_go(100, 4)
    for seed in range(5):
        street = generate_street(poses, seed, scene="stop-and-go")
        laterals = [car.lateral for car in street.escort_cars]
        assert len(laterals) == 4 and all(lateral < 1.0 for lateral in laterals)  # lead, follower, two on the right
        assert any(abs(lateral) < 1.0 for lateral in laterals) and any(lateral < -2.0 for lateral in laterals)
        # Only the oncoming lane on the left flows: no lane car drives through the queue on the right.
        assert street.moving_cars and all(car.lateral > 0 and car.direction < 0 for car in street.moving_cars)
        assert 7.0 <= street.layout.road_left <= 9.0


def test_traffic_passes_while_the_ego_and_its_queue_stand(tmp_path: Path) -> None:
    frames = 40
    poses = generate_stop_and_go(frames, 41)
    standing = np.flatnonzero(_steps(poses) == 0.0)
    first, last = int(standing[0]), int(standing[0]) + 8
    assert np.all(_steps(poses)[first:last] == 0.0)
    result = simulate_sequence(tmp_path, frames=last + 1, seed=41, scene="stop-and-go", progress=False)
    assert result.lidar_poses.shape == (last + 1, 4, 4)
    sequence = open_sequence(tmp_path)
    a, b = sequence[first], sequence[last]
    assert a.labels is not None and b.labels is not None

    def cars(frame) -> dict[int, np.ndarray]:
        moving = (frame.labels & 0xFFFF) == MOVING_CAR
        instances = frame.labels >> 16
        found = {int(i): frame.points[moving & (instances == i), :3] for i in np.unique(instances[moving])}
        return {instance: points for instance, points in found.items() if len(points) >= 30}

    def in_queue(centre: np.ndarray) -> bool:  # the ego's lane and the one on its right, close by
        return abs(centre[0]) < 16.0 and -5.0 < centre[1] < 1.5

    cars_a, cars_b = cars(a), cars(b)
    queue = [i for i, points in cars_a.items() if in_queue(points.mean(0))]
    assert len(queue) >= 3  # lead, follower, and the right lane's
    for instance in queue:  # the queue stands with the ego
        assert instance in cars_b and np.linalg.norm(cars_a[instance].mean(0) - cars_b[instance].mean(0)) < 0.05
    others = [i for i in cars_a if i not in queue]
    passing = [i for i in others if i not in cars_b or np.linalg.norm(cars_a[i].mean(0) - cars_b[i].mean(0)) > 1.0]
    # The oncoming lane flows: every other car seen moved on or out of sight.
    assert others and passing == others
    simulation = (tmp_path / "simulation.json").read_text()
    assert '"scene": "stop-and-go"' in simulation and '"escorts": true' in simulation
