"""Output folders and files (issue 25, items 5 and 6): an earlier run's files are refused or replaced,
never mixed with a new run's; failures to write are one-line errors; the KITTI, TUM and diagnostics files
always hold the same frames, whatever stops the run (a full disk is an `OSError` injected into the writer)."""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dmlo import outputs as writers
from dmlo.cli import main
from dmlo.datasets import open_sequence
from dmlo.odometry import Odometry
from dmlo.run import run_sequence
from dmlo.outputs import BENCH_FILES, RUN_FILES, FrameFiles, OutputError, atomic_output, prepare_output_folder
from dmlo.poses import read_kitti_poses, read_tum_poses
from dmlo.simulator import simulate_sequence

FRAMES = 5


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("drive")
    simulate_sequence(out, frames=FRAMES, seed=9, progress=False)
    return out


@pytest.fixture(scope="module")
def drive_without_ground_truth(drive: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("no_truth") / "drive"
    shutil.copytree(drive, out)
    (out / "poses.txt").unlink()
    return out


def dmlo(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "dmlo", *args], capture_output=True, text=True)


def assert_one_line(stderr: str, *fragments: str) -> None:
    """One line besides the progress bar, no traceback, holding every fragment."""
    lines = [line for line in stderr.strip().splitlines() if "%|" not in line]
    assert "Traceback" not in stderr and len(lines) == 1, stderr
    for fragment in fragments:
        assert fragment in stderr, stderr


def frames_in(out: Path) -> tuple[int, int, int]:
    """Frames in the KITTI, TUM and diagnostics files; each must read back whole."""
    kitti = len(read_kitti_poses(out / "poses_kitti.txt")) if (out / "poses_kitti.txt").stat().st_size else 0
    tum = len(read_tum_poses(out / "poses_tum.txt")[1]) if (out / "poses_tum.txt").stat().st_size else 0
    records = [json.loads(line) for line in (out / "diagnostics.jsonl").read_text().splitlines()]
    assert [r["index"] for r in records] == list(range(len(records)))
    return kitti, tum, len(records)


def run(drive: Path, out: Path, **options: object):  # type: ignore[no-untyped-def]
    return run_sequence(open_sequence(drive), Odometry.from_default(), out, progress=False, **options)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------------------
# Item 5: one run's files at a time


