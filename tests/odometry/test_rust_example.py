"""The Rust example `examples/odometry.rs` (the crate's odometry over onnxruntime loaded by `ort`, no Python)
gives `dmlo run`'s poses on a simulated drive and on every shared real set, on the same machine in the same run,
with the config `dmlo run` wrote (issue 24: 1e-6 m / 1e-6 rad), the moving-object network run by both (or by
neither, with `--keep-moving`). Both read the bare `.bin` folders, so neither has the sets' labels.

The example binary is the one `cargo test --release --features inference,onnxruntime` builds (CI builds it
before pytest); the test skips when it is missing or older than the crate's sources. The crate's own test
(`src/inference/tests.rs`) holds the same runs against poses recorded on another machine
(`odometry_poses.json`), to the tolerance onnxruntime's kernels allow between processors."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dmlo.odometry.matcher import onnxruntime_library
from support import REPO, rust_example

MODEL = REPO / "python/dmlo/models/default"


def _poses(path: Path) -> np.ndarray:
    return np.loadtxt(path, ndmin=2).reshape(-1, 3, 4)


def _dmlo_run_and_example(
    scans: Path, out: Path, mapping: bool, keep_moving: bool = False, encode_ahead: bool = False
) -> tuple[np.ndarray, np.ndarray, str]:
    """The poses of `dmlo run` and of the example over the `.bin` folder `scans`, with the config `dmlo run`
    wrote, and what the example wrote to stderr. `keep_moving`: neither runs the moving-object network;
    `encode_ahead`: the example encodes each scan while the one before it is registered."""
    from dmlo.cli import main

    example = rust_example("odometry")
    python_out, rust_out = out / "dmlo_run", out / "rust"
    assert main(["run", str(scans), "--out", str(python_out), "--mapping" if mapping else "--no-mapping"]
                + (["--keep-moving"] if keep_moving else [])) == 0
    finished = subprocess.run(
        [str(example), str(scans), "--out", str(rust_out), "--model", str(MODEL),
         "--config", str(python_out / "config.json"), "--onnxruntime", str(onnxruntime_library())]
        + (["--encode-ahead"] if encode_ahead else []),
        check=True, capture_output=True, text=True,
    )
    assert f"{len(list(scans.glob('*.bin')))} scans" in finished.stdout, finished.stdout
    flagged = [[json.loads(line)["num_moving_predicted"] for line in (folder / "diagnostics.jsonl").open()]
               for folder in (python_out, rust_out)]
    assert flagged[0] == flagged[1]
    assert all(count is None for count in flagged[0]) if keep_moving else all(count > 0 for count in flagged[0])
    return _poses(python_out / "poses_kitti.txt"), _poses(rust_out / "poses_kitti.txt"), finished.stderr


def _assert_same_poses(expected: np.ndarray, got: np.ndarray) -> None:
    """Within 1e-6 m and 1e-6 rad, pose by pose; the drive moves (equal poses are not the identity repeated)."""
    assert got.shape == expected.shape
    assert np.linalg.norm(expected[-1, :, 3]) > 1.0
    np.testing.assert_allclose(got[:, :, 3], expected[:, :, 3], rtol=0, atol=1e-6)
    turns = Rotation.from_matrix(np.einsum("nji,njk->nik", expected[:, :, :3], got[:, :, :3])).magnitude()
    assert turns.max() <= 1e-6, turns


@pytest.mark.parametrize("mapping", [True, False], ids=["mapping", "frame_to_frame"])
def test_the_rust_example_gives_dmlo_runs_poses_on_a_simulated_drive(drive: Path, tmp_path: Path,
                                                                      mapping: bool) -> None:
    expected, got, _ = _dmlo_run_and_example(drive / "velodyne", tmp_path, mapping)
    assert got.shape == (5, 3, 4)
    _assert_same_poses(expected, got)


# The moving-object network run by both, each scan encoded in turn and (the example) flagged and encoded ahead,
# and kept out of both, encoded ahead.
MODES = {"moving_network": (False, False), "moving_network_ahead": (False, True), "keep_moving_ahead": (True, True)}


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("mapping", [True, False], ids=["mapping", "frame_to_frame"])
@pytest.mark.parametrize("name", ["odometry_01", "odometry_02", "odometry_03", "raw_drive_22"])
def test_the_rust_example_gives_dmlo_runs_poses_on_real_scans(shared_data: Path, tmp_path: Path, name: str,
                                                              mapping: bool, mode: str) -> None:
    keep_moving, encode_ahead = MODES[mode]
    scans = shared_data / "kitti_real" / name / "velodyne"
    expected, got, _ = _dmlo_run_and_example(scans, tmp_path, mapping, keep_moving, encode_ahead)
    _assert_same_poses(expected, got)


def test_the_rust_example_takes_the_forward_start_as_dmlo_run_does(shared_data: Path, tmp_path: Path) -> None:
    """Two scans of the simulated highway at 2.4 m a frame whose first pair, matched from the identity, reverses
    (an alias of the guard rails' posts; `test_start_at_speed.py`): both take a start's forward motion, and say
    so."""
    from dmlo.simulator import simulate_sequence

    simulate_sequence(tmp_path / "highway", frames=2, seed=32, scene="highway", start=150, laser_gain_spread=0.6,
                      progress=False, trajectory=shared_data / "kitti_gt_poses" / "01.txt")
    expected, got, stderr = _dmlo_run_and_example(tmp_path / "highway" / "velodyne", tmp_path, mapping=True,
                                                  keep_moving=True)
    _assert_same_poses(expected, got)
    assert expected[1, 0, 3] > 2.0  # forward, as far as the truth
    assert "the start driving forward was taken" in stderr, stderr
    rows = [json.loads(line) for line in (tmp_path / "rust" / "diagnostics.jsonl").open()]
    assert rows[1]["ambiguous_start"] is True and rows[1]["fallback"] == "forward_start"
