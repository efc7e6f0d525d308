"""The learned moving-object network (issue 22, item 3): it finds the cars that keep pace with the ego in a
traffic jam without labels, the odometry leaves their points out, and it can be turned off."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest

import dmlo_rs
from dmlo.datasets import moving_mask, open_sequence
from dmlo.metrics.moving import precision_recall
from dmlo.odometry import Odometry, OdometryConfig
from dmlo.odometry.matcher import ModelError, default_model_path
from dmlo.odometry.moving import MovingObjectDetector, moving_objects_graph, range_and_height
from dmlo.simulator import simulate_sequence
from support import frame_to_frame

GRAPH = dmlo_rs.ModelFolder.MOVING_OBJECTS
BUNDLED = default_model_path() / GRAPH


@pytest.fixture(scope="module")
def jam(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A generated-route traffic jam: six cars keep pace with the ego (a seed no training drive used)."""
    out = tmp_path_factory.mktemp("jam") / "drive"
    simulate_sequence(out, frames=15, seed=41, escorts=True, progress=False)
    return out


def test_point_cells_are_the_cells_of_the_numpy_formula() -> None:
    cylinder = dmlo_rs.CylinderConfig.kitti()
    rng = np.random.default_rng(3)
    points = rng.uniform(-60, 60, size=(5000, 4)).astype(np.float32)
    points[:, 2] = rng.uniform(-4, 1, size=5000)
    points[:3] = [[np.nan, 1, 1, 0], [0, 0, 0, 0], [1, 0, 50, 0]]  # NaN, origin, straight up (out of view)
    cells = dmlo_rs.point_cells(points, cylinder)
    p = points[3:].astype(np.float64)
    elevation = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
    azimuth = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
    row = np.floor(cylinder.row_of_zero_elevation - elevation / cylinder.vertical_resolution_deg + 0.5)
    col = np.floor(cylinder.col_of_zero_azimuth - azimuth / cylinder.horizontal_resolution_deg + 0.5)
    inside = (row >= 0) & (row < cylinder.height) & (col >= 0) & (col < cylinder.width)
    expected = np.where(inside, row * cylinder.width + col, -1).astype(np.int64)
    # The crate's rule is the formula in radians; degrees differ from it only on a cell's boundary.
    assert np.mean(cells[3:] == expected) > 0.999
    assert list(cells[:3]) == [-1, -1, -1]
    projection = dmlo_rs.project(points, cylinder)
    kept = projection.index[projection.index >= 0]
    assert np.array_equal(cells[kept], np.flatnonzero(projection.index.ravel() >= 0))


def test_the_networks_images_and_rule_are_the_projection_and_a_threshold_per_cell() -> None:
    """The crate's images and rule (`odometry::moving`), which the detector, the training and the crate's
    odometry share, against numpy on the projection: each cell's kept point's range and z, and every point of
    a cell above the threshold flagged."""
    cylinder = dmlo_rs.CylinderConfig.kitti()
    rng = np.random.default_rng(4)
    points = rng.uniform(-40, 40, size=(20000, 4)).astype(np.float32)
    points[:, 2] = rng.uniform(-3, 0.5, size=20000)
    points[:2] = [[np.nan, 1, 1, 0], [0, 0, 0, 0]]
    ranges, height = range_and_height(points, cylinder)
    index = np.asarray(dmlo_rs.project(points, cylinder).index)
    kept = index >= 0
    norms = np.linalg.norm(points[np.maximum(index, 0), :3].astype(np.float64), axis=-1)
    np.testing.assert_allclose(ranges, np.where(kept, norms, 0), rtol=1e-6, atol=0)
    np.testing.assert_array_equal(height, np.where(kept, points[np.maximum(index, 0), 2], 0))
    probability = rng.uniform(0, 1, size=(cylinder.height, cylinder.width)).astype(np.float32)
    flags = dmlo_rs.flagged_points(points, probability, cylinder, 0.5)
    cells = dmlo_rs.point_cells(points, cylinder)
    np.testing.assert_array_equal(flags, (cells >= 0) & (probability.ravel()[np.maximum(cells, 0)] > 0.5))
    assert 0.3 < flags.mean() < 0.7 and not flags[:2].any()
    with pytest.raises(ValueError, match="probability"):
        dmlo_rs.flagged_points(points, probability[:10], cylinder, 0.5)
    with pytest.raises(ValueError, match="points"):
        dmlo_rs.moving_network_images(points[:, :3], cylinder)


