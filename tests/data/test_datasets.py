"""Dataset readers: real extracts in shared/data, and generated (also broken) files in tmp_path."""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dmlo import datasets as D
from dmlo import poses as P

AV2_LOG = "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"


def random_points(count: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    points = rng.normal(scale=20.0, size=(count, 4)).astype(np.float32)
    points[:, 3] = rng.uniform(0, 1, count)
    return points


def check_frame(frame: D.Frame) -> None:
    assert frame.points.dtype == np.float32 and frame.points.ndim == 2 and frame.points.shape[1] == 4
    assert np.all(np.isfinite(frame.points))
    assert frame.points[:, 3].min() >= 0.0 and frame.points[:, 3].max() <= 1.0
    if frame.pose is not None:
        assert frame.pose.shape == (4, 4) and frame.pose.dtype == np.float64
        np.testing.assert_allclose(frame.pose[:3, :3] @ frame.pose[:3, :3].T, np.eye(3), atol=1e-5)
    if frame.labels is not None:
        assert frame.labels.dtype == np.uint32 and len(frame.labels) == len(frame.points)


# ---------------------------------------------------------------------------------------------------
# Real data


def test_kitti_raw_static_folder(shared_data: Path) -> None:
    sequence = D.open_sequence(shared_data / "kitti_raw_static")
    assert isinstance(sequence, D.FolderSequence) and isinstance(sequence, D.ScanSequence)
    assert len(sequence) == 11 and sequence.poses is None
    sizes = []
    for frame in sequence:
        check_frame(frame)
        sizes.append(len(frame.points))
        # Independent reading: the raw file is float32 x y z r records.
        raw = np.fromfile(frame.path, dtype=np.float32).reshape(-1, 4)
        np.testing.assert_array_equal(frame.points, raw)
    assert all(110_000 < size < 125_000 for size in sizes)
    assert abs(np.mean(sizes) - 117_700) < 500
    stamps = sequence.timestamps
    assert stamps is not None and np.all(np.diff(stamps) > 0.09) and np.all(np.diff(stamps) < 0.11)
    # 2011-09-26 14:30:15.002263428 UTC, with the sub-millisecond part kept.
    assert sequence[0].timestamp == pytest.approx(1317047415.002263428, abs=1e-6)
    assert sequence[-1].path.name == "0000000010.bin"


def test_semantickitti_pair_labels_and_moving_mask(shared_data: Path) -> None:
    folder = shared_data / "semantickitti_08_pair"
    sequence = D.open_sequence(folder)
    assert len(sequence) == 2
    for frame in sequence:
        check_frame(frame)
        assert frame.labels is not None
        moving = D.moving_mask(frame.labels)
        semantic = frame.labels & 0xFFFF
        np.testing.assert_array_equal(moving, np.isin(semantic, np.arange(252, 260)))
        # A parked-car scene: some moving points, but few.
        assert 0 < moving.sum() < 0.01 * len(moving)
        # Most points carry a known class (road 40, building 50, vegetation 70, car 10…).
        assert np.mean(semantic == 0) < 0.2
        assert {40, 50, 70}.issubset(set(np.unique(semantic)))
    # The pair's poses are camera-frame KITTI poses: 3.6 m apart with a −148° yaw (camera y is "down").
    poses = P.read_kitti_poses(folder / "poses_cam0_frames_720_1500.txt")
    relative = np.linalg.inv(poses[0]) @ poses[1]
    assert np.linalg.norm(relative[:3, 3]) == pytest.approx(3.6, abs=0.1)
    angle = np.degrees(Rotation.from_matrix(relative[:3, :3]).magnitude())
    assert angle == pytest.approx(148, abs=2)


def test_argoverse1_layout(shared_data: Path) -> None:
    log = shared_data / "argoverse1_layout" / "tracking" / "1"
    assert D.detect_format(log) == "argoverse"
    sequence = D.open_sequence(log)
    assert isinstance(sequence, D.Argoverse1Sequence) and len(sequence) == 3
    for index, frame in enumerate(sequence):
        check_frame(frame)
        assert len(frame.points) == 10
        assert frame.timestamp == pytest.approx(index * 1e-9)
        record = json.loads((log / "poses" / f"city_SE3_egovehicle_{index}.json").read_text())
        w, x, y, z = record["rotation"]
        expected = np.eye(4)
        expected[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
        expected[:3, 3] = record["translation"]
        np.testing.assert_allclose(frame.pose, expected, atol=1e-12)
    # Root of the layout: the loose real sweep makes it a plain folder; format= finds the log below.
    root = shared_data / "argoverse1_layout"
    assert D.detect_format(root) == "folder"
    below = D.open_sequence(root, format="argoverse")
    assert below.name == "1" and len(below) == 3
    assert len(D.open_sequence(root, format="argoverse", sequence="tracking/1")) == 3


def test_argoverse1_real_sweep(shared_data: Path) -> None:
    path = shared_data / "argoverse1_layout" / "real_sweep_PC_315971347819783000.ply"
    points = D.read_ply(path)
    assert points.shape == (91_083, 4) and points.dtype == np.float32
    # Independent parse of the known layout: float x y z, uchar intensity, ushort laser_number.
    data = path.read_bytes()
    body = data.index(b"end_header\n") + len(b"end_header\n")
    records = np.frombuffer(
        data,
        dtype=np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("i", "u1"), ("laser", "<u2")]),
        offset=body,
    )
    assert len(records) == 91_083 and records["laser"].max() == 31
    np.testing.assert_array_equal(points[:, 0], records["x"])
    np.testing.assert_array_equal(points[:, 2], records["z"])
    np.testing.assert_allclose(points[:, 3], records["i"] / 255.0, atol=1e-7)
    ranges = np.linalg.norm(points[:, :3], axis=1)
    assert 1.0 < np.median(ranges) < 50.0


