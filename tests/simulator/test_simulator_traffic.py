"""Mixed traffic: cross streets cleared of static objects, cars crossing and turning on their own paths,
labelled moving per object, never overlapping the ego; the ego's ground truth stays exact, and the default
("lanes") traffic of a seed is untouched."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from dmlo.datasets import moving_mask, open_sequence
from dmlo.simulator import generate_drive, generate_street, simulate_sequence
from dmlo.simulator.scene import StreetScene
from dmlo.simulator.traffic import CrossStreet
from support import gicp_departure_from_truth

MOVING_CAR = 252
FRAMES = 5


@pytest.fixture(scope="module")
def streets() -> tuple[np.ndarray, StreetScene, StreetScene]:
    poses = generate_drive(300, seed=2)
    return poses, generate_street(poses, 2, traffic="lanes"), generate_street(poses, 2, traffic="mixed")


@pytest.fixture(scope="module")
def crossing_drive(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """KITTI 00 from frame 300 with seed 4: the ego starts 7 m past a cross street."""
    out = tmp_path_factory.mktemp("sim_traffic")
    trajectory = shared_data / "kitti_gt_poses" / "00.txt"
    simulate_sequence(out, FRAMES, seed=4, trajectory=trajectory, start=300, traffic="mixed", progress=False)
    return out


def test_mixed_traffic_leaves_the_lane_traffic_of_a_seed_alone(
    streets: tuple[np.ndarray, StreetScene, StreetScene],
) -> None:
    _, lanes, mixed = streets
    assert lanes.traffic is None and lanes.path_cars == []
    assert mixed.moving_cars == lanes.moving_cars
    assert mixed.traffic is not None and len(mixed.traffic.cross_streets) >= 2
    # Clearing the cross streets only removes objects; the road surfaces are the only additions.
    for kind in ("boxes", "cylinders", "ellipsoids"):
        assert len(mixed.static.parameters(kind)) < len(lanes.static.parameters(kind)), kind
    assert len(mixed.static.parameters("triangles")) > len(lanes.static.parameters("triangles"))


def _in_strip(points_xy: np.ndarray, street: CrossStreet, margin: float) -> np.ndarray:
    d = np.asarray(street.direction)
    along = (points_xy - street.center) @ d
    across = (points_xy - street.center) @ np.array([-d[1], d[0]])
    inside = np.abs(across) < street.half_width + margin
    return inside & (along > -street.reach[0]) & (along < street.reach[1])


def test_cross_streets_are_clear_of_static_objects(
    streets: tuple[np.ndarray, StreetScene, StreetScene],
) -> None:
    _, lanes, mixed = streets
    assert mixed.traffic is not None
    for street in mixed.traffic.cross_streets:
        assert street.half_width >= 3.5 and min(street.reach) > 20.0
        before = 0
        for kind, xy in (("boxes", slice(0, 2)), ("cylinders", slice(0, 2)), ("ellipsoids", slice(0, 2))):
            # Centres only: a stricter footprint test is in the clearing itself.
            assert not _in_strip(mixed.static.parameters(kind)[:, xy], street, 0.0).any(), kind
            before += int(_in_strip(lanes.static.parameters(kind)[:, xy], street, 0.0).sum())
        assert before > 0  # there was something to clear


def test_cars_cross_and_turn_on_their_own_paths(streets: tuple[np.ndarray, StreetScene, StreetScene]) -> None:
    _, _, mixed = streets
    assert mixed.traffic is not None
    cars = mixed.path_cars
    assert len(cars) >= 4 and len({car.instance for car in cars}) == len(cars)
    lane_ids = {car.instance for car in mixed.moving_cars}
    assert not lane_ids & {car.instance for car in cars}
    crossing = turning = 0
    for car in cars:
        path = mixed.traffic.paths[car.path]
        assert path.length > 20.0 and 4.0 <= car.speed <= 13.0
        turn = abs(path.heading[-1] - path.heading[0])
        # Relative to the street axis where the car's path is closest to it: across or along.
        middle = path.xy[len(path.xy) // 2]
        _, nearest = mixed.path.distance(middle)
        relative = np.degrees(
            abs(
                ((path.heading[len(path.xy) // 2] - mixed.path.heading[nearest]) + np.pi / 2) % np.pi
                - np.pi / 2
            )
        )
        crossing += int(turn < np.radians(5) and relative > 60)
        turning += int(np.radians(60) < turn < np.radians(120))
        # Cars follow the ground without kerb steps where they cross into the main street; further out
        # the terrain's hills reach grades of up to ~35 %.
        steps = np.abs(np.diff(path.ground_z))
        near_main_street = (
            mixed.path.distance(path.xy[1:])[0] < max(mixed.layout.outer(1), mixed.layout.outer(-1)) + 10
        )
        assert steps[near_main_street].max() < 0.15  # kerb plus gutter would be 0.2–0.3 m
        assert steps.max() < 0.4
    assert crossing >= 2 and turning >= 1, (crossing, turning)


def test_path_cars_never_overlap_or_vanish_near_the_ego(
    streets: tuple[np.ndarray, StreetScene, StreetScene],
) -> None:
    poses, _, mixed = streets
    assert mixed.traffic is not None
    seen_near = 0
    for k in range(0, len(poses), 3):
        ego_xy = poses[k, :2, 3]
        expected = set()
        for car in mixed.path_cars:
            path = mixed.traffic.paths[car.path]
            s = car.s0 + car.speed * k / 10.0
            if 0.0 <= s <= path.length and np.linalg.norm(path.at(s)[0] - ego_xy) <= 150.0:
                expected.add(car.instance)
                gap = np.linalg.norm(path.at(s)[0] - ego_xy)
                assert gap > car.length / 2 + 4.0 - 1e-6, (k, car.instance, gap)
                seen_near += int(gap < 30.0)
        _, attributes = mixed.dynamic(k / 10.0, ego_xy).build()
        shown = set(attributes.instance[attributes.semantic == MOVING_CAR].tolist())
        assert expected <= shown, (k, expected - shown)
    assert seen_near > 0  # cars do come close


def test_path_cars_never_overlap_other_moving_cars(
    streets: tuple[np.ndarray, StreetScene, StreetScene],
) -> None:
    from dmlo.simulator.traffic import _collide, _path_track, lane_car_tracks

    poses, _, mixed = streets
    assert mixed.traffic is not None
    times = np.arange(len(poses)) / 10.0
    lane_tracks = lane_car_tracks(mixed.path, mixed.moving_cars, times)
    path_tracks = [
        _path_track(mixed.traffic.paths[car.path], car.s0 + car.speed * times, car.length, car.width)
        for car in mixed.path_cars
    ]
    for i, track in enumerate(path_tracks):
        assert track.present.any()
        for other in lane_tracks + path_tracks[:i]:
            assert not _collide(track, other, margin=0.0)
    # Some lane cars do overlap each other (same lane, different speeds: the "lanes" traffic as it was),
    # so the test above can fail.
    collisions = sum(_collide(a, b, 0.0) for i, a in enumerate(lane_tracks) for b in lane_tracks[:i])
    assert collisions > 0


def test_footprint_overlap_is_a_box_test() -> None:
    from dmlo.simulator.traffic import _collide, _Track

    def car(x: float, y: float, heading_deg: float) -> _Track:
        return _Track(
            np.array([[x, y]]), np.radians([heading_deg]), np.array([True]), length=4.5, width=1.8
        )

    a = car(0.0, 0.0, 0.0)
    assert _collide(a, car(0.0, 1.7, 0.0), 0.0) and not _collide(a, car(0.0, 1.9, 0.0), 0.0)
    assert _collide(a, car(3.1, 0.0, 90.0), 0.0) and not _collide(a, car(3.2, 0.0, 90.0), 0.0)
    # Corner to corner at 45°, where a test of centre distances would be wrong either way: the answer
    # agrees with a dense sampling of B's box against A's.
    grid = np.stack(np.meshgrid(np.linspace(-1, 1, 81), np.linspace(-1, 1, 81)), -1).reshape(-1, 2)
    rotation = np.array([[np.cos(np.pi / 4), -np.sin(np.pi / 4)], [np.sin(np.pi / 4), np.cos(np.pi / 4)]])
    outcomes = []
    for x, y in ((3.8, 1.6), (2.0, 3.2), (3.6, 2.2)):  # centres 3.8–4.2 m apart, all under 4.5 m
        b_points = (grid * [2.25, 0.9]) @ rotation.T + [x, y]
        sampled = bool(((np.abs(b_points[:, 0]) <= 2.25) & (np.abs(b_points[:, 1]) <= 0.9)).any())
        assert _collide(a, car(x, y, 45.0), 0.0) == sampled, (x, y)
        outcomes.append(sampled)
    assert True in outcomes and False in outcomes
    assert _collide(a, a, 0.0)
    assert not _collide(a, _Track(a.xy, a.heading, np.array([False]), 4.5, 1.8), 0.0)


def test_independent_motion_is_labelled_and_the_ground_truth_stays_exact(crossing_drive: Path) -> None:
    sequence = open_sequence(crossing_drive)
    poses = sequence.poses
    assert poses is not None
    ego_direction = poses[-1, :2, 3] - poses[0, :2, 3]
    ego_direction /= np.linalg.norm(ego_direction)
    classes: dict[int, set[int]] = {}
    tracks: dict[int, list[tuple[int, np.ndarray, int]]] = {}
    for k in range(FRAMES):
        frame = sequence[k]
        assert frame.labels is not None
        things = frame.labels >> 16
        for instance in np.unique(things[things > 0]):
            mask = things == instance
            classes.setdefault(int(instance), set()).update((frame.labels[mask] & 0xFFFF).tolist())
            if moving_mask(frame.labels[mask]).all():
                pose = poses[k]
                world = frame.points[mask, :3] @ pose[:3, :3].T + pose[:3, 3]
                tracks.setdefault(int(instance), []).append((k, world.mean(0), int(mask.sum())))
    # One class per object across every frame and point.
    assert all(len(found) == 1 for found in classes.values()), classes
    across = 0
    for track in tracks.values():
        (k0, c0, n0), (k1, c1, n1) = track[0], track[-1]
        if k1 - k0 < 3 or min(n0, n1) < 50:
            continue
        motion = (c1 - c0)[:2]
        speed = np.linalg.norm(motion) / ((k1 - k0) / 10.0)
        assert speed > 2.0  # every well-seen moving car moves
        cosine = abs(motion @ ego_direction) / np.linalg.norm(motion)
        across += int(cosine < np.cos(np.radians(45)))
    assert across >= 1, tracks.keys()
    # Static points (moving classes masked, as the odometry does) still align under the ground truth.
    for k in range(FRAMES - 1):
        source, target = sequence[k], sequence[k + 1]
        assert source.labels is not None and target.labels is not None
        truth = np.linalg.inv(poses[k + 1]) @ poses[k]
        translation_error, angle = gicp_departure_from_truth(
            target.points[~moving_mask(target.labels), :3].astype(np.float64),
            source.points[~moving_mask(source.labels), :3].astype(np.float64),
            truth,
        )
        assert translation_error < 0.01 and angle < 0.05, (k, translation_error, angle)


def test_traffic_option_on_the_command_line(tmp_path: Path) -> None:
    from dmlo.cli import main

    out = tmp_path / "seq"
    assert (
        main(["simulate", "--frames", "1", "--seed", "2", "--traffic", "mixed", "--out", str(out), "--quiet"])
        == 0
    )
    assert '"traffic": "mixed"' in (out / "simulation.json").read_text()
    with pytest.raises(SystemExit):
        main(["simulate", "--traffic", "chaos", "--out", str(tmp_path / "x")])