def test_precision_and_recall_count_hits_and_leave_undefined_ratios_undefined() -> None:
    result = precision_recall([True, True, False, False], [True, False, True, False])
    assert (result["precision"], result["recall"], result["predicted"], result["moving"]) == (0.5, 0.5, 2, 2)
    assert math.isnan(precision_recall([False, False], [True, False])["precision"])
    assert math.isnan(precision_recall([True, False], [False, False])["recall"])
    with pytest.raises(ValueError, match="differ in size"):
        precision_recall([True], [True, False])


def test_the_bundled_network_finds_the_cars_of_a_jam_it_never_saw(jam: Path) -> None:
    detector = MovingObjectDetector(BUNDLED)
    sequence = open_sequence(jam)
    flagged, truth = [], []
    for index in range(0, len(sequence), 3):
        frame = sequence[index]
        flagged.append(detector.mask(frame.points))
        truth.append(moving_mask(frame.labels))
    result = precision_recall(np.concatenate(flagged), np.concatenate(truth))
    assert result["recall"] > 0.8 and result["precision"] > 0.8, result


def test_the_network_flags_little_of_a_real_street_without_moving_objects(shared_data: Path) -> None:
    """KITTI odometry 03, frames 0–9: no moving object, parked cars; the road, buildings and trees must stay."""
    sequence = open_sequence(shared_data / "kitti_real" / "odometry_03")
    detector = MovingObjectDetector(BUNDLED)
    flagged = np.concatenate([detector.mask(sequence[i].points) for i in range(0, len(sequence), 3)])
    labels = np.concatenate([sequence[i].labels & 0xFFFF for i in range(0, len(sequence), 3)])
    not_vehicle = labels != 10
    assert flagged[not_vehicle].mean() < 0.01


def pair_errors(drive: Path, config: OdometryConfig) -> tuple[np.ndarray, Odometry]:
    odometry = Odometry(default_model_path(), config)
    sequence = open_sequence(drive)
    poses = [odometry.register(sequence[i].points) for i in range(len(sequence))]
    errors = [
        np.linalg.norm((np.linalg.inv(poses[i - 1]) @ poses[i])[:3, 3]
                       - (np.linalg.inv(sequence[i - 1].pose) @ sequence[i].pose)[:3, 3])
        for i in range(1, len(poses))
    ]
    return np.array(errors), odometry


@pytest.mark.slow
@pytest.mark.parametrize("mapping", [False, True], ids=["dmlo", "dmlo+mapping"])
def test_in_a_jam_the_odometry_follows_the_road_not_the_cars_around_it(jam: Path, mapping: bool) -> None:
    config = frame_to_frame()
    config.mapping.enabled = mapping
    errors, odometry = pair_errors(jam, config)
    assert errors.mean() < 0.05 and errors.max() < 0.15, errors.round(3)
    assert all(d.num_moving_predicted for d in odometry.diagnostics)
    # Without it the escorts capture the consensus: the car seems to stand still.
    config.moving_objects.detect = False
    kept, odometry = pair_errors(jam, config)
    assert kept.mean() > 0.3, kept.round(3)
    assert all(d.num_moving_predicted is None for d in odometry.diagnostics)


def test_labels_when_given_decide_and_the_network_stays_idle(jam: Path) -> None:
    sequence = open_sequence(jam)
    odometry = Odometry(default_model_path(), frame_to_frame())
    odometry.register(sequence[0].points, moving=moving_mask(sequence[0].labels))
    odometry.register(sequence[1].points)
    assert odometry.diagnostics[0].num_moving_predicted is None
    assert odometry.diagnostics[1].num_moving_predicted and odometry.diagnostics[1].num_moving_predicted > 1000


def test_a_model_without_the_network_keeps_every_point(tmp_path: Path, jam: Path) -> None:
    model = tmp_path / "model"
    shutil.copytree(default_model_path(), model, ignore=shutil.ignore_patterns("training", "range_only", GRAPH))
    assert moving_objects_graph(model / "frame.onnx") is None
    odometry = Odometry(model, frame_to_frame())
    odometry.register(open_sequence(jam)[0].points)
    assert odometry.diagnostics[0].num_moving_predicted is None


