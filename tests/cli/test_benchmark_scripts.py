"""The benchmark scripts (`benchmarks/`, outside the wheel) run end to end on a tiny simulated drive (their numbers
go into BENCHMARKS.md and the README)."""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from dmlo.odometry.matcher import default_model_path
from dmlo.peers.consensus import missing_gicps
from dmlo.simulator import simulate_sequence
from support import REPO, rust_example

SCRIPTS = REPO / "benchmarks"


def script(name: str) -> ModuleType:
    """`benchmarks/<name>.py`, imported as a module (under a name of its own, so it shadows nothing)."""
    spec = importlib.util.spec_from_file_location(f"benchmark_script_{name}", SCRIPTS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the script runs
    spec.loader.exec_module(module)
    return module


large_motion, matching, missing_scans, network = (script(n) for n in ("large_motion", "matching", "missing_scans", "network"))


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("drive")
    simulate_sequence(out, frames=4, seed=13, progress=False)
    return out


def test_matching_benchmark_reports_flow_and_pose_errors(drive: Path) -> None:
    result = matching.evaluate(default_model_path(), [drive], pairs_per_drive=2)
    assert set(result) == {"epe", "fl_all", "kept_epe", "kept_fl_all", "rotation_deg", "translation_m",
                           "network_ms", "pair_ms"}
    assert all(np.isfinite(v) and v >= 0 for v in result.values())
    assert 0 <= result["fl_all"] <= 100


def test_large_motion_benchmark_tabulates_every_method(drive: Path) -> None:
    table = large_motion.run([drive], gaps=[2], pairs=2, model=None).splitlines()
    assert table[0].startswith("| gap | method | success |")
    rows = table[2:]
    assert any("DMLO (wide window, searched, re-matched)" in row for row in rows)
    assert any("DMLO (wide window once, the paper)" in row for row in rows)
    assert all(row.startswith("| 2 |") for row in rows)


def test_missing_scans_benchmark_tabulates_dmlo_and_the_peers(tmp_path: Path) -> None:
    simulate_sequence(tmp_path, frames=7, seed=13, progress=False)
    table = missing_scans.run([tmp_path], gaps=[2], cases=1, model=None, peers=["KISS-ICP"], lead_in=5).splitlines()
    assert table[0].startswith("| gap (frames) | method | bridged |")
    methods = [row.split(" | ")[1] for row in table[2:]]
    assert methods == ["DMLO (re-matched from the prediction)", "DMLO (the paper: the prediction when the pair fails)",
                       "DMLO + mapping", "KISS-ICP"]
    # A slow simulated drive: every method bridges a single missing scan.
    assert all(row.startswith("| 2 |") and " | 1/1 | " in row for row in table[2:])
    with pytest.raises(SystemExit, match="too few for a gap of 3"):
        missing_scans.run([tmp_path], gaps=[3], cases=1, model=None, peers=[], lead_in=5)
    with pytest.raises(SystemExit, match="unknown peer 'KISS'"):
        missing_scans.run([tmp_path], gaps=[2], cases=1, model=None, peers=["KISS"], lead_in=5)


def test_odometry_benchmark_on_skewed_sweeps_adds_the_deskewed_rows(tmp_path: Path) -> None:
    def bench(*flags: str) -> subprocess.CompletedProcess[str]:
        command = [sys.executable, str(SCRIPTS / "odometry.py"), "--frames", "4", "--seeds", "1", "--poses",
                   str(tmp_path / "no_poses"), "--peers", "--out", str(tmp_path), *flags]
        return subprocess.run(command, capture_output=True, text=True)

    result = bench("--motion-distortion")
    assert result.returncode == 0, result.stderr
    methods = [row.split(" | ")[0].strip("| ") for row in result.stdout.strip().splitlines()[-4:]]
    assert methods == ["DMLO", "DMLO + mapping", "DMLO deskewed", "DMLO + mapping, deskewed"]
    # The drive in --out was cast skewed: a run that expects snapshots must not reuse it.
    refused = bench()
    assert refused.returncode == 2 and "holds drives with motion distortion" in refused.stderr


def test_network_benchmark_compares_model_folders_without_writing_beside_them(
    drive: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model = default_model_path()
    copy = shutil.copytree(model, tmp_path / "copy", ignore=shutil.ignore_patterns("training"))
    before = sorted(p.name for p in model.iterdir())
    network.main(["--models", str(model), str(copy), "--drive", str(drive), "--repeats", "1", "--profile"])
    lines = capsys.readouterr().out.splitlines()
    rows = [line for line in lines if line.startswith((f"| {model} |", f"| {copy} |"))]
    assert len(rows) == 2
    # Byte-identical graphs: no flow or confidence difference, so the comparison itself is not broken.
    assert all(row.endswith("| 0 | 0 | 0 |") for row in rows)
    assert sum(line.startswith((f"{model}: ", f"{copy}: ")) and "Conv" in line for line in lines) == 2
    assert sorted(p.name for p in model.iterdir()) == before  # no profiling trace left in the model folder
    with pytest.raises(SystemExit, match="each folder once"):
        network.main(["--models", str(model), str(model), "--drive", str(drive)])


def test_network_benchmark_times_the_matching_stage_both_ways(drive: Path, capsys: pytest.CaptureFixture[str]) -> None:
    network.main(["--stages", "--drive", str(drive), "--repeats", "1"])
    lines = capsys.readouterr().out.splitlines()
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ") for line in lines if line.startswith("| ") and "---" not in line}
    assert set(rows) >= {"frame.onnx (encode + match)", "encoder.onnx + crate", "match.onnx (cached features)",
                         "crate alone (cached features)", "frame_wide.onnx (encode + match)",
                         "encoder.onnx + crate, wide window"}
    for crate_row in ("encoder.onnx + crate", "crate alone (cached features)", "encoder.onnx + crate, wide window"):
        ratio, differing = rows[crate_row][3], rows[crate_row][4]
        assert float(ratio) > 0
        count, total = differing.strip(" |").split(" of ")
        assert int(total) == 64 * 1792 and int(count) < 0.001 * int(total)  # the same matches both ways
    with pytest.raises(SystemExit, match="--stages needs --drive"):
        network.main(["--stages"])


def test_real_scan_benchmark_runs_on_a_plain_folder_of_scans(drive: Path, tmp_path: Path) -> None:
    pytest.importorskip("small_gicp")
    scans = tmp_path / "my_drive"
    scans.mkdir()
    for path in sorted((drive / "velodyne").glob("*.bin"))[:3]:
        shutil.copy(path, scans / path.name)  # no poses, no calibration: anyone's own drive
    out = tmp_path / "out"
    command = [sys.executable, str(SCRIPTS / "real.py"), str(scans), "--peers", "--out", str(out)]
    result = subprocess.run(command, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    missing = missing_gicps()
    if len(missing) == 1:  # a single GICP: the warning says why the other is missing
        assert next(iter(missing.values())) in result.stderr, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("| DMLO")]
    assert [row.split(" | ")[0] for row in rows] == ["| DMLO", "| DMLO + mapping"]
    assert "on every pair up to 3 scans apart, solved jointly" in result.stdout  # the multi-scan reference
    assert all(row.split(" | ")[6] != "—" for row in rows)  # … with the consecutive pairs' figures beside it
    report = json.loads((out / "real.json").read_text())
    (entry,) = report["sets"].values()
    assert len(entry["reference"]["motions"]) == 2 and entry["reference"]["span"] == 3
    assert len(entry["reference"]["residual_m"]) == 3 * len(entry["reference"]["sources"])  # 0-1, 1-2, 0-2
    refused = subprocess.run([*command[:-2], "--max-frames", "1"], capture_output=True, text=True)
    assert refused.returncode == 2 and "--max-frames" in refused.stderr
    refused = subprocess.run([*command[:-2], "--span", "0"], capture_output=True, text=True)
    assert refused.returncode == 2 and "--span: at least 1" in refused.stderr


def test_real_scan_benchmark_names_an_unreadable_set_and_keeps_the_others(drive: Path, tmp_path: Path) -> None:
    pytest.importorskip("small_gicp")
    good, truncated, single = tmp_path / "good", tmp_path / "truncated", tmp_path / "single"
    scans = sorted((drive / "velodyne").glob("*.bin"))[:2]
    for folder in (good, truncated):
        folder.mkdir()
        for path in scans:
            shutil.copy(path, folder / path.name)
    with open(truncated / scans[1].name, "r+b") as file:
        file.truncate(1001)
    single.mkdir()
    shutil.copy(scans[0], single / scans[0].name)
    out = tmp_path / "out"
    command = [sys.executable, str(SCRIPTS / "real.py"), str(truncated), str(single), str(good), "--peers", "--out", str(out)]
    result = subprocess.run(command, capture_output=True, text=True)
    assert result.returncode == 1
    assert f"error: {truncated}: " in result.stderr and "truncated" in result.stderr.split(str(truncated), 1)[1]
    assert f"error: {single}: 1 scan(s); a pair needs at least 2" in result.stderr
    assert "2 of 3 set(s) not measured" in result.stderr
    report = json.loads((out / "real.json").read_text())
    assert list(report["sets"]) == [str(good)]  # the readable set measured and written
    assert "| DMLO + mapping |" in result.stdout


def test_real_scan_benchmark_keeps_the_sets_done_when_interrupted(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from dmlo.peers.consensus import ConsensusReference

    real = script("real")
    first, second = tmp_path / "first", tmp_path / "second"
    reference = ConsensusReference(np.eye(4)[None], np.zeros(1), np.zeros(1), ("stub",))

    def one_set(folder: Path, *_: object) -> tuple[ConsensusReference, list[object]]:
        if folder == second:
            raise KeyboardInterrupt  # Ctrl-C while the second set runs
        return reference, []

    monkeypatch.setattr(real, "run_set", one_set)
    monkeypatch.setattr(sys, "argv", ["real.py", str(first), str(second), "--peers", "--out", str(tmp_path / "out")])
    with pytest.raises(KeyboardInterrupt):
        real.main()
    report = json.loads((tmp_path / "out" / "real.json").read_text())
    assert list(report["sets"]) == [str(first)]


def test_real_scan_pair_errors_are_measured_against_the_reference() -> None:
    from scipy.spatial.transform import Rotation

    from dmlo.peers.consensus import ConsensusReference
    pair_errors = script("real").pair_errors

    rng = np.random.default_rng(0)
    motions = np.tile(np.eye(4), (5, 1, 1))
    motions[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.02, (5, 3))).as_matrix()
    motions[:, :3, 3] = rng.normal(0, 1, (5, 3))
    error = np.eye(4)
    error[:3, :3] = Rotation.from_rotvec([0.0, np.radians(0.1), 0.0]).as_matrix()  # nose down by 0.1°
    error[:3, 3] = [0.02, 0.0, 0.0]
    estimate = [np.eye(4)]
    for motion in motions:
        estimate.append(estimate[-1] @ motion @ error)
    reference = ConsensusReference(motions, np.zeros(5), np.zeros(5), ("test",))
    row = pair_errors("m", np.stack(estimate), reference, hz=10.0)
    assert row.translation_mean_cm == pytest.approx(2.0) and row.translation_max_cm == pytest.approx(2.0)
    assert row.rotation_mean_deg == pytest.approx(0.1) and row.pitch_bias_deg == pytest.approx(0.1)
    assert row.consecutive_translation_mean_cm is None  # a reference of consecutive pairs alone
    consecutive = motions.copy()
    consecutive[:, :3, 3] += [0.0, 0.03, 0.0]
    multi = ConsensusReference(motions, np.zeros(5), np.zeros(5), ("test",), span=3, consecutive_motions=consecutive)
    row = pair_errors("m", np.stack(estimate), multi, hz=10.0)
    assert row.translation_mean_cm == pytest.approx(2.0)
    assert row.consecutive_translation_mean_cm is not None and row.consecutive_translation_mean_cm > 3.0  # 2 and 3 cm apart


def test_reference_benchmark_measures_the_consensus_against_a_simulated_truth(capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("small_gicp")
    script("reference").main(["--seeds", "5", "--frames", "5", "--spans", "1", "3"])
    out = capsys.readouterr().out
    rows = {line.split(" | ")[0]: line for line in out.splitlines() if line.startswith("| 1 |") or line.startswith("| 3 |")}
    assert set(rows) == {"| 1", "| 3"}, out
    error = {span: float(rows[f"| {span}"].split(" | ")[1]) for span in (1, 3)}
    assert 0 < error[3] < error[1] < 5, error  # the multi-scan consensus is the nearer the truth
    with pytest.raises(SystemExit):
        script("reference").main(["--spans", "0"])


def test_odometry_benchmark_adds_the_named_highway_drive(tmp_path: Path) -> None:
    command = [sys.executable, str(SCRIPTS / "odometry.py"), "--frames", "3", "--seeds", "1", "--highway", "3",
               "--poses", str(tmp_path / "no_poses"), "--peers", "--out", str(tmp_path)]
    result = subprocess.run(command, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "### highway_seed3 (generated trajectory, 3 frames)" in result.stdout
    info = json.loads((tmp_path / "highway_seed3" / "simulation.json").read_text())
    assert info["scene"] == "highway" and info["laser_gain_spread"] == 0.6


def test_odometry_benchmark_adds_the_named_jam_and_the_rows_without_the_network(tmp_path: Path) -> None:
    command = [sys.executable, str(SCRIPTS / "odometry.py"), "--frames", "3", "--seeds", "--jam", "4", "--keep-moving",
               "--peers", "--out", str(tmp_path)]
    result = subprocess.run(command, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "### jam_seed4 (generated trajectory, 3 frames)" in result.stdout
    assert "| DMLO, moving kept |" in result.stdout and "| DMLO + mapping, moving kept |" in result.stdout
    info = json.loads((tmp_path / "jam_seed4" / "simulation.json").read_text())
    assert info["escorts"] is True and info["traffic"] == "mixed" and info["scene"] == "street"


def test_moving_objects_benchmark_scores_the_network_on_a_labelled_drive(drive: Path, tmp_path: Path) -> None:
    out = tmp_path / "moving.json"
    command = [sys.executable, str(SCRIPTS / "moving_objects.py"), str(drive), "--json", str(out)]
    result = subprocess.run(command, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert drive.name in result.stdout and "precision" in result.stdout
    scores = json.loads(out.read_text())[drive.name]
    assert scores["scans"] == 4 and scores["points"] > 100_000 and scores["moving"] > 0
    assert 0 <= scores["precision"] <= 1 and 0 <= scores["recall"] <= 1


def test_rust_odometry_benchmark_times_both_languages_on_the_same_scans(drive: Path, tmp_path: Path) -> None:
    from dmlo.odometry import OdometryConfig
    from dmlo.odometry.matcher import onnxruntime_library

    rust_odometry = script("rust_odometry")
    rust_odometry.EXAMPLE = rust_example("odometry")
    config = OdometryConfig()
    config.moving_objects.detect = False
    config.threads = 2
    config.save(tmp_path / "config.json")
    python_rate, python_moved = rust_odometry.python_run(drive / "velodyne", tmp_path / "config.json")
    ort_rate, ort_moved = rust_odometry.rust_run(drive / "velodyne", tmp_path / "config.json", 2, onnxruntime_library())
    tract_rate, tract_moved = rust_odometry.rust_run(drive / "velodyne", tmp_path / "config.json", 2, None)
    assert min(python_rate, ort_rate, tract_rate) > 0
    assert python_moved.shape == ort_moved.shape == tract_moved.shape == (4, 3)
    assert np.linalg.norm(python_moved[-1]) > 1.0
    np.testing.assert_allclose(ort_moved, python_moved, rtol=0, atol=1e-6)
    assert np.isfinite(tract_moved).all()