def test_argoverse2_pair(shared_data: Path) -> None:
    feather = pytest.importorskip("pyarrow.feather")
    root = shared_data / "argoverse2_pair"
    assert D.detect_format(root) == "argoverse2"
    sequence = D.open_sequence(root)
    assert isinstance(sequence, D.Argoverse2Sequence) and sequence.name == AV2_LOG
    assert len(sequence) == 2
    log = root / AV2_LOG
    table = feather.read_table(log / "city_SE3_egovehicle.feather").to_pydict()
    for frame in sequence:
        check_frame(frame)
        sweep = feather.read_table(frame.path).to_pydict()
        np.testing.assert_array_equal(frame.points[:, 0], np.asarray(sweep["x"], dtype=np.float32))
        np.testing.assert_allclose(frame.points[:, 3], np.asarray(sweep["intensity"]) / 255.0, atol=1e-7)
        stamp_ns = int(frame.path.stem)
        assert frame.timestamp == pytest.approx(stamp_ns * 1e-9)
        row = table["timestamp_ns"].index(stamp_ns)
        rotation = Rotation.from_quat([table[k][row] for k in ("qx", "qy", "qz", "qw")]).as_matrix()
        np.testing.assert_allclose(frame.pose[:3, :3], rotation, atol=1e-12)
        np.testing.assert_allclose(frame.pose[:3, 3], [table[k][row] for k in ("tx_m", "ty_m", "tz_m")])
    poses = sequence.poses
    assert np.linalg.norm(poses[1, :3, 3] - poses[0, :3, 3]) == pytest.approx(0.066, abs=0.005)
    assert 80_000 < len(sequence[0].points) < 120_000