def test_a_folder_with_an_earlier_run_is_refused_and_left_as_it_was(drive: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    run(drive, out)
    before = {path.name: path.read_bytes() for path in out.iterdir()}
    assert set(before) == set(RUN_FILES)
    with pytest.raises(OutputError, match="holds the files of an earlier run .*--overwrite"):
        run(drive, out, max_frames=2)
    assert {path.name: path.read_bytes() for path in out.iterdir()} == before


def test_overwrite_clears_every_file_of_the_earlier_run(drive: Path, drive_without_ground_truth: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    run(drive, out)  # with ground truth: metrics.json, ground_truth_kitti.txt, trajectory.png
    (out / ".poses_kitti.txt.x1y2.tmp").write_text("left by a killed atomic write")
    (out / "notes.md").write_text("the user's own")
    run(drive_without_ground_truth, out, max_frames=3, overwrite=True)
    names = {path.name for path in out.iterdir()}
    assert names == {"config.json", "poses_kitti.txt", "poses_tum.txt", "diagnostics.jsonl", "notes.md"}
    assert frames_in(out) == (3, 3, 3)


def test_a_folder_of_other_files_is_not_a_run(drive: Path, tmp_path: Path) -> None:
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.md").write_text("kept")
    run(drive, out, max_frames=2)
    assert (out / "notes.md").read_text() == "kept" and frames_in(out) == (2, 2, 2)


def test_a_bench_folder_is_an_earlier_run_too(drive: Path, tmp_path: Path) -> None:
    out = tmp_path / "bench"
    out.mkdir()
    for name in ("ground_truth.txt", "DMLO_+_mapping.txt", "KISS-ICP.txt"):
        (out / name).write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(OutputError, match="DMLO_\\+_mapping.txt"):
        run(drive, out, max_frames=2)
    run(drive, out, max_frames=2, overwrite=True)
    assert {path.name for path in out.glob("*.txt")} == {"poses_kitti.txt", "poses_tum.txt", "ground_truth_kitti.txt"}


def test_bench_file_patterns_cover_every_peer() -> None:
    import fnmatch

    from dmlo.peers.peers import PEERS

    for name in ["DMLO", "DMLO (symmetric, deskewed) + mapping", *(peer.name for peer in PEERS)]:
        file = f"{name.replace(' ', '_')}.txt"
        assert any(fnmatch.fnmatchcase(file, pattern) for pattern in BENCH_FILES), file


class StandStill:
    """A stand-in odometry for the bench runner: the identity for every scan."""

    def register(self, points: np.ndarray) -> np.ndarray:
        return np.eye(4)


def test_bench_refuses_an_earlier_run_and_overwrite_removes_every_method_file(drive: Path, tmp_path: Path) -> None:
    from dmlo.peers.runner import benchmark_sequence

    sequence, out = open_sequence(drive), tmp_path / "bench"
    benchmark_sequence(sequence, {"DMLO": StandStill, "DMLO + mapping": StandStill}, out, peers=[], max_frames=2)
    assert {p.name for p in out.iterdir()} == {"ground_truth.txt", "DMLO.txt", "DMLO_+_mapping.txt"}
    with pytest.raises(OutputError, match="earlier run"):
        benchmark_sequence(sequence, {"DMLO": StandStill}, out, peers=[], max_frames=2)
    benchmark_sequence(sequence, {"DMLO": StandStill}, out, peers=[], max_frames=2, overwrite=True)
    assert {p.name for p in out.iterdir()} == {"ground_truth.txt", "DMLO.txt"}


def test_run_command_refuses_an_earlier_run_in_one_line_and_overwrites_on_request(
    drive: Path, drive_without_ground_truth: Path, tmp_path: Path
) -> None:
    out = tmp_path / "run"
    assert dmlo("run", str(drive), "--out", str(out), "--max-frames", "3").returncode == 0
    assert (out / "metrics.json").is_file()
    refused = dmlo("run", str(drive_without_ground_truth), "--out", str(out))
    assert refused.returncode == 2
    assert_one_line(refused.stderr, "dmlo run: error:", "earlier run", "--overwrite")
    result = dmlo("run", str(drive_without_ground_truth), "--out", str(out), "--overwrite")
    assert result.returncode == 0, result.stderr
    assert not (out / "metrics.json").exists() and not (out / "trajectory.png").exists()
    assert not (out / "ground_truth_kitti.txt").exists()
    assert frames_in(out) == (FRAMES, FRAMES, FRAMES)


def test_demo_replaces_its_own_earlier_results(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    for _ in range(2):
        result = dmlo("demo", "--frames", "3", "--out", str(out))
        assert result.returncode == 0, result.stderr
    assert frames_in(out / "odometry") == (3, 3, 3)


# ---------------------------------------------------------------------------------------------------------
# Item 6: one-line errors, files that agree


def test_out_under_a_file_is_one_line(drive: Path, tmp_path: Path) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    for args in (["run", str(drive)], ["bench", str(drive), "--peers"], ["demo", "--frames", "2"]):
        result = dmlo(*args, "--out", str(blocker / "run"))
        assert result.returncode == 2, (args, result.stderr)
        assert_one_line(result.stderr, str(blocker), "a file")
    result = dmlo("run", str(drive), "--out", str(blocker))
    assert result.returncode == 2
    assert_one_line(result.stderr, f"output folder {blocker} is a file")


def test_register_out_under_a_file_or_on_a_folder_is_one_line(drive: Path, tmp_path: Path) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    scans = [str(drive / "velodyne" / f"00000{i}.bin") for i in (0, 1)]
    under = dmlo("register", *scans, "--out", str(blocker / "T.txt"))
    assert under.returncode == 2
    assert_one_line(under.stderr, "dmlo register: error:", f"{blocker} is a file")
    folder = tmp_path / "a_folder"
    folder.mkdir()
    on_folder = dmlo("register", *scans, "--out", str(folder))
    assert on_folder.returncode == 2
    assert_one_line(on_folder.stderr, f"cannot write {folder}: it is a folder")


def test_a_folder_in_place_of_a_pose_file_is_one_line(drive: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    (out / "poses_tum.txt").mkdir(parents=True)
    for extra in ([], ["--overwrite"]):
        result = dmlo("run", str(drive), "--out", str(out), *extra)
        assert result.returncode == 2
        assert_one_line(result.stderr, f"{out / 'poses_tum.txt'} is a folder")
    assert (out / "poses_tum.txt").is_dir()  # never deleted recursively


def full_disk_after(calls: int, monkeypatch: pytest.MonkeyPatch, error: BaseException | None = None) -> None:
    """The writer's `calls`-th write (counting from 0) takes half of its bytes and then fails as a full
    disk does (or raises `error`)."""
    real = writers._write_all
    count = {"n": 0}

    def write(descriptor: int, data: bytes) -> None:
        count["n"] += 1
        if count["n"] - 1 == calls:
            os.write(descriptor, data[: len(data) // 2])
            raise error if error is not None else OSError(errno.ENOSPC, "No space left on device")
        real(descriptor, data)

    monkeypatch.setattr(writers, "_write_all", write)


@pytest.mark.parametrize("failing_file", [0, 1, 2])
def test_frame_files_on_a_full_disk_hold_the_same_complete_frames(
    failing_file: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    paths = [tmp_path / name for name in ("a.txt", "b.txt", "c.txt")]
    full_disk_after(3 * 4 + failing_file, monkeypatch)  # in frame 4, at file `failing_file`
    with pytest.raises(OutputError, match=r"cannot write .*: no space left on device \(the output files hold the 4 frames"):
        with FrameFiles(paths) as files:
            for frame in range(10):
                files.append([f"{name} {frame}\n" for name in "abc"])
    for path, name in zip(paths, "abc", strict=True):
        assert path.read_text() == "".join(f"{name} {frame}\n" for frame in range(4))


def test_run_on_a_full_disk_is_one_line_and_keeps_the_same_frames_in_all_three(
    drive: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    full_disk_after(3 * 3 + 1, monkeypatch)  # frame 3's TUM line
    assert main(["run", str(drive), "--out", str(out)]) == 2
    assert_one_line(capsys.readouterr().err, "dmlo run: error: cannot write", "poses_tum.txt", "no space left on device")
    assert frames_in(out) == (3, 3, 3)


def test_ctrl_c_between_two_files_of_a_frame_keeps_the_same_frames(
    drive: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    full_disk_after(3 * 2 + 2, monkeypatch, KeyboardInterrupt())  # frame 2's diagnostics line
    with pytest.raises(KeyboardInterrupt):
        run(drive, tmp_path)
    assert frames_in(tmp_path) == (2, 2, 2)


def test_a_full_disk_at_the_metrics_leaves_no_half_file(
    drive: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pathlib import Path as PathType

    real = PathType.write_text

    def write_text(self: PathType, text: str, *args: object, **kwargs: object) -> int:
        if self.name.startswith(".metrics.json."):
            real(self, text[:10], *args, **kwargs)  # type: ignore[arg-type]
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, text, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(PathType, "write_text", write_text)
    with pytest.raises(OutputError, match="cannot write .*metrics.json: no space left on device"):
        run(drive, tmp_path / "run")
    names = {path.name for path in (tmp_path / "run").iterdir()}
    assert "metrics.json" not in names and not any(name.startswith(".") for name in names)
    assert frames_in(tmp_path / "run") == (FRAMES, FRAMES, FRAMES)


def test_atomic_output_keeps_the_previous_file_on_failure(tmp_path: Path) -> None:
    target = tmp_path / "T.txt"
    target.write_text("previous")
    with pytest.raises(OutputError, match="T.txt: no space left"), atomic_output(target) as temporary:
        temporary.write_text("half")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert target.read_text() == "previous" and [p.name for p in tmp_path.iterdir()] == ["T.txt"]


def test_prepare_names_the_file_in_the_way(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(OutputError, match=f"output folder {blocker}/a/b is under {blocker}, a file"):
        prepare_output_folder(blocker / "a" / "b", RUN_FILES)


def test_a_fresh_training_run_refuses_an_earlier_one(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    for name in ("best.pt", "log.jsonl"):
        (run_dir / name).write_text("an earlier run's")
    data = ["train", "--data", str(tmp_path / "missing"), "--out", str(run_dir)]
    assert main(data) == 2
    assert_one_line(capsys.readouterr().err, "dmlo train: error:", "holds the files of an earlier run (best.pt, log.jsonl)")
    assert main([*data, "--overwrite", "--init", str(run_dir / "best.pt")]) == 2
    assert_one_line(capsys.readouterr().err, "--init", "would delete")
    assert main([*data, "--resume"]) == 2  # past the folder check: the data are missing
    assert "sequence folder not found" in capsys.readouterr().err
    assert sorted(p.name for p in run_dir.iterdir()) == ["best.pt", "log.jsonl"]