def test_a_graph_that_is_not_a_moving_object_network_is_a_model_error(tmp_path: Path) -> None:
    graph = onnx.load(str(BUNDLED))
    for entry in graph.metadata_props:
        if entry.key == "dmlo.graph":
            entry.value = "frame"
    onnx.save(graph, str(tmp_path / GRAPH))
    with pytest.raises(ModelError, match="a dmlo \"frame\" graph, not the moving-object network"):
        MovingObjectDetector(tmp_path / GRAPH)
    (tmp_path / "broken.onnx").write_bytes(b"not onnx")
    with pytest.raises(ModelError, match="not a readable ONNX model"):
        MovingObjectDetector(tmp_path / "broken.onnx")


def test_config_and_flag_turn_the_detection_off() -> None:
    with pytest.raises(ValueError, match="moving_objects.threshold"):
        OdometryConfig.from_dict({"moving_objects": {"threshold": 1.0}})
    with pytest.raises(ValueError, match="moving_objects.detect"):
        OdometryConfig.from_dict({"moving_objects": {"detect": "false"}})
    from dmlo.cli import build_parser

    args = build_parser().parse_args(["register", "a.bin", "b.bin", "--keep-moving"])
    from dmlo.commands.run import build_odometry

    assert build_odometry(args).config.moving_objects.detect is False
    args = build_parser().parse_args(["register", "a.bin", "b.bin"])
    assert build_odometry(args).config.moving_objects.detect is True


@pytest.mark.slow
def test_training_writes_a_network_the_odometry_opens_and_resumes(tmp_path: Path, jam: Path) -> None:
    out = tmp_path / "net"
    command = [sys.executable, "-m", "dmlo.train.moving", "--data", str(jam), "--val", str(jam), "--out", str(out),
               "--stride", "4", "--batch", "2", "--crop", "256", "--threads", "1"]
    subprocess.run([*command, "--steps", "2"], check=True, capture_output=True)
    assert (out / "moving.pt").is_file() and (out / "moving.onnx").is_file()
    finished = subprocess.run([*command, "--steps", "3"], check=True, capture_output=True, text=True)
    assert "resumed at step 2" in finished.stdout
    detector = MovingObjectDetector(out / "moving.onnx")
    assert detector.mask(open_sequence(jam)[0].points).dtype == bool
    import onnx

    operators = {node.op_type for node in onnx.load(str(out / "moving.onnx")).graph.node}
    assert not operators & {"IsInf", "IsNaN"}, "tract, the crate's pure-Rust runtime, cannot run them"


@pytest.mark.slow
def test_the_recipe_simulates_its_drives_once_and_trains_on_them(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                 shared_data: Path) -> None:
    from dmlo.train import moving_recipe

    drives = (("train/a", None, 0, 5, 3, {"escorts": True}), ("train/b", "01", 40, 6, 3, {"scene": "highway"}),
              ("val/c", None, 0, 7, 2, {}))
    monkeypatch.setattr(moving_recipe, "DRIVES", drives)
    monkeypatch.setattr(moving_recipe, "TRAIN_ARGUMENTS", ["--batch", "2", "--crop", "256"])
    data, run = tmp_path / "data", tmp_path / "run"
    assert moving_recipe.main(["--data", str(data), "--out", str(run), "--steps", "2",
                               "--poses", str(shared_data / "kitti_gt_poses")]) == 0
    assert sorted(p.name for p in (data / "train").iterdir()) == ["a", "b"]
    assert json.loads((data / "train" / "a" / "simulation.json").read_text())["escorts"] is True
    written = (data / "train" / "a" / "poses.txt").stat().st_mtime_ns
    assert moving_recipe.main(["--data", str(data), "--out", str(run), "--steps", "3",
                               "--poses", str(shared_data / "kitti_gt_poses")]) == 0
    assert (data / "train" / "a" / "poses.txt").stat().st_mtime_ns == written
    assert json.loads((run / "train.json").read_text())["steps"] == 3
    # Without KITTI's poses the drives along them are left out, not replaced by generated routes.
    train, val = moving_recipe.simulate_drives(tmp_path / "other", tmp_path / "no_poses")
    assert [p.name for p in train] == ["a"] and [p.name for p in val] == ["c"]