def test_argoverse2_without_pyarrow_is_a_clear_error(shared_data: Path, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    monkeypatch.setitem(sys.modules, "pyarrow.feather", None)
    with pytest.raises(D.DatasetError, match=r"pip install 'dmlo\[argoverse2\]'"):
        D.open_sequence(shared_data / "argoverse2_pair")[0]


def test_kitti_gt_poses_through_a_kitti_tree(shared_data: Path, tmp_path: Path) -> None:
    """ROOT/sequences/01/{velodyne,calib.txt} + ROOT/poses/01.txt: poses come out in the LiDAR frame."""
    gt = P.read_kitti_poses(shared_data / "kitti_gt_poses" / "01.txt")[:5]
    calib_text = (shared_data / "kitti_gt_poses" / "calib_00-02.txt").read_text()
    sequence_dir = tmp_path / "sequences" / "01"
    for index in range(5):
        D.write_bin(sequence_dir / "velodyne" / f"{index:06d}.bin", random_points(100, index))
    (sequence_dir / "calib.txt").write_text(calib_text)
    (sequence_dir / "times.txt").write_text("".join(f"{0.1 * i:e}\n" for i in range(5)))
    P.write_kitti_poses(tmp_path / "poses" / "01.txt", gt)
    sequence = D.open_sequence(tmp_path, sequence=1)
    assert isinstance(sequence, D.KittiSequence) and sequence.name == "01" and len(sequence) == 5
    tr = P.read_kitti_calib(sequence_dir / "calib.txt")["Tr"]
    np.testing.assert_allclose(sequence.poses, np.linalg.inv(tr) @ gt @ tr, atol=1e-9)
    np.testing.assert_allclose(P.lidar_to_camera(sequence.poses, tr), gt, atol=1e-9)
    np.testing.assert_allclose(sequence.timestamps, np.arange(5) * 0.1)
    np.testing.assert_array_equal(sequence[2].points, random_points(100, 2))
    assert sequence[2].labels is None and sequence[2].timestamp == pytest.approx(0.2)
    # Only one sequence: it is found without sequence=.
    assert len(D.open_sequence(tmp_path)) == 5
    # Opening the sequence folder itself still finds ROOT/poses/01.txt.
    direct = D.open_sequence(sequence_dir)
    np.testing.assert_array_equal(direct.poses, sequence.poses)


# ---------------------------------------------------------------------------------------------------
# The simulator's layout and its side files


def write_sim_sequence(directory: Path, count: int = 4, with_calib: bool = True) -> np.ndarray:
    poses_cam = np.tile(np.eye(4), (count, 1, 1))
    poses_cam[:, 2, 3] = np.arange(count) * 1.0  # camera z forward
    for index in range(count):
        points = random_points(50 + index, index)
        D.write_bin(directory / "velodyne" / f"{index:06d}.bin", points)
        labels = np.where(np.arange(len(points)) % 5 == 0, 252, 40).astype(np.uint32) | (7 << 16)
        D.write_labels(directory / "labels" / f"{index:06d}.label", labels)
    P.write_kitti_poses(directory / "poses.txt", poses_cam)
    if with_calib:
        tr = np.eye(4)
        tr[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]  # LiDAR x forward → camera z forward
        (directory / "calib.txt").write_text("Tr: " + " ".join(f"{v:.12e}" for v in tr[:3].ravel()) + "\n")
    (directory / "times.txt").write_text("".join(f"{0.1 * i}\n" for i in range(count)))
    return poses_cam


def test_simulator_layout(tmp_path: Path) -> None:
    write_sim_sequence(tmp_path)
    sequence = D.open_sequence(tmp_path)
    assert isinstance(sequence, D.KittiSequence) and len(sequence) == 4
    frame = sequence[3]
    check_frame(frame)
    # In the LiDAR frame the car drives along +x.
    np.testing.assert_allclose(frame.pose[:3, 3], [3.0, 0.0, 0.0], atol=1e-12)
    moving = D.moving_mask(frame.labels)
    assert moving.sum() == len(range(0, 53, 5))
    assert frame.path.name == "000003.bin" and frame.timestamp == pytest.approx(0.3)
    assert sequence[-1].path == frame.path
    with pytest.raises(IndexError):
        sequence[4]


def test_poses_without_calib_warn_and_are_used_as_given(tmp_path: Path) -> None:
    poses_cam = write_sim_sequence(tmp_path, with_calib=False)
    with pytest.warns(UserWarning, match="no calib.txt"):
        sequence = D.open_sequence(tmp_path)
    np.testing.assert_array_equal(sequence.poses, poses_cam)
    # An explicit calibration silences the warning and converts.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        converted = D.open_sequence(tmp_path, tr_cam_lidar=np.eye(4))
    np.testing.assert_array_equal(converted.poses, poses_cam)


def test_label_count_mismatch(tmp_path: Path) -> None:
    write_sim_sequence(tmp_path)
    D.write_labels(tmp_path / "labels" / "000001.label", np.zeros(3, dtype=np.uint32))
    sequence = D.open_sequence(tmp_path)
    with pytest.raises(D.DatasetError, match=r"000001.label: 3 labels but the scan has 51 points|3 labels for 51"):
        sequence[1]


def test_missing_label_file(tmp_path: Path) -> None:
    write_sim_sequence(tmp_path)
    (tmp_path / "labels" / "000002.label").unlink()
    with pytest.raises(D.DatasetError, match="no label file, first 000002.label"):
        D.open_sequence(tmp_path)


def test_pose_count_mismatch(tmp_path: Path) -> None:
    write_sim_sequence(tmp_path)
    P.write_kitti_poses(tmp_path / "poses.txt", np.tile(np.eye(4), (3, 1, 1)))
    with pytest.raises(D.DatasetError, match="3 poses but 4 scans"):
        D.open_sequence(tmp_path)


def test_malformed_poses_file_in_a_sequence(tmp_path: Path) -> None:
    write_sim_sequence(tmp_path)
    (tmp_path / "poses.txt").write_text("1 2 3\n")
    with pytest.raises(D.DatasetError, match=r"poses.txt:1: expected 12 numbers"):
        D.open_sequence(tmp_path)


def test_times_count_mismatch_and_bad_times(tmp_path: Path) -> None:
    write_sim_sequence(tmp_path)
    (tmp_path / "times.txt").write_text("0\n0.1\n")
    with pytest.raises(D.DatasetError, match="2 timestamps but 4 scans"):
        D.open_sequence(tmp_path)
    (tmp_path / "times.txt").write_text("0\nyesterday\n0.2\n0.3\n")
    with pytest.raises(D.DatasetError, match="times.txt:2"):
        D.open_sequence(tmp_path)
    (tmp_path / "times.txt").write_text("0\n0.1\nnan\n0.3\n")
    with pytest.raises(D.DatasetError, match="times.txt:3: timestamp 'nan' is not a finite number"):
        D.open_sequence(tmp_path)


def test_truncated_bin(tmp_path: Path) -> None:
    write_sim_sequence(tmp_path)
    path = tmp_path / "velodyne" / "000002.bin"
    path.write_bytes(path.read_bytes()[:-5])
    sequence = D.open_sequence(tmp_path)
    sequence[1]
    with pytest.raises(D.DatasetError, match=r"000002.bin: size \d+ bytes is not a multiple of 16"):
        sequence[2]


def test_bad_label_file_size(tmp_path: Path) -> None:
    path = tmp_path / "x.label"
    path.write_bytes(b"\x00" * 7)
    with pytest.raises(D.DatasetError, match="not a multiple of 4"):
        D.read_labels(path)


# ---------------------------------------------------------------------------------------------------
# open_sequence rules and errors


def test_open_sequence_errors(tmp_path: Path) -> None:
    with pytest.raises(D.DatasetError, match="no such folder"):
        D.open_sequence(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(D.DatasetError, match="cannot tell the dataset format"):
        D.open_sequence(tmp_path / "empty")
    with pytest.raises(D.DatasetError, match="unknown dataset format 'nuscenes'"):
        D.open_sequence(tmp_path / "empty", format="nuscenes")
    with pytest.raises(D.DatasetError, match="no velodyne/ folder"):
        D.open_sequence(tmp_path / "empty", format="kitti")
    with pytest.raises(D.DatasetError, match=r"no Argoverse 2 log \(sensors/lidar/\)"):
        D.open_sequence(tmp_path / "empty", format="argoverse2")
    with pytest.raises(D.DatasetError, match="no Argoverse 1 log"):
        D.open_sequence(tmp_path / "empty", format="argoverse")
    with pytest.raises(D.DatasetError, match="no .bin, .ply, .pcd scans"):
        D.open_sequence(tmp_path / "empty", format="folder")


def test_kitti_tree_with_several_sequences_needs_a_choice(tmp_path: Path) -> None:
    for key in ("00", "05"):
        write_sim_sequence(tmp_path / "sequences" / key, with_calib=True)
    with pytest.raises(D.DatasetError, match="sequences 00, 05; pick one"):
        D.open_sequence(tmp_path)
    with pytest.raises(D.DatasetError, match="no sequence '07'"):
        D.open_sequence(tmp_path, sequence=7)
    assert D.open_sequence(tmp_path, sequence="5").name == "05"


def test_argoverse1_missing_and_broken_poses(tmp_path: Path) -> None:
    log = tmp_path / "log"
    write_ply_binary(log / "lidar" / "PC_100.ply", random_points(5))
    write_ply_binary(log / "lidar" / "PC_200.ply", random_points(6))
    (log / "poses").mkdir()
    (log / "poses" / "city_SE3_egovehicle_100.json").write_text(
        json.dumps({"rotation": [1, 0, 0, 0], "translation": [0, 0, 0]})
    )
    with pytest.raises(D.DatasetError, match="missing pose for sweep PC_200.ply"):
        D.open_sequence(log)
    (log / "poses" / "city_SE3_egovehicle_200.json").write_text("{not json")
    with pytest.raises(D.DatasetError, match="not valid JSON"):
        D.open_sequence(log)
    (log / "poses" / "city_SE3_egovehicle_200.json").write_text(json.dumps({"rotation": [1, 0, 0]}))
    with pytest.raises(D.DatasetError, match="'rotation' and 'translation'"):
        D.open_sequence(log)
    (log / "poses" / "city_SE3_egovehicle_200.json").write_text(
        json.dumps({"rotation": [1, 0, 0], "translation": [0, 0, 0]})
    )
    with pytest.raises(D.DatasetError, match="rotation must be 4 numbers"):
        D.open_sequence(log)


def test_argoverse2_generated_log(tmp_path: Path) -> None:
    pa = pytest.importorskip("pyarrow")
    feather = pytest.importorskip("pyarrow.feather")
    log = tmp_path / "log"
    (log / "sensors" / "lidar").mkdir(parents=True)
    stamps = [1000, 2000]
    for stamp in stamps:
        points = random_points(20, stamp)
        table = pa.table(
            {
                "x": points[:, 0].astype(np.float16),
                "y": points[:, 1].astype(np.float16),
                "z": points[:, 2].astype(np.float16),
                "intensity": (points[:, 3] * 255).astype(np.uint8),
                "laser_number": np.zeros(20, dtype=np.uint8),
            }
        )
        feather.write_feather(table, log / "sensors" / "lidar" / f"{stamp}.feather")
    quaternions = Rotation.from_euler("z", [[10], [20]], degrees=True).as_quat()
    poses_table = {
        "timestamp_ns": np.array([500, 1000, 2000], dtype=np.int64),
        "qw": np.r_[1.0, quaternions[:, 3]],
        "qx": np.r_[0.0, quaternions[:, 0]],
        "qy": np.r_[0.0, quaternions[:, 1]],
        "qz": np.r_[0.0, quaternions[:, 2]],
        "tx_m": np.array([0.0, 1.0, 2.0]),
        "ty_m": np.zeros(3),
        "tz_m": np.zeros(3),
    }
    feather.write_feather(pa.table(poses_table), log / "city_SE3_egovehicle.feather")
    sequence = D.open_sequence(log)
    assert len(sequence) == 2
    np.testing.assert_allclose(
        sequence.poses[:, :3, :3], Rotation.from_euler("z", [[10], [20]], degrees=True).as_matrix(), atol=1e-12
    )
    np.testing.assert_allclose(sequence.poses[:, 0, 3], [1.0, 2.0])
    check_frame(sequence[1])
    # A sweep without a pose at its timestamp, and a table without the needed columns.
    poses_table["timestamp_ns"] = np.array([500, 1000, 2500], dtype=np.int64)
    feather.write_feather(pa.table(poses_table), log / "city_SE3_egovehicle.feather")
    with pytest.raises(D.DatasetError, match="no pose at sweep timestamp 2000"):
        D.open_sequence(log)
    del poses_table["qw"]
    feather.write_feather(pa.table(poses_table), log / "city_SE3_egovehicle.feather")
    with pytest.raises(D.DatasetError, match="missing column.*qw"):
        D.open_sequence(log)
    (log / "city_SE3_egovehicle.feather").write_bytes(b"ARROW1 broken")
    with pytest.raises(D.DatasetError, match="cannot read Feather file"):
        D.open_sequence(log)


# ---------------------------------------------------------------------------------------------------
# PLY and PCD files written by hand


def write_ply_binary(path: Path, points: np.ndarray, endian: str = "<", extra_element: bool = False) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    name = "binary_little_endian" if endian == "<" else "binary_big_endian"
    header = f"ply\nformat {name} 1.0\ncomment made by a test\n"
    prefix = b""
    if extra_element:
        header += "element camera 1\nproperty float fx\nproperty uchar id\n"
        prefix = np.array([(500.0, 3)], dtype=[("fx", endian + "f4"), ("id", "u1")]).tobytes()
    header += (
        f"element vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar intensity\nproperty ushort laser_number\nend_header\n"
    )
    records = np.zeros(
        len(points),
        dtype=[("x", endian + "f4"), ("y", endian + "f4"), ("z", endian + "f4"), ("i", "u1"), ("l", endian + "u2")],
    )
    records["x"], records["y"], records["z"] = points[:, 0], points[:, 1], points[:, 2]
    records["i"] = np.round(points[:, 3] * 255).astype(np.uint8)
    records["l"] = np.arange(len(points)) % 32
    path.write_bytes(header.encode() + prefix + records.tobytes())


def expected_from_uchar(points: np.ndarray) -> np.ndarray:
    expected = points.copy()
    expected[:, 3] = np.round(points[:, 3] * 255).astype(np.uint8) / np.float32(255.0)
    return expected


@pytest.mark.parametrize("endian", ["<", ">"])
@pytest.mark.parametrize("extra_element", [False, True])
def test_ply_binary(tmp_path: Path, endian: str, extra_element: bool) -> None:
    points = random_points(257)
    path = tmp_path / "scan.ply"
    write_ply_binary(path, points, endian, extra_element)
    np.testing.assert_allclose(D.read_ply(path), expected_from_uchar(points), atol=1e-6)


def test_ply_ascii_with_float_intensity_in_0_255(tmp_path: Path) -> None:
    points = random_points(40)
    lines = [
        "ply", "format ascii 1.0", f"element vertex {len(points)}", "property float x", "property float y",
        "property float z", "property float intensity", "element face 0",
        "property list uchar int vertex_indices", "end_header",
    ]  # fmt: skip
    lines += [f"{x} {y} {z} {r * 255.0}" for x, y, z, r in points.astype(np.float64)]
    path = tmp_path / "scan.ply"
    path.write_text("\n".join(lines) + "\n")
    np.testing.assert_allclose(D.read_ply(path), points, atol=1e-5)
    # Truncated: one vertex line short.
    path.write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(D.DatasetError, match="truncated: 40 vertices declared, 39 found"):
        D.read_ply(path)
    # A word that is not a number.
    path.write_text("\n".join(lines[:-1] + ["1 2 three 4"]) + "\n")
    with pytest.raises(D.DatasetError, match="not a number"):
        D.read_ply(path)


@pytest.mark.parametrize(
    ("header", "body", "message"),
    [
        ("ply\nformat binary_little_endian 1.0\nelement face 2\nproperty float a\nend_header\n", b"", "no vertex element"),
        ("ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n", b"", "no 'end_header' line"),
        ("ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n", b"\x00" * 35, "truncated: 3 vertices need 36 bytes, 35 present"),
        ("ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n", b"\x00" * 8, "no z field"),
        ("ply\nformat utf8 1.0\nelement vertex 1\nproperty float x\nend_header\n", b"", "format 'utf8'"),
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty complex x\nend_header\n", b"", "bad property"),
        ("ply\nformat ascii 1.0\nelement vertex many\nend_header\n", b"", "bad element count 'many'"),
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar int x\nend_header\n", b"", "list property"),
        ("plz\n", b"", "not a PLY file"),
        ("ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nproperty float y\nend_header\n", b"\x00" * 16, "property 'y' is declared twice"),
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float x\nproperty float y\nproperty float z\nend_header\n", b"1 2 3 4\n", "property 'x' is declared twice"),
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float X\nproperty float y\nproperty float z\nend_header\n", b"1 2 3 4\n", "field 'X' is declared twice"),
    ],
)  # fmt: skip
def test_malformed_ply(tmp_path: Path, header: str, body: bytes, message: str) -> None:
    path = tmp_path / "bad.ply"
    path.write_bytes(header.encode() + body)
    with pytest.raises(D.DatasetError, match=message) as info:
        D.read_ply(path)
    assert "bad.ply" in str(info.value)


def pcd_header(count: int, data: str, fields: str = "x y z intensity", sizes: str = "4 4 4 4",
               types: str = "F F F F", counts: str = "1 1 1 1") -> str:  # fmt: skip
    return (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {fields}\nSIZE {sizes}\nTYPE {types}\nCOUNT {counts}\n"
        f"WIDTH {count}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {count}\nDATA {data}\n"
    )


def test_pcd_binary_with_padding_and_nan(tmp_path: Path) -> None:
    points = random_points(100)
    points[7, 1] = np.nan  # an organised cloud's missing return
    records = np.zeros(
        100, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("pad", "u1", (3,)), ("intensity", "<f4"), ("ring", "<u2")]
    )
    records["x"], records["y"], records["z"] = points[:, 0], points[:, 1], points[:, 2]
    records["intensity"] = points[:, 3]
    header = pcd_header(100, "binary", "x y z _ intensity ring", "4 4 4 1 4 2", "F F F U F U", "1 1 1 3 1 1")
    path = tmp_path / "scan.pcd"
    path.write_bytes(header.encode() + records.tobytes())
    expected = np.delete(points, 7, axis=0)
    np.testing.assert_allclose(D.read_pcd(path), expected, atol=1e-7)
    path.write_bytes(header.encode() + records.tobytes()[:-3])
    with pytest.raises(D.DatasetError, match="truncated: 100 points need"):
        D.read_pcd(path)


def test_pcd_ascii(tmp_path: Path) -> None:
    points = random_points(30)
    body = "".join(f"{x:.9g} {y:.9g} {z:.9g} {int(round(r * 255))}\n" for x, y, z, r in points)
    path = tmp_path / "scan.pcd"
    path.write_text(pcd_header(30, "ascii", sizes="4 4 4 1", types="F F F U") + body)
    np.testing.assert_allclose(D.read_pcd(path), expected_from_uchar(points), atol=1e-5)
    path.write_text(pcd_header(31, "ascii") + body)
    with pytest.raises(D.DatasetError, match="truncated: 31 points declared, 30 found"):
        D.read_pcd(path)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (pcd_header(1, "binary_compressed"), "without its size words"),
        (pcd_header(1, "zip"), "unknown PCD DATA encoding 'zip'"),
        (pcd_header(1, "ascii", fields="x y z"), "different lengths"),
        (pcd_header(1, "ascii", types="F F F Q"), "unsupported TYPE Q"),
        (pcd_header(1, "ascii", fields="a b c intensity") + "1 2 3 4\n", "no x, y, z field"),
        ("VERSION 0.7\nFIELDS x y z\n", "no 'DATA' line"),
        (pcd_header(1, "binary", counts="3 1 1 1") + "\0" * 24, "field 'x' holds 3 values per point"),
        (pcd_header(1, "ascii", counts="1 1 2 1") + "1 2 3 4 5\n", "field 'z' holds 2 values per point"),
        (pcd_header(1, "binary", sizes="4 4 4 1", types="F F F F") + "\0" * 13, "unsupported TYPE F SIZE 1"),
        (pcd_header(1, "binary", counts="1 1 1 0") + "\0" * 12, "COUNT 0"),
        (pcd_header(1, "binary", counts="1 1 1 -2") + "\0" * 12, "COUNT -2"),
        (pcd_header(1, "binary", counts="1 1 1 99999999999") + "\0" * 16, "COUNT 99999999999"),
        (pcd_header(1, "ascii", fields="x y z x") + "1 2 3 4\n", "field 'x' is declared twice"),
        (pcd_header(1, "ascii").replace("DATA ascii", "DATA") + "1 2 3 4\n", "unknown PCD DATA encoding ''"),
    ],
)
def test_malformed_pcd(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.pcd"
    path.write_text(text)
    with pytest.raises(D.DatasetError, match=message) as info:
        D.read_pcd(path)
    assert "bad.pcd" in str(info.value)


def test_a_multi_valued_pcd_field_that_is_not_read_is_skipped(tmp_path: Path) -> None:
    path = tmp_path / "descriptor.pcd"
    path.write_text(pcd_header(1, "ascii", fields="x y z fpfh", sizes="4 4 4 4", counts="1 1 1 3") + "1 2 3 7 8 9\n")
    np.testing.assert_array_equal(D.read_pcd(path), [[1, 2, 3, 0]])


def test_mangled_headers_raise_dataset_errors_or_read_points(tmp_path: Path) -> None:
    # Every header line of a valid PCD and PLY file replaced in turn by plausible mistakes: each read gives
    # an N×4 float32 array or a DatasetError naming the file, never another exception.
    rng = np.random.default_rng(5)
    points = random_points(5)
    words = ["0", "-1", "1", "3", "8", "1e3", "99999999999", "x", "F", "U", "", "1 1", "4 4 4 4 4", "x y z z"]
    pcd_bodies = {"binary": points.tobytes(), "ascii": "".join(f"{x} {y} {z} {r}\n" for x, y, z, r in points).encode()}
    ply_bodies = {"binary_little_endian": points.tobytes(), "ascii": pcd_bodies["ascii"]}
    files: list[tuple[str, bytes]] = []
    for data, body in pcd_bodies.items():
        lines = pcd_header(5, data).splitlines()
        for number in range(1, len(lines)):
            key = lines[number].split()[0]
            for _ in range(12):
                value = " ".join(rng.choice(words) for _ in range(rng.integers(1, 5)))
                mangled = lines[:number] + [f"{key} {value}"] + lines[number + 1 :]
                files.append(("mangled.pcd", "\n".join(mangled).encode() + b"\n" + body))
    properties = ["float x", "float y", "float z", "float intensity", "uchar intensity", "double X", "float",
                  "list uchar int x", "char y", "half z", "float x extra"]  # fmt: skip
    for data, body in ply_bodies.items():
        for _ in range(150):
            chosen = rng.choice(properties, size=rng.integers(0, 6))
            count = rng.choice(["5", "0", "-1", "99999999999", "many"])
            header = f"ply\nformat {data} 1.0\nelement vertex {count}\n"
            header += "".join(f"property {p}\n" for p in chosen) + "end_header\n"
            files.append(("mangled.ply", header.encode() + body))
    for name, content in files:
        path = tmp_path / name
        path.write_bytes(content)
        try:
            read = D.read_scan(path)
        except D.DatasetError as error:
            assert name in str(error)
        else:
            assert read.dtype == np.float32 and read.ndim == 2 and read.shape[1] == 4, content[:200]


def lzf_literals(raw: bytes) -> bytes:
    """A valid LZF stream using literal runs only (at most 32 bytes each)."""
    out = bytearray()
    for start in range(0, len(raw), 32):
        chunk = raw[start : start + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def test_lzf_back_references() -> None:
    # "abc" as literals, then a 3-byte copy from 3 back, then an overlapping 9-byte copy from 1 back
    # (control 7 << 5 with an extra length byte 0 → 7 + 2 = 9).
    stream = bytes([2]) + b"abc" + bytes([1 << 5, 2]) + bytes([7 << 5, 0, 0])
    assert D.lzf_decompress(stream, 15) == b"abcabc" + b"c" * 9
    with pytest.raises(ValueError, match="error in compressed data"):  # a back reference before the start
        D.lzf_decompress(bytes([1 << 5, 5]), 3)
    with pytest.raises(ValueError, match="error in compressed data"):  # a literal run past the end
        D.lzf_decompress(bytes([5]) + b"ab", 6)
    with pytest.raises(ValueError, match="decompressed to 3 bytes, the header says 7"):
        D.lzf_decompress(bytes([2]) + b"abc", 7)
    with pytest.raises(ValueError, match="decompressed to 15 bytes, the header says 14"):
        D.lzf_decompress(stream, 14)
    with pytest.raises(ValueError, match="decompressed to more than 13 bytes"):
        D.lzf_decompress(stream, 13)
    assert D.lzf_decompress(b"", 0) == b""
    with pytest.raises(ValueError, match="for an empty result"):
        D.lzf_decompress(bytes([2]) + b"abc", 0)


def test_binary_compressed_pcd_without_the_io_extra_names_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # The LZF decoder is optional (the io extra): without it a compressed scan is an unreadable scan whose
    # error says what to install, and the other encodings still read.
    monkeypatch.setitem(sys.modules, "lzf", None)  # `import lzf` raises ImportError
    points = random_points(20)
    raw = b"".join(np.ascontiguousarray(points[:, i]).tobytes() for i in range(4))
    compressed = lzf_literals(raw)
    path = tmp_path / "scan.pcd"
    sizes = np.array([len(compressed), len(raw)], "<u4").tobytes()
    path.write_bytes(pcd_header(20, "binary_compressed").encode() + sizes + compressed)
    hint = r"scan.pcd: binary_compressed PCD needs the LZF decoder: pip install 'dmlo\[io\]'"
    with pytest.raises(D.DatasetError, match=hint):
        D.read_pcd(path)
    path.write_bytes(pcd_header(20, "binary").encode() + points.tobytes())
    np.testing.assert_array_equal(D.read_pcd(path), points)


def test_pcd_binary_compressed(tmp_path: Path) -> None:
    points = random_points(77)
    fields = [points[:, 0], points[:, 1], points[:, 2], (points[:, 3] * 255).round().astype(np.uint8)]
    raw = b"".join(np.ascontiguousarray(f).tobytes() for f in fields)  # one field after the other
    compressed = lzf_literals(raw)
    header = pcd_header(77, "binary_compressed", sizes="4 4 4 1", types="F F F U")
    path = tmp_path / "scan.pcd"
    path.write_bytes(header.encode() + np.array([len(compressed), len(raw)], "<u4").tobytes() + compressed)
    np.testing.assert_allclose(D.read_pcd(path), expected_from_uchar(points), atol=1e-7)
    path.write_bytes(header.encode() + np.array([len(compressed), len(raw)], "<u4").tobytes() + compressed[:-9])
    with pytest.raises(D.DatasetError, match="truncated: \\d+ compressed bytes declared"):
        D.read_pcd(path)
    path.write_bytes(header.encode() + np.array([len(compressed), len(raw) + 4], "<u4").tobytes() + compressed)
    with pytest.raises(D.DatasetError, match="corrupt LZF data"):
        D.read_pcd(path)


@pytest.mark.parametrize("text", [False, True])
@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_ply_written_by_plyfile(tmp_path: Path, text: bool, byte_order: str) -> None:
    plyfile = pytest.importorskip("plyfile")
    points = random_points(300, seed=12)
    vertex = np.zeros(
        300, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "u1"), ("ring", "u2")]
    )
    vertex["x"], vertex["y"], vertex["z"] = points[:, 0], points[:, 1], points[:, 2]
    vertex["intensity"] = np.round(points[:, 3] * 255)
    faces = np.zeros(2, dtype=[("vertex_indices", "i4", (3,))])
    ply = plyfile.PlyData(
        [plyfile.PlyElement.describe(vertex, "vertex"), plyfile.PlyElement.describe(faces, "face")],
        text=text,
        byte_order=byte_order,
    )
    ply.write(str(tmp_path / "scan.ply"))
    np.testing.assert_allclose(D.read_ply(tmp_path / "scan.ply"), expected_from_uchar(points), atol=1e-5)


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_pcd_written_by_pypcd4(tmp_path: Path, encoding: str) -> None:
    pypcd4 = pytest.importorskip("pypcd4")
    points = random_points(5000, seed=13)
    ring = (np.arange(5000) // 100).astype(np.uint16)  # long constant runs: LZF back references
    cloud = pypcd4.PointCloud.from_points(
        [points[:, 0], points[:, 1], points[:, 2], points[:, 3], ring],
        ("x", "y", "z", "intensity", "ring"),
        (np.float32, np.float32, np.float32, np.float32, np.uint16),
    )
    path = tmp_path / "scan.pcd"
    cloud.save(path, encoding=pypcd4.Encoding(encoding))
    assert f"DATA {encoding}".encode() in path.read_bytes()[:500]
    tolerance = 1e-5 if encoding == "ascii" else 0.0
    np.testing.assert_allclose(D.read_pcd(path), points, atol=tolerance)


def test_folder_of_mixed_scans_sorted_by_name(tmp_path: Path) -> None:
    first, second, third = random_points(10, 1), random_points(11, 2), random_points(12, 3)
    D.write_bin(tmp_path / "a_000.bin", first)
    write_ply_binary(tmp_path / "a_001.ply", second)
    body = "".join(f"{x:.9g} {y:.9g} {z:.9g} {r:.9g}\n" for x, y, z, r in third)
    (tmp_path / "a_002.pcd").write_text(pcd_header(12, "ascii") + body)
    (tmp_path / "notes.txt").write_text("not a scan")
    sequence = D.open_sequence(tmp_path)
    assert isinstance(sequence, D.FolderSequence)
    assert [frame.path.name for frame in sequence] == ["a_000.bin", "a_001.ply", "a_002.pcd"]
    np.testing.assert_array_equal(sequence[0].points, first)
    np.testing.assert_allclose(sequence[1].points, expected_from_uchar(second), atol=1e-6)
    np.testing.assert_allclose(sequence[2].points, third, atol=1e-5)
    assert sequence.poses is None and sequence[0].pose is None and sequence[0].timestamp is None
    with pytest.raises(D.DatasetError, match="unknown scan suffix"):
        D.read_scan(tmp_path / "notes.txt")


def test_unpadded_frame_numbers_run_in_numeric_order(tmp_path: Path) -> None:
    folder = tmp_path / "folder"
    folder.mkdir()
    for number in (10, 2, 1, 100, 9):
        D.write_bin(folder / f"{number}.bin", random_points(5 + number, number))
    sequence = D.open_sequence(folder)
    assert [frame.path.name for frame in sequence] == ["1.bin", "2.bin", "9.bin", "10.bin", "100.bin"]
    np.testing.assert_array_equal(sequence[1].points, random_points(7, 2))
    # A KITTI velodyne/ folder with unpadded names, its labels following the scans.
    kitti = tmp_path / "kitti"
    for number in (0, 1, 2, 10, 11):
        D.write_bin(kitti / "velodyne" / f"{number}.bin", random_points(20, number))
        D.write_labels(kitti / "labels" / f"{number}.label", np.full(20, number, dtype=np.uint32))
    sequence = D.open_sequence(kitti)
    assert isinstance(sequence, D.KittiSequence)
    assert [frame.path.stem for frame in sequence] == ["0", "1", "2", "10", "11"]
    assert [int(frame.labels[0]) for frame in sequence] == [0, 1, 2, 10, 11]
    # Timestamps with fractions beyond a float's digits, and names that are not all numbers.
    stamps = ["1623456789.000000002", "1623456789.000000010", "1623456790.5"]
    assert D.in_scan_order(Path(f"{s}.pcd") for s in reversed(stamps)) == [Path(f"{s}.pcd") for s in stamps]
    mixed = [Path("scan_10.bin"), Path("2.bin"), Path("scan_9.bin")]
    assert D.in_scan_order(mixed) == sorted(mixed)


def test_scans_without_plausible_points_are_refused_naming_the_file(tmp_path: Path) -> None:
    good = random_points(200, 1)
    no_returns = good.copy()
    no_returns[::2, :3] = 0.0  # a driver's no-return markers: left out, the rest is a scan
    scans = {
        "0.bin": good,
        "1.bin": good * np.float32(1e30),  # every point beyond any sensor's reach
        "2.bin": good * np.float32(1000.0),  # millimetres read as metres: mostly beyond 1 km
        "3.bin": np.zeros((0, 4), np.float32),
        "4.bin": np.full((50, 4), np.nan, np.float32),
        "5.bin": no_returns,
    }
    for name, points in scans.items():
        D.write_bin(tmp_path / name, points)
    (tmp_path / "6.bin").write_text(("The quick brown fox jumps over the lazy dog. " * 40)[:1600])
    sequence = D.open_sequence(tmp_path)
    np.testing.assert_array_equal(sequence[0].points, good)
    np.testing.assert_array_equal(sequence[5].points, no_returns)
    for index, reason in ((1, "not a plausible LiDAR scan: 0 of its 200"), (2, "not a plausible LiDAR scan"),
                          (3, "holds no point"), (4, "0 of its 50 points"), (6, "not a plausible LiDAR scan")):  # fmt: skip
        with pytest.raises(D.DatasetError, match=reason) as info:
            sequence[index]
        assert f"{index}.bin" in str(info.value)
    # The reader alone still returns what the file holds: plausibility is the sequence's judgement.
    assert D.read_scan(tmp_path / "1.bin").shape == (200, 4)


def test_moving_mask_bits_and_errors() -> None:
    labels = np.array([252, 259, 251, 260, 10, (5 << 16) | 254, 0], dtype=np.uint32)
    np.testing.assert_array_equal(D.moving_mask(labels), [True, True, False, False, False, True, False])
    with pytest.raises(ValueError, match="one-dimensional"):
        D.moving_mask(labels.reshape(7, 1))
    with pytest.raises(TypeError, match="integers"):
        D.moving_mask(labels.astype(np.float32))


def test_frame_index_errors(shared_data: Path) -> None:
    sequence = D.open_sequence(shared_data / "kitti_raw_static")
    with pytest.raises(IndexError, match="out of range for 11 frames"):
        sequence[11]
    with pytest.raises(TypeError, match="integer"):
        sequence["0"]  # type: ignore[index]
