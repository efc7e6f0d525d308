"""Training end to end on a simulated KITTI-layout sequence: dmlo_rs ground truth, `dmlo train`, resume."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
dmlo_rs = pytest.importorskip("dmlo_rs")
if not hasattr(dmlo_rs, "ground_truth_flow"):
    pytest.skip("dmlo_rs without ground_truth_flow", allow_module_level=True)
simulator = pytest.importorskip("dmlo.simulator")

from dmlo.cli import main as dmlo_main  # noqa: E402
from dmlo.train import Augmentation, PairDataset  # noqa: E402


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "00"
    simulator.simulate_sequence(out, 4, 7, progress=False)
    return out


@pytest.mark.slow
def test_pair_dataset_on_simulated_sequence(simulated) -> None:
    dataset = PairDataset.from_paths([simulated], augmentation=Augmentation(None, 448), seed=1)
    assert len(dataset) == 5  # (0,1) (0,2) (1,2) (1,3) (2,3)
    raw = dataset.raw_sample(0)
    assert raw["ref"].shape == (2, 64, 1792) and raw["flow"].dtype == np.float32 and raw["valid"].dtype == bool
    assert raw["valid"].mean() > 0.2
    # Ground truth lands on target cells whose range is close to the reference's (a short forward motion).
    rows, cols = np.nonzero(raw["valid"])
    target_rows = np.clip(np.round(rows + raw["flow"][0, rows, cols]).astype(int), 0, 63)
    target_cols = np.clip(np.round(cols + raw["flow"][1, rows, cols]).astype(int), 0, 1791)
    difference = np.abs(raw["tgt"][0, target_rows, target_cols] - raw["ref"][0, rows, cols])
    assert np.median(difference) < 1.0
    item = dataset[0]
    assert item["ref"].shape == (2, 64, 448) and item["valid"].shape == (64, 448)


@pytest.mark.slow
def test_train_command_runs_and_resumes(simulated, tmp_path) -> None:
    run = tmp_path / "run"
    common = ["train", "--data", str(simulated), "--val", str(simulated), "--out", str(run), "--crop-width", "64",
              "--batch-size", "1", "--preset", "fast", "--val-max-pairs", "1", "--val-width", "64", "--no-progress",
              "--confidence-loss-weight", "0.25"]
    assert dmlo_main([*common, "--epochs", "1", "--max-steps", "2"]) == 0
    assert not (run / "log.jsonl").exists()
    assert dmlo_main([*common, "--epochs", "1", "--resume", "--workers", "1"]) == 0  # a loader process
    row = json.loads((run / "log.jsonl").read_text().splitlines()[-1])
    assert row["epoch"] == 1 and row["step"] == 5 and np.isfinite(row["val_epe"])
    assert (run / "best.pt").is_file()
    assert json.loads((run / "train.json").read_text())["confidence_loss_weight"] == 0.25
