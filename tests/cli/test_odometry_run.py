"""`dmlo run` and `run_sequence` end to end on a short simulated drive: the files a user asked for,
an interrupted run, damaged datasets, and one-line errors for user mistakes."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dmlo.datasets import open_sequence
from dmlo.odometry import Odometry
from dmlo.run import run_sequence
from dmlo.poses import read_kitti_poses, read_tum_poses
from dmlo.simulator import simulate_sequence


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("drive")
    simulate_sequence(out, frames=6, seed=9, progress=False)
    return out


def dmlo(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "dmlo", *args], capture_output=True, text=True)


def test_run_command_writes_poses_diagnostics_config_and_metrics(drive: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    result = dmlo("run", str(drive), "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert "vs ground truth" in result.stdout
    poses = read_kitti_poses(out / "poses_kitti.txt")
    timestamps, tum = read_tum_poses(out / "poses_tum.txt")
    assert poses.shape == (6, 4, 4) and np.allclose(poses, tum, atol=1e-6)
    assert np.allclose(np.diff(timestamps), 0.1, atol=1e-3)  # the simulator's 10 Hz clock
    diagnostics = [json.loads(line) for line in (out / "diagnostics.jsonl").read_text().splitlines()]
    assert [d["index"] for d in diagnostics] == list(range(6))
    metrics = json.loads((out / "metrics.json").read_text())
    assert {"ate_rmse", "rpe_t_mean", "rpe_r_mean"} <= set(metrics)
    assert json.loads((out / "config.json").read_text())["ransac"]["threshold"] == 0.1
    assert (out / "trajectory.png").stat().st_size > 0


def test_matching_flags_reach_the_config_and_the_diagnostics(drive: Path, tmp_path: Path) -> None:
    default, changed = tmp_path / "default", tmp_path / "changed"
    assert dmlo("run", str(drive), "--out", str(default), "--max-frames", "3").returncode == 0
    result = dmlo("run", str(drive), "--out", str(changed), "--max-frames", "3", "--symmetric", "--no-coherence")
    assert result.returncode == 0, result.stderr
    for out, symmetric, coherence in ((default, False, 0.5), (changed, True, None)):
        matching = json.loads((out / "config.json").read_text())["matching"]
        assert matching["symmetric"] is symmetric and matching["coherence_px"] == coherence
        timings = json.loads((out / "diagnostics.jsonl").read_text().splitlines()[1])["timings_ms"]
        assert "pair" in timings
        assert ("network_backward" in timings) is symmetric


def test_interrupted_run_leaves_valid_poses_for_the_frames_done(drive: Path, tmp_path: Path) -> None:
    def stop_after_three(index: int, _pose: np.ndarray) -> None:
        if index == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_sequence(open_sequence(drive), Odometry.from_default(), tmp_path, progress=False,
                     on_frame=stop_after_three)
    assert read_kitti_poses(tmp_path / "poses_kitti.txt").shape == (3, 4, 4)
    assert read_tum_poses(tmp_path / "poses_tum.txt")[1].shape == (3, 4, 4)
    assert len((tmp_path / "diagnostics.jsonl").read_text().splitlines()) == 3


def test_truncated_scan_is_skipped_and_recorded(drive: Path, tmp_path: Path) -> None:
    damaged = tmp_path / "damaged"
    shutil.copytree(drive, damaged)
    scan = damaged / "velodyne" / "000003.bin"
    scan.write_bytes(scan.read_bytes()[:1000])  # not a whole number of points
    summary = run_sequence(open_sequence(damaged), Odometry.from_default(), tmp_path / "out", progress=False)
    assert summary.skipped == [3]
    assert read_kitti_poses(tmp_path / "out" / "poses_kitti.txt").shape == (6, 4, 4)
    record = json.loads((tmp_path / "out" / "diagnostics.jsonl").read_text().splitlines()[3])
    assert "000003.bin" in record["skipped"]


def test_scans_that_parse_but_hold_no_plausible_points_are_skipped_and_recorded(drive: Path, tmp_path: Path) -> None:
    from dmlo.datasets import write_bin

    damaged = tmp_path / "damaged"
    shutil.copytree(drive, damaged)
    scan = damaged / "velodyne" / "000002.bin"
    write_bin(scan, open_sequence(drive)[2].points * np.float32(1e30))
    text = ("Not a scan, yet 16-byte records all the same. " * 40)[:640]
    (damaged / "velodyne" / "000004.bin").write_text(text)
    summary = run_sequence(open_sequence(damaged), Odometry.from_default(), tmp_path / "out", progress=False)
    assert summary.skipped == [2, 4]
    records = (tmp_path / "out" / "diagnostics.jsonl").read_text().splitlines()
    assert "000002.bin: not a plausible LiDAR scan" in json.loads(records[2])["skipped"]
    assert "000004.bin: not a plausible LiDAR scan" in json.loads(records[4])["skipped"]


def test_missing_scan_file_is_skipped(drive: Path, tmp_path: Path) -> None:
    damaged = tmp_path / "damaged"
    shutil.copytree(drive, damaged)
    sequence = open_sequence(damaged)
    (damaged / "velodyne" / "000004.bin").unlink()  # vanished after the folder was listed
    summary = run_sequence(sequence, Odometry.from_default(), tmp_path / "out", progress=False)
    assert summary.skipped == [4]


def test_matching_stage_flag_reaches_the_config_and_gives_the_same_poses(drive: Path, tmp_path: Path) -> None:
    poses = {}
    for stage in ("crate", "graph"):
        out = tmp_path / stage
        result = dmlo("run", str(drive), "--out", str(out), "--max-frames", "3", "--matching-stage", stage)
        assert result.returncode == 0, result.stderr
        assert json.loads((out / "config.json").read_text())["matching_stage"] == stage
        timings = json.loads((out / "diagnostics.jsonl").read_text().splitlines()[1])["timings_ms"]
        assert ("matching" in timings) is (stage == "crate") and timings["network"] > 0
        poses[stage] = read_kitti_poses(out / "poses_kitti.txt")
    np.testing.assert_allclose(poses["crate"], poses["graph"], atol=1e-3)


def test_a_config_with_an_unknown_matching_stage_is_one_line(drive: Path, tmp_path: Path) -> None:
    config = tmp_path / "config.json"
    config.write_text(json.dumps({"matching_stage": "gpu"}))
    result = dmlo("run", str(drive), "--out", str(tmp_path / "out"), "--config", str(config))
    assert result.returncode == 2
    assert f"cannot read config {config}: matching_stage: must be one of auto, crate, graph, got \"gpu\"" in result.stderr
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["run", "/nonexistent/drive"], "no such dataset folder: /nonexistent/drive"),
        (["run", ".", "--model", "/nonexistent/model.onnx"], "model not found: /nonexistent/model.onnx"),
    ],
)
def test_user_mistakes_are_one_line(args: list[str], message: str, drive: Path) -> None:
    if args[1] == ".":
        args[1] = str(drive)
    result = dmlo(*args)
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("value", ["0", "-1"])
def test_max_frames_below_one_is_refused_naming_the_flag(drive: Path, tmp_path: Path, value: str) -> None:
    result = dmlo("run", str(drive), "--out", str(tmp_path / "out"), "--max-frames", value)
    assert result.returncode == 2
    assert f"argument --max-frames: must be a positive integer (>= 1), got {value}" in result.stderr
    assert "Traceback" not in result.stderr and not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match="max_frames: must be at least 1, got 0"):
        run_sequence(open_sequence(drive), Odometry.from_default(), tmp_path / "api", max_frames=0)


def test_simulate_seed_and_counts_are_checked_naming_the_flag(tmp_path: Path) -> None:
    for args, message in (
        (["--seed", "-1"], "argument --seed: must be a non-negative integer (>= 0), got -1"),
        (["--frames", "0"], "argument --frames: must be a positive integer (>= 1), got 0"),
        (["--start", "-2"], "argument --start: must be a non-negative integer (>= 0), got -2"),
        (["--seed", "x"], "argument --seed: expected an integer, got 'x'"),
    ):
        result = dmlo("simulate", "--out", str(tmp_path / "sim"), *args)
        assert result.returncode == 2 and message in result.stderr, (args, result.stderr)
        assert "Traceback" not in result.stderr


def test_register_command_prints_and_writes_the_motion_between_two_scan_files(drive: Path, tmp_path: Path) -> None:
    from dmlo.datasets import write_bin
    from dmlo.metrics import registration_errors

    sequence = open_sequence(drive)
    write_bin(tmp_path / "a.bin", sequence[0].points)
    write_bin(tmp_path / "b.bin", sequence[1].points)
    truth = np.linalg.inv(sequence[1].pose) @ sequence[0].pose
    for flags in ([], ["--large-motion"]):
        out = tmp_path / f"T{len(flags)}.txt"
        result = dmlo("register", str(tmp_path / "a.bin"), str(tmp_path / "b.bin"), "--json", "--out", str(out), *flags)
        assert result.returncode == 0, result.stderr
        report = json.loads(result.stdout)
        transform = np.array(report["T_b_a"])
        errors = registration_errors(transform, truth)
        assert errors.angular_mean < 0.5 and errors.translation_mean < 0.1, (flags, errors)
        assert report["inliers"] >= 10 and report["rounds"] >= 1
        np.testing.assert_allclose(np.loadtxt(out), transform, atol=1e-8)
    text = dmlo("register", str(tmp_path / "a.bin"), str(tmp_path / "b.bin"))
    assert text.returncode == 0 and text.stdout.startswith("T_b_a (p_b = T_b_a · p_a):") and "RANSAC inliers" in text.stdout


def test_register_command_mistakes_are_one_line(drive: Path, tmp_path: Path) -> None:
    from dmlo.datasets import write_bin

    sequence = open_sequence(drive)
    write_bin(tmp_path / "a.bin", sequence[0].points)
    write_bin(tmp_path / "sparse.bin", sequence[1].points[:10])
    (tmp_path / "broken.bin").write_bytes(b"\x00" * 10)
    write_bin(tmp_path / "garbage.bin", sequence[1].points * np.float32(1e30))
    a = str(tmp_path / "a.bin")
    for args, message in (
        ([a, str(tmp_path / "missing.bin")], "target scan not found"),
        ([a, str(tmp_path / "garbage.bin")], "garbage.bin: not a plausible LiDAR scan"),
        ([a, str(tmp_path / "sparse.bin")], "target: 10 finite points, fewer than the 1000 needed"),
        ([a, str(tmp_path / "broken.bin")], "broken.bin"),
        ([a, a, "--mapping", "--large-motion"], "--mapping refines consecutive scans"),
    ):
        result = dmlo("register", *args)
        assert result.returncode == 2, args
        assert message in result.stderr, result.stderr
        assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_bench_command_compares_with_kiss_icp(drive: Path, tmp_path: Path) -> None:
    pytest.importorskip("kiss_icp")
    result = dmlo("bench", str(drive), "--peers", "KISS-ICP", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    table = result.stdout.strip().splitlines()
    assert table[0].startswith("| method |") and len(table) == 5  # both DMLO rows by default
    assert table[2].startswith("| DMLO |") and table[3].startswith("| DMLO + mapping |")
    assert table[4].startswith("| KISS-ICP |") and table[4].endswith("| 1.00 | 1.00 |")  # the reference's ratios to itself
    assert read_kitti_poses(tmp_path / "KISS-ICP.txt").shape == (6, 4, 4)


def test_bench_rows_say_which_matching_they_ran(drive: Path, tmp_path: Path) -> None:
    result = dmlo("bench", str(drive), "--peers", "--max-frames", "3", "--symmetric", "--no-coherence", "--mapping",
                  "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    rows = [line.split("|")[1].strip() for line in result.stdout.strip().splitlines()[2:]]
    assert rows == ["DMLO (symmetric, no coherence)", "DMLO (symmetric, no coherence) + mapping"]
    result = dmlo("bench", str(drive), "--peers", "--max-frames", "3", "--matching-stage", "graph", "--no-mapping",
                  "--out", str(tmp_path / "graph"))
    assert result.returncode == 0, result.stderr
    rows = [line.split("|")[1].strip() for line in result.stdout.strip().splitlines()[2:]]
    assert rows == ["DMLO (matching in onnxruntime)"]  # --no-mapping: the frame-to-frame row alone


@pytest.mark.parametrize(
    ("flags", "config", "mapping"),
    [([], None, True), (["--no-mapping"], None, False), (["--mapping"], None, True),
     ([], False, False), (["--mapping"], False, True), (["--no-mapping"], True, False)],
    ids=["default", "no-mapping", "mapping", "config-off", "flag-over-config", "no-flag-over-config"],
)
def test_mapping_is_the_default_and_no_mapping_is_frame_to_frame(
    flags: list[str], config: bool | None, mapping: bool, drive: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from dmlo.cli import main as dmlo_main

    extra = []
    if config is not None:
        (tmp_path / "config.json").write_text(json.dumps({"mapping": {"enabled": config}}))
        extra = ["--config", str(tmp_path / "config.json")]
    out = tmp_path / "out"
    assert dmlo_main(["run", str(drive), "--out", str(out), "--max-frames", "2", *flags, *extra]) == 0, capsys.readouterr().err
    assert json.loads((out / "config.json").read_text())["mapping"]["enabled"] is mapping
    second = json.loads((out / "diagnostics.jsonl").read_text().splitlines()[1])
    assert (second["ndt_converged"] is not None) is mapping


def test_register_refines_a_consecutive_pair_by_ndt_unless_no_mapping(drive: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from dmlo.cli import main as dmlo_main
    from dmlo.datasets import write_bin

    sequence = open_sequence(drive)
    write_bin(tmp_path / "a.bin", sequence[0].points)
    write_bin(tmp_path / "b.bin", sequence[1].points)
    reports = {}
    for flags in ([], ["--no-mapping"], ["--large-motion"]):
        capsys.readouterr()
        assert dmlo_main(["register", str(tmp_path / "a.bin"), str(tmp_path / "b.bin"), "--json", *flags]) == 0
        reports[" ".join(flags)] = json.loads(capsys.readouterr().out)
    assert reports[""]["map_refined"] is True
    assert reports["--no-mapping"]["map_refined"] is None and reports["--large-motion"]["map_refined"] is None
    assert reports[""]["inliers"] == reports["--no-mapping"]["inliers"]  # the same matches, the motion refined
    assert dmlo_main(["register", str(tmp_path / "a.bin"), str(tmp_path / "b.bin")]) == 0
    assert "refined against A (mapping: NDT" in capsys.readouterr().out


def test_deskew_flag_reaches_the_config_and_the_diagnostics(drive: Path, tmp_path: Path) -> None:
    result = dmlo("run", str(drive), "--out", str(tmp_path), "--max-frames", "4", "--deskew")
    assert result.returncode == 0, result.stderr
    assert json.loads((tmp_path / "config.json").read_text())["deskew"]["enabled"] is True
    diagnostics = [json.loads(line) for line in (tmp_path / "diagnostics.jsonl").read_text().splitlines()]
    assert [d["deskewed"] for d in diagnostics] == [False, False, True, True]  # from the first measured motion on


def test_bench_with_deskew_compares_with_kiss_icp_deskewed(drive: Path, tmp_path: Path) -> None:
    pytest.importorskip("kiss_icp")
    result = dmlo("bench", str(drive), "--deskew", "--peers", "KISS-ICP deskewed", "--max-frames", "4",
                  "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    rows = [line.split("|")[1].strip() for line in result.stdout.strip().splitlines()[2:]]
    assert rows == ["DMLO (deskewed)", "DMLO (deskewed) + mapping", "KISS-ICP deskewed"]
    assert read_kitti_poses(tmp_path / "KISS-ICP_deskewed.txt").shape == (4, 4, 4)


def test_bench_names_an_unknown_peer(drive: Path, tmp_path: Path) -> None:
    result = dmlo("bench", str(drive), "--peers", "ICP-9000", "--out", str(tmp_path))
    assert result.returncode == 2
    assert "unknown peer(s): ICP-9000" in result.stderr


def test_demo_simulates_runs_and_reports(tmp_path: Path) -> None:
    result = dmlo("demo", "--frames", "4", "--seed", "3", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    assert "4 scans in" in result.stdout and "vs ground truth" in result.stdout
    assert read_kitti_poses(tmp_path / "odometry" / "poses_kitti.txt").shape == (4, 4, 4)
    assert (tmp_path / "odometry" / "trajectory.png").is_file()


def test_demo_on_skewed_sweeps_deskews(tmp_path: Path) -> None:
    result = dmlo("demo", "--frames", "4", "--motion-distortion", "--deskew", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    assert json.loads((tmp_path / "drive" / "simulation.json").read_text())["motion_distortion"] is True
    diagnostics = (tmp_path / "odometry" / "diagnostics.jsonl").read_text().splitlines()
    assert [json.loads(line)["deskewed"] for line in diagnostics] == [False, False, True, True]


def test_register_has_no_deskew_flag(drive: Path) -> None:
    # Two scans have no motion model to deskew them by: the flag would do nothing, so it is not offered.
    scans = sorted((drive / "velodyne").glob("*.bin"))
    result = dmlo("register", str(scans[0]), str(scans[1]), "--deskew")
    assert result.returncode == 2 and "unrecognized arguments: --deskew" in result.stderr


def test_command_dataset_formats_are_the_reader_registry() -> None:
    from dmlo.commands.run import DATASET_FORMATS
    from dmlo.datasets import FORMATS

    assert set(DATASET_FORMATS) == set(FORMATS)


def test_run_on_another_sensor_warns_in_one_line(tmp_path: Path) -> None:
    drive = tmp_path / "argoverse"
    simulate_sequence(drive, frames=2, seed=3, sensor="argoverse", progress=False)
    result = dmlo("run", str(drive), "--out", str(tmp_path / "out"))
    assert result.returncode == 0, result.stderr
    # Its own line above the progress bar (which redraws with carriage returns).
    lines = [line.split("\r")[-1] for line in result.stderr.splitlines()]
    warning = [line for line in lines if "warning" in line]
    assert len(warning) == 1 and warning[0].startswith("dmlo run: warning: the scans fill only"), result.stderr


def test_run_without_matplotlib_writes_everything_but_the_plot_and_says_how_to_get_it(
    drive: Path, tmp_path: Path
) -> None:
    # Plots are the optional `plot` extra: the command line runs with matplotlib made unimportable.
    out = tmp_path / "out"
    code = (
        "import sys; sys.modules['matplotlib'] = None; from dmlo.cli import main; "
        f"sys.exit(main(['run', {str(drive)!r}, '--max-frames', '3', '--out', {str(out)!r}]))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "vs ground truth" in result.stdout
    assert (out / "metrics.json").is_file() and (out / "poses_kitti.txt").is_file()
    assert not (out / "trajectory.png").exists() and not list(out.glob(".trajectory*"))
    lines = [line.split("\r")[-1] for line in result.stderr.splitlines()]
    warning = [line for line in lines if "warning" in line]
    notice = "dmlo run: warning: trajectory.png skipped: plots need matplotlib: pip install 'dmlo[plot]'"
    assert warning == [notice], result.stderr


def test_an_estimate_beyond_the_metrics_range_keeps_its_poses_and_skips_the_metrics(drive: Path, tmp_path: Path) -> None:
    """An estimate gone 10¹³ m away (a broken model, say): the poses are written as they are, the metrics are
    skipped with a warning instead of failing the run after the poses."""
    from dmlo.odometry import FrameDiagnostics, OdometryConfig

    class RunawayOdometry:
        config = OdometryConfig()

        def __init__(self) -> None:
            self.poses: list[np.ndarray] = []
            self.diagnostics: list[FrameDiagnostics] = []

        def register(self, points: np.ndarray, moving: object = None, timestamp: object = None) -> np.ndarray:
            pose = np.eye(4)
            pose[0, 3] = 1e13 * len(self.poses)
            self.poses.append(pose)
            self.diagnostics.append(FrameDiagnostics(index=len(self.poses) - 1, num_points=len(points)))
            return pose

    with pytest.warns(UserWarning, match="metrics.json and trajectory.png skipped: poses_est: pose 1 lies 1e\\+13 m"):
        summary = run_sequence(open_sequence(drive), RunawayOdometry(), tmp_path, progress=False)  # type: ignore[arg-type]
    assert summary.metrics is None and summary.frames == len(open_sequence(drive))
    assert not (tmp_path / "metrics.json").exists()
    assert read_kitti_poses(tmp_path / "poses_kitti.txt")[-1, 0, 3] == pytest.approx(1e13 * (summary.frames - 1))