def test_the_sensor_check_counts_the_whole_scan_not_what_is_left_after_the_moving_objects(
    jam: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Cars all around fill much of the image; left out, they leave it emptier than any sensor mismatch would."""
    import warnings

    from dmlo.odometry import SensorMismatchWarning

    class MostlyMoving:
        """A network that puts three columns in four on moving objects."""

        def __init__(self, cylinder: object) -> None:
            self.cylinder = cylinder

        def probability(self, ranges: np.ndarray, height: np.ndarray) -> np.ndarray:
            probability = np.ones_like(ranges)
            probability[:, ::4] = 0.0
            return probability

    monkeypatch.setattr(Odometry, "_open_moving_objects", lambda self: MostlyMoving(self._matcher.cylinder))
    points = open_sequence(jam)[0].points
    odometry = Odometry(default_model_path(), frame_to_frame())
    with warnings.catch_warnings():
        warnings.simplefilter("error", SensorMismatchWarning)
        odometry.register(points)
    assert odometry.diagnostics[0].num_moving_predicted > 0.6 * len(points)
    assert odometry.diagnostics[0].image_fill < 0.35


def test_non_finite_rows_change_nothing_the_network_flags(jam: Path) -> None:
    sequence = open_sequence(jam)
    rng = np.random.default_rng(2)
    dirty_run, clean_run = Odometry(default_model_path(), frame_to_frame()), Odometry(default_model_path(), frame_to_frame())
    for index in range(3):
        scan = sequence[index].points
        dirty = scan.copy()
        rows = rng.choice(len(scan), 300, replace=False)
        dirty[rows, rng.integers(0, 4, 300)] = np.nan
        np.testing.assert_array_equal(dirty_run.register(dirty), clean_run.register(np.delete(scan, rows, axis=0)))
    assert [d.num_moving_predicted for d in dirty_run.diagnostics] == [d.num_moving_predicted for d in clean_run.diagnostics]


def test_register_pair_leaves_the_moving_out_of_a_consecutive_pair_not_of_a_far_one(jam: Path) -> None:
    sequence = open_sequence(jam)
    kept = frame_to_frame()
    kept.moving_objects.detect = False
    detecting, keeping = Odometry(default_model_path(), frame_to_frame()), Odometry(default_model_path(), kept)
    a, b, far = sequence[0].points, sequence[1].points, sequence[6].points
    truth = np.linalg.inv(sequence[1].pose) @ sequence[0].pose
    consecutive = detecting.register_pair(a, b).T_tgt_ref
    assert np.linalg.norm(consecutive[:3, 3] - truth[:3, 3]) < 0.05
    assert np.linalg.norm(keeping.register_pair(a, b).T_tgt_ref[:3, 3] - truth[:3, 3]) > 0.2  # the escorts win
    np.testing.assert_array_equal(detecting.register_pair(a, far, large_motion=True).T_tgt_ref,
                                  keeping.register_pair(a, far, large_motion=True).T_tgt_ref)


@pytest.mark.slow
def test_creeping_behind_traffic_the_odometry_does_not_follow_the_cars(tmp_path: Path) -> None:
    """The real failure of issue 22: a car creeping at 0.17 m a frame in a jam, reported driving backwards."""
    frames = 20
    poses = np.zeros((frames, 3, 4))
    poses[:, :, :3] = np.eye(3)
    poses[:, 2, 3] = np.arange(frames) * 0.17  # KITTI camera frame: z ahead, the LiDAR's x
    np.savetxt(tmp_path / "creep.txt", poses.reshape(frames, 12))
    simulate_sequence(tmp_path / "drive", frames=frames, seed=52, trajectory=tmp_path / "creep.txt", escorts=True,
                      progress=False)
    detecting, _ = pair_errors(tmp_path / "drive", frame_to_frame())
    config = frame_to_frame()
    config.moving_objects.detect = False
    keeping, _ = pair_errors(tmp_path / "drive", config)
    assert detecting.max() < 0.04, detecting.round(3)
    assert keeping.max() > 2 * detecting.max(), (keeping.max(), detecting.max())


def test_a_run_says_how_much_the_network_left_out(jam: Path, tmp_path: Path) -> None:
    from dmlo.commands.run import format_summary
    from dmlo.run import run_sequence

    sequence = open_sequence(jam)
    summary = run_sequence(sequence, Odometry(default_model_path(), frame_to_frame()), tmp_path / "network",
                           remove_moving=False, max_frames=3, progress=False)
    assert summary.moving_share is not None and 0.05 < summary.moving_share < 0.6
    assert f"left out {100 * summary.moving_share:.1f} %" in format_summary(summary)
    labelled = run_sequence(sequence, Odometry(default_model_path(), frame_to_frame()), tmp_path / "labels",
                            max_frames=3, progress=False)
    assert labelled.moving_share is None and "moving objects" not in format_summary(labelled)
