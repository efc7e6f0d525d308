"""Each match's vote in RANSAC by the tilt of the surface under it (`dmlo_rs.horizontal_votes`,
`ransac_rigid(votes=)`, `ransac.vote_by_tilt`), and the plane-free upright test of the mapping's level alignment
(`dmlo_rs.steep_to_next_ring`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import dmlo_rs
from dmlo.odometry import Odometry, OdometryConfig
from dmlo_rs import CylinderConfig
from support import REPO, frame_to_frame


def _plane_scan(normal: np.ndarray, offset: float, config: CylinderConfig) -> np.ndarray:
    """Points of the plane `n·p = offset` where every cell's ray meets it within 60 m (N×4)."""
    rows, cols = np.meshgrid(np.arange(config.height, dtype=float), np.arange(config.width, dtype=float), indexing="ij")
    rays = dmlo_rs.unproject(rows.ravel(), cols.ravel(), np.ones(rows.size), config)
    along = rays @ normal
    with np.errstate(divide="ignore"):
        distance = offset / along
    hit = np.isfinite(distance) & (distance > 0.5) & (distance < 60)
    points = rays[hit] * distance[hit, None]
    return np.hstack([points, np.zeros((len(points), 1))]).astype(np.float32)


def _votes(scan: np.ndarray, config: CylinderConfig, floor: float = 0.0) -> np.ndarray:
    """The vote of every occupied cell, with its point image as the odometry builds it."""
    projection = dmlo_rs.project(scan, config)
    points = np.where((projection.index >= 0)[..., None], scan[np.maximum(projection.index, 0), :3], np.nan)
    rows, cols = np.nonzero(projection.index >= 0)
    return dmlo_rs.horizontal_votes(points.astype(np.float32), rows, cols, config, floor=floor)


@pytest.mark.parametrize(
    ("normal", "offset", "vote"),
    [
        ((0.0, 0.0, 1.0), -1.73, 0.0),  # the road
        ((0.6, 0.8, 0.0), 12.0, 1.0),  # a wall
        ((np.sin(np.radians(20)), 0.0, np.cos(np.radians(20))), -2.0, np.sin(np.radians(20))),  # a ramp
    ],
)
def test_a_plane_votes_the_sine_of_its_tilt(normal: tuple[float, float, float], offset: float, vote: float) -> None:
    config = CylinderConfig.kitti()
    votes = _votes(_plane_scan(np.array(normal), offset, config), config)
    told = votes[votes < 1.0] if vote < 1.0 else votes  # 1: cells whose neighbourhood is one ring
    assert len(told) > 0.5 * len(votes)
    np.testing.assert_allclose(told, vote, atol=2e-3)


def test_the_floor_holds_and_bad_arguments_are_named() -> None:
    config = CylinderConfig.kitti()
    road = _plane_scan(np.array([0.0, 0.0, 1.0]), -1.73, config)
    votes = _votes(road, config, floor=0.05)
    assert votes.min() == pytest.approx(0.05)
    points = np.full((config.height, config.width, 3), np.nan, np.float32)
    one = np.array([1])
    with pytest.raises(ValueError, match="points"):
        dmlo_rs.horizontal_votes(points[1:], one, one, config)
    with pytest.raises(ValueError, match="rows and cols"):
        dmlo_rs.horizontal_votes(points, one, np.array([1, 2]), config)
    with pytest.raises(ValueError, match="rows and cols"):
        dmlo_rs.horizontal_votes(points, np.array([-1]), one, config)
    with pytest.raises(ValueError, match="cells"):
        dmlo_rs.horizontal_votes(points, np.array([config.height]), one, config)
    with pytest.raises(ValueError, match="floor"):
        dmlo_rs.horizontal_votes(points, one, one, config, floor=2.0)


