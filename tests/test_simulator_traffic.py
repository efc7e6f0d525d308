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

MOVING_CAR = 252
FRAMES = 5


@pytest.fixture(scope="module")
def streets() -> tuple[np.ndarray, StreetScene, StreetScene]:
    poses = generate_drive(300, seed=8)
    return poses, generate_street(poses, 8, traffic="lanes"), generate_street(poses, 8, traffic="mixed")


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
        assert steps[near_main_street].max() < 0.12
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


def test_independent_motion_is_labelled_and_the_ground_truth_stays_exact(crossing_drive: Path) -> None:
    import small_gicp

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
        result = small_gicp.align(
            target.points[~moving_mask(target.labels), :3].astype(np.float64),
            source.points[~moving_mask(source.labels), :3].astype(np.float64),
            init_T_target_source=truth,
            registration_type="GICP",
            downsampling_resolution=0.25,
            max_correspondence_distance=1.0,
            num_threads=2,
            max_iterations=30,
            translation_epsilon=1e-5,
            rotation_epsilon=1e-5,
        )
        error = np.linalg.inv(truth) @ result.T_target_source
        angle = np.degrees(np.arccos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1)))
        assert np.linalg.norm(error[:3, 3]) < 0.01 and angle < 0.05, (k, error[:3, 3], angle)


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
