"""Pose files (KITTI, TUM), camera↔LiDAR conversion and relative motions, checked against evo and scipy."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dmlo import poses as P


def random_poses(count: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = Rotation.random(count, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.normal(scale=50.0, size=(count, 3))
    return poses


# ---------------------------------------------------------------------------------------------------
# Quaternions


def test_quaternion_round_trip_matches_scipy() -> None:
    rotations = Rotation.random(200, random_state=1)
    ours = P.quaternion_to_matrix(rotations.as_quat())
    np.testing.assert_allclose(ours, rotations.as_matrix(), atol=1e-12)
    quaternions = P.matrix_to_quaternion(rotations.as_matrix())
    reference = rotations.as_quat()
    reference[reference[:, 3] < 0] *= -1.0
    np.testing.assert_allclose(quaternions, reference, atol=1e-12)


def test_matrix_to_quaternion_near_180_degrees() -> None:
    rotations = Rotation.from_rotvec(np.array([[np.pi, 0, 0], [0, np.pi - 1e-9, 0], [0, 0, np.pi]]))
    back = P.quaternion_to_matrix(P.matrix_to_quaternion(rotations.as_matrix()))
    np.testing.assert_allclose(back, rotations.as_matrix(), atol=1e-9)


def test_zero_quaternion_is_refused() -> None:
    with pytest.raises(ValueError, match="non-zero"):
        P.quaternion_to_matrix([0, 0, 0, 0])


# ---------------------------------------------------------------------------------------------------
# KITTI and TUM files


def test_kitti_round_trip(tmp_path) -> None:
    poses = random_poses(50)
    path = tmp_path / "poses.txt"
    P.write_kitti_poses(path, poses)
    np.testing.assert_allclose(P.read_kitti_poses(path), poses, rtol=1e-9, atol=1e-9)
    assert P.detect_pose_format(path) == "kitti"
    assert not list(tmp_path.glob(".*.tmp")), "temporary file left behind"


def test_tum_round_trip(tmp_path) -> None:
    poses = random_poses(50, seed=3)
    stamps = 1e9 + np.arange(50) * 0.1
    path = tmp_path / "poses.tum"
    P.write_tum_poses(path, poses, stamps)
    read_stamps, read_poses = P.read_tum_poses(path)
    np.testing.assert_allclose(read_stamps, stamps, atol=1e-6)
    np.testing.assert_allclose(read_poses, poses, atol=1e-8)
    assert P.detect_pose_format(path) == "tum"
    stamps_auto, poses_auto = P.read_poses(path)
    np.testing.assert_array_equal(poses_auto, read_poses)


def test_kitti_files_agree_with_evo(tmp_path) -> None:
    file_interface = pytest.importorskip("evo.tools.file_interface")
    poses = random_poses(30, seed=5)
    ours = tmp_path / "ours.txt"
    P.write_kitti_poses(ours, poses)
    np.testing.assert_allclose(
        np.stack(file_interface.read_kitti_poses_file(str(ours)).poses_se3), poses, atol=1e-8
    )
    theirs = tmp_path / "evo.txt"
    file_interface.write_kitti_poses_file(str(theirs), file_interface.read_kitti_poses_file(str(ours)))
    np.testing.assert_allclose(P.read_kitti_poses(theirs), poses, atol=1e-8)


def test_tum_files_agree_with_evo(tmp_path) -> None:
    file_interface = pytest.importorskip("evo.tools.file_interface")
    poses = random_poses(30, seed=6)
    stamps = np.arange(30) * 0.1 + 5.0
    ours = tmp_path / "ours.tum"
    P.write_tum_poses(ours, poses, stamps)
    trajectory = file_interface.read_tum_trajectory_file(str(ours))
    np.testing.assert_allclose(trajectory.timestamps, stamps, atol=1e-9)
    np.testing.assert_allclose(np.stack(trajectory.poses_se3), poses, atol=1e-8)
    theirs = tmp_path / "evo.tum"
    file_interface.write_tum_trajectory_file(str(theirs), trajectory)
    read_stamps, read_poses = P.read_tum_poses(theirs)
    np.testing.assert_allclose(read_stamps, stamps, atol=1e-6)
    np.testing.assert_allclose(read_poses, poses, atol=1e-6)


def test_real_kitti_ground_truth_matches_evo(shared_data) -> None:
    file_interface = pytest.importorskip("evo.tools.file_interface")
    path = shared_data / "kitti_gt_poses" / "04.txt"
    ours = P.read_kitti_poses(path)
    theirs = np.stack(file_interface.read_kitti_poses_file(str(path)).poses_se3)
    assert ours.shape == (271, 4, 4)
    np.testing.assert_allclose(ours, theirs, atol=0)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("1 2 3\n", "expected 12 numbers"),
        ("1 0 0 0 0 1 0 0 0 0 1 x\n", "'x' is not a number"),
        ("1 0 0 0 0 1 0 0 0 0 1 nan\n", "NaN"),
        ("# only a comment\n\n", "no poses"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 0 0 0 0 0 1 0\n", r":2: the rotation is not orthonormal"),
        ("1 0 0 0 0 1 0 0 0 0 -1 0\n", r":1: the rotation is not orthonormal with determinant \+1 .*det = -1"),
        ("1.01 0 0 0 0 1 0 0 0 0 1 0\n", r":1: the rotation is not orthonormal"),
        ("1.0000001 0 0 0 0 1 0 0 0 0 1 0\n", None),  # printed precision is fine
    ],
)
def test_malformed_kitti_file(tmp_path, content: str, message: str | None) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(content)
    if message is None:
        assert P.read_kitti_poses(path).shape == (1, 4, 4)
        return
    with pytest.raises(P.PoseFileError, match=message) as info:
        P.read_kitti_poses(path)
    assert str(path) in str(info.value)


def test_malformed_line_names_its_number(tmp_path) -> None:
    path = tmp_path / "bad.txt"
    good = " ".join(["1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0"])
    path.write_text(f"{good}\n{good}\n{good} 7\n")
    with pytest.raises(P.PoseFileError, match=r"bad.txt:3: expected 12 numbers .* found 13"):
        P.read_kitti_poses(path)


def test_tum_zero_quaternion_and_format_detection(tmp_path) -> None:
    path = tmp_path / "bad.tum"
    path.write_text("0.0 1 2 3 0 0 0 0\n")
    with pytest.raises(P.PoseFileError, match="zero quaternion"):
        P.read_tum_poses(path)
    odd = tmp_path / "odd.txt"
    odd.write_text("1 2 3 4 5\n")
    with pytest.raises(P.PoseFileError, match="cannot tell the pose format"):
        P.read_poses(odd)


def test_missing_file() -> None:
    with pytest.raises(FileNotFoundError, match="not found"):
        P.read_kitti_poses("/nonexistent/poses.txt")


def test_writers_reject_bad_shapes(tmp_path) -> None:
    with pytest.raises(ValueError, match=r"\(N, 4, 4\)"):
        P.write_kitti_poses(tmp_path / "x.txt", np.zeros((3, 3, 4)))
    with pytest.raises(ValueError, match="NaN"):
        P.write_kitti_poses(tmp_path / "x.txt", np.full((1, 4, 4), np.nan))
    with pytest.raises(ValueError, match="timestamps"):
        P.write_tum_poses(tmp_path / "x.tum", random_poses(3), [0.0, 1.0])


# ---------------------------------------------------------------------------------------------------
# Appending writer


@pytest.mark.parametrize("fmt", ["kitti", "tum"])
def test_pose_writer_leaves_a_valid_file_after_each_pose(tmp_path, fmt) -> None:
    poses = random_poses(5, seed=9)
    path = tmp_path / f"run.{fmt}"
    writer = P.PoseWriter(path, fmt)
    for count, pose in enumerate(poses, start=1):
        writer.append(pose, timestamp=count * 0.1)
        # Read while the writer is still open, as if the run had been killed here.
        _, read_back = P.read_poses(path, fmt)
        assert len(read_back) == count
        np.testing.assert_allclose(read_back, poses[:count], atol=1e-8)
    writer.close()
    with P.PoseWriter(path, fmt, append=True) as more:
        more.append(np.eye(4))
    assert len(P.read_poses(path, fmt)[1]) == 6


def test_pose_writer_rejects_bad_input(tmp_path) -> None:
    with pytest.raises(ValueError, match="format"):
        P.PoseWriter(tmp_path / "x.txt", "csv")  # type: ignore[arg-type]
    with P.PoseWriter(tmp_path / "x.txt") as writer, pytest.raises(ValueError, match=r"\(4, 4\)"):
        writer.append(np.eye(3))


# ---------------------------------------------------------------------------------------------------
# Frames and motions


def test_calib_and_camera_lidar_round_trip(shared_data) -> None:
    calib = P.read_kitti_calib(shared_data / "kitti_gt_poses" / "calib_00-02.txt")
    tr = calib["Tr"]
    assert set(calib) >= {"P0", "P1", "P2", "P3", "Tr"}
    np.testing.assert_allclose(tr[:3, :3] @ tr[:3, :3].T, np.eye(3), atol=1e-6)
    poses_cam = P.read_kitti_poses(shared_data / "kitti_gt_poses" / "00.txt")
    poses_lidar = P.camera_to_lidar(poses_cam, tr)
    # Definition, element by element with an independent inverse.
    expected = np.einsum("ij,njk,kl->nil", np.linalg.inv(tr), poses_cam, tr)
    np.testing.assert_allclose(poses_lidar, expected, atol=1e-9)
    np.testing.assert_allclose(P.lidar_to_camera(poses_lidar, tr), poses_cam, atol=1e-9)
    # The first LiDAR pose is the identity and the car drives along LiDAR +x (forward), not camera +z.
    np.testing.assert_allclose(poses_lidar[0], np.eye(4), atol=1e-6)
    first_step = poses_lidar[10, :3, 3]
    assert first_step[0] > 5 * abs(first_step[1]) and first_step[0] > 5 * abs(first_step[2])
    # A point seen by the LiDAR lands at the same world point both ways (camera world = Tr · lidar world).
    point_lidar = np.array([5.0, -2.0, 1.0, 1.0])
    world_cam = poses_cam[100] @ tr @ point_lidar
    np.testing.assert_allclose(tr @ poses_lidar[100] @ point_lidar, world_cam, atol=1e-9)


def test_calib_without_tr_is_an_error(tmp_path) -> None:
    path = tmp_path / "calib.txt"
    path.write_text("P0: " + " ".join(["0"] * 12) + "\n")
    with pytest.raises(P.PoseFileError, match="no 'Tr:' line"):
        P.read_kitti_calib(path)
    path.write_text("Tr: 1 2 3\n")
    with pytest.raises(P.PoseFileError, match="expected 12 numbers"):
        P.read_kitti_calib(path)


def test_relative_motions_follow_the_pipeline_convention() -> None:
    poses = random_poses(20, seed=11)
    motions = P.relative_motions(poses)
    assert motions.shape == (19, 4, 4)
    for index, motion in enumerate(motions):
        # p_t = T p_{t-1}: a world point seen from frame t-1 maps to how frame t sees it.
        world = np.array([3.0, -1.0, 2.0, 1.0])
        in_previous = np.linalg.inv(poses[index]) @ world
        in_current = np.linalg.inv(poses[index + 1]) @ world
        np.testing.assert_allclose(motion @ in_previous, in_current, atol=1e-9)
        np.testing.assert_allclose(poses[index + 1], poses[index] @ np.linalg.inv(motion), atol=1e-9)
    np.testing.assert_allclose(P.accumulate_motions(motions, poses[0]), poses, atol=1e-8)


def test_accumulate_no_motions_is_the_start() -> None:
    np.testing.assert_array_equal(P.accumulate_motions(np.zeros((0, 4, 4))), np.eye(4)[None])