def _locked_rings(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Road matches that agree on no motion (low votes), post matches on the true one, outliers."""
    rng = np.random.default_rng(seed)
    truth = np.eye(4)
    truth[:3, 3] = [-1.0, 0.05, 0.0]
    angle, distance = rng.uniform(0, 2 * np.pi, 400), rng.uniform(4, 15, 400)
    road = np.stack([distance * np.cos(angle), distance * np.sin(angle), np.full(400, -1.73)], axis=1)
    posts = rng.uniform([-30, -12, -1], [30, 12, 3], (100, 3))
    outliers = rng.uniform([-30, -12, -1], [30, 12, 3], (2, 100, 3))
    src = np.concatenate([road, posts, outliers[0]])
    dst = np.concatenate([road, posts + truth[:3, 3], outliers[1]])
    votes = np.concatenate([np.full(400, 0.05), np.ones(100), rng.uniform(0.05, 1, 100)])
    return src, dst, votes, truth


def test_votes_keep_the_road_from_outvoting_the_posts() -> None:
    src, dst, votes, truth = _locked_rings(1)
    counted = dmlo_rs.ransac_rigid(src, dst)
    assert np.linalg.norm(counted.transform[:3, 3]) < 0.05
    voted = dmlo_rs.ransac_rigid(src, dst, votes=votes)
    np.testing.assert_allclose(voted.transform, truth, atol=1e-6)
    assert voted.num_inliers == 100
    same = [dmlo_rs.ransac_rigid(src, dst, votes=votes, num_threads=t).transform for t in (1, 2)]
    np.testing.assert_array_equal(same[0], same[1])
    with pytest.raises(ValueError, match="votes"):
        dmlo_rs.ransac_rigid(src, dst, votes=votes[1:])
    with pytest.raises(ValueError, match="votes"):
        dmlo_rs.ransac_rigid(src, dst, votes=np.zeros(len(src)))


@pytest.mark.parametrize(
    ("key", "value"), [("vote_by_tilt", "false"), ("vote_by_tilt", 1), ("min_vote", 0.0), ("min_vote", 1.5), ("min_vote", None)],
)
def test_a_bad_vote_setting_is_refused_by_name(key: str, value: object) -> None:
    with pytest.raises(ValueError, match=f"^ransac.{key}: "):
        OdometryConfig.from_dict({"ransac": {key: value}})  # when loaded
    config = OdometryConfig()
    setattr(config.ransac, key, value)
    with pytest.raises(ValueError, match=f"^ransac.{key}: "):
        Odometry.from_default(config)  # and when changed after loading


def test_a_scene_of_road_alone_is_reported_degenerate_and_bridged_by_the_motion_model() -> None:
    """An empty lot: every scan the same rings wherever the car is; their matches say nothing of where it went."""
    config = CylinderConfig.kitti()
    road = _plane_scan(np.array([0.0, 0.0, 1.0]), -1.73, config)
    road[:, 3] = np.random.default_rng(0).uniform(0.1, 0.6, len(road))  # asphalt's texture
    odometry = Odometry.from_default(frame_to_frame())
    for _ in range(3):
        odometry.register(road)
    matched = odometry.diagnostics[1:]
    assert all(d.num_inliers >= 10 and d.inlier_votes is not None and d.inlier_votes < 5 for d in matched)
    assert all(d.fallback == "degenerate_scene" for d in matched)
    assert odometry.diagnostics[1].to_dict()["inlier_votes"] == pytest.approx(matched[0].inlier_votes, abs=0.01)
    trusting = frame_to_frame()
    trusting.motion_model.min_inlier_votes = 0.0
    odometry = Odometry.from_default(trusting)
    for _ in range(2):
        odometry.register(road)
    assert odometry.diagnostics[1].fallback is None


def test_cars_keeping_pace_with_the_ego_do_not_outvote_the_static_scene(tmp_path: Path) -> None:
    """A traffic jam (`simulate_sequence(escorts=True)`): six cars ride along a few metres around the ego, each
    filling much of the image; counted by the matches they hold they pull the motion towards standing still."""
    from dmlo.datasets import open_sequence
    from dmlo.simulator import simulate_sequence

    trajectory = REPO.parent / "shared" / "data" / "kitti_gt_poses" / "07.txt"
    if not trajectory.is_file():  # the generated drive's jam is another scene, measured on neither setting
        pytest.skip(f"KITTI 07's poses not found at {trajectory}")
    simulate_sequence(tmp_path, frames=15, seed=41, trajectory=trajectory, escorts=True, progress=False)
    sequence = open_sequence(tmp_path)
    truth = np.linalg.inv(sequence.poses[:-1]) @ sequence.poses[1:]

    def errors(voxel: float | None) -> np.ndarray:
        config = frame_to_frame()
        config.ransac.vote_voxel = voxel
        config.moving_objects.detect = False  # the votes alone: with the network the escorts are gone
        odometry = Odometry.from_default(config)
        poses = np.stack([odometry.register(sequence[i].points) for i in range(len(sequence))])
        deltas = np.linalg.inv(poses[:-1]) @ poses[1:]
        return np.linalg.norm((np.linalg.inv(truth) @ deltas)[:, :3, 3], axis=1)

    spread, crowded = errors(2.0), errors(None)
    assert spread.mean() < 0.7 * crowded.mean(), (spread.mean(), crowded.mean())


@pytest.mark.parametrize("value", [0.0, -1.0, "2"])
def test_a_bad_vote_voxel_is_refused_by_name(value: object) -> None:
    with pytest.raises(ValueError, match="^ransac.vote_voxel: "):
        OdometryConfig.from_dict({"ransac": {"vote_voxel": value}})  # when loaded
    config = OdometryConfig()
    config.ransac.vote_voxel = value  # type: ignore[assignment]
    with pytest.raises(ValueError, match="^ransac.vote_voxel: "):
        Odometry.from_default(config)  # and when changed after loading


# SemanticKITTI classes: building, fence, pole, trunk, traffic sign; road, parking, sidewalk, other ground, terrain.
_UPRIGHT_CLASSES = (50, 51, 80, 71, 81)
_GROUND_CLASSES = (40, 44, 48, 49, 72)


@pytest.mark.parametrize("name", ["odometry_01", "odometry_02", "odometry_03"])
def test_the_next_ring_tells_the_far_walls_from_the_far_ground_on_real_scans(shared_data: Path, name: str) -> None:
    """`dmlo_rs.steep_to_next_ring` on labelled real scans beyond 15 m, where the mapping's level alignment
    (`mapping.level_without_far_upright`) leaves the upright surfaces out: most walls, poles and signs are
    upright, nearly no road or terrain is."""
    from dmlo.datasets import open_sequence

    config = CylinderConfig.kitti()
    sequence = open_sequence(shared_data / "kitti_real" / name)
    upright: list[np.ndarray] = []
    ground: list[np.ndarray] = []
    for i in range(0, len(sequence), 3):
        frame = sequence[i]
        assert frame.labels is not None
        projection = dmlo_rs.project(frame.points, config)
        rows, cols = np.nonzero(projection.index >= 0)
        index = projection.index[rows, cols]
        points = np.full((config.height, config.width, 3), np.nan, np.float32)
        points[rows, cols] = frame.points[index, :3]
        far = np.linalg.norm(points[rows, cols], axis=1) > 15.0
        steep = dmlo_rs.steep_to_next_ring(points, rows[far], cols[far], config)
        labels = np.asarray(frame.labels)[index[far]] & 0xFFFF
        upright.append(steep[np.isin(labels, _UPRIGHT_CLASSES)])
        ground.append(steep[np.isin(labels, _GROUND_CLASSES)])
    upright_share, ground_share = np.concatenate(upright), np.concatenate(ground)
    assert len(upright_share) > 1000 and len(ground_share) > 1000
    assert upright_share.mean() > 0.75, upright_share.mean()
    assert ground_share.mean() < 0.06, ground_share.mean()


def test_bad_arguments_of_the_ring_test_are_named() -> None:
    config = CylinderConfig.kitti()
    points = np.full((config.height, config.width, 3), np.nan, np.float32)
    one = np.array([1])
    with pytest.raises(ValueError, match="points"):
        dmlo_rs.steep_to_next_ring(points[1:], one, one, config)
    with pytest.raises(ValueError, match="rows and cols"):
        dmlo_rs.steep_to_next_ring(points, one, np.array([1, 2]), config)
    with pytest.raises(ValueError, match="cells"):
        dmlo_rs.steep_to_next_ring(points, np.array([config.height]), one, config)
    with pytest.raises(ValueError, match="min_sine"):
        dmlo_rs.steep_to_next_ring(points, one, one, config, min_sine=1.5)
    assert dmlo_rs.steep_to_next_ring(points, one, one, config).tolist() == [True]  # an empty cell
