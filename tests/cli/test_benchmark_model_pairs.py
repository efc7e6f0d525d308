"""`benchmarks/model_pairs.py`: frame-to-frame DMLO per model against a shared, cached reference, end to end on
a tiny simulated drive (its figures go into docs/measurements.md)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dmlo.simulator import simulate_sequence
from support import REPO


def test_models_share_one_cached_reference_and_the_reflectance_setting_is_passed(tmp_path: Path) -> None:
    pytest.importorskip("small_gicp")
    drive = tmp_path / "drive"
    simulate_sequence(drive, frames=3, seed=13, progress=False)
    out = tmp_path / "out"
    command = [sys.executable, str(REPO / "benchmarks" / "model_pairs.py"), "--model", "bundled=",
               "--model", "range-only=,reflectance=none", "--sets", str(drive), "--sim", "--out", str(out)]
    result = subprocess.run(command, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("| drive |")]
    assert [row.split(" | ")[1] for row in rows] == ["bundled", "range-only"]
    assert "range-only model runs" in result.stderr  # reflectance: "none" reached the odometry
    cached = np.load(out / "reference_drive.npz")
    assert cached["motions"].shape == (2, 4, 4)
    figures = json.loads((out / "model_pairs.json").read_text())["drive"]
    assert set(figures) == {"bundled", "range-only"} and all(f["t_mean_cm"] >= 0 for f in figures.values())
    again = subprocess.run(command[:4] + command[6:], capture_output=True, text=True)  # the bundled model alone
    assert again.returncode == 0, again.stderr
    rerun = json.loads((out / "model_pairs.json").read_text())["drive"]["bundled"]
    assert {k: v for k, v in rerun.items() if k != "hz"} == {k: v for k, v in figures["bundled"].items() if k != "hz"}
