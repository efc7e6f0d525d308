"""Training: pairs, honest augmentations, checkpoint/resume equivalence, the command line."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dmlo.cli import main as dmlo_main  # noqa: E402
from dmlo.model import MatcherConfig  # noqa: E402
from dmlo.train import ArrayPairDataset, Augmentation, PairDataset, TrainConfig, Trainer, load_model, pair_indices  # noqa: E402
from dmlo.train.checkpoint import load  # noqa: E402
from dmlo.train.dataset import crop, mirror_columns, roll_columns  # noqa: E402
from dmlo.train.metrics import FlowErrorSums  # noqa: E402

from test_model import synthetic_pair  # noqa: E402

TINY = MatcherConfig(coarse_channels=8, refine_channels=4, refine_plain_layers=1, refine_deformable_layers=1)


def sample(shift: tuple[int, int], seed: int = 0, height: int = 16, width: int = 64) -> dict[str, np.ndarray]:
    ref, tgt, flow, valid = synthetic_pair(height, width, shift, seed)
    return {"ref": ref[0].numpy(), "tgt": tgt[0].numpy(), "flow": flow[0].numpy(), "valid": valid[0].numpy()}


def assert_matches_are_honest(s: dict[str, np.ndarray]) -> None:
    """Every valid cell's target location (integer flows here) shows the reference cell's values."""
    rows, cols = np.nonzero(s["valid"])
    target_rows = rows + s["flow"][0, rows, cols].astype(int)
    target_cols = cols + s["flow"][1, rows, cols].astype(int)
    np.testing.assert_array_equal(s["tgt"][:, target_rows, target_cols], s["ref"][:, rows, cols])


def test_pair_indices_are_the_triplet_pairs() -> None:
    assert pair_indices(4) == [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)]
    assert pair_indices(3, max_gap=1) == [(0, 1), (1, 2)]
    assert pair_indices(1) == []


def test_roll_and_crop_keep_matches_honest_and_drop_leaving_targets() -> None:
    original = sample((2, 7), width=64)
    assert_matches_are_honest(original)
    rolled = roll_columns(original, 20)
    assert_matches_are_honest(rolled)
    # Cells within 7 columns of the seam lose their match; the rest keep it.
    assert not rolled["valid"][:, 13:20].any() and rolled["valid"][:10, 20:50].all()
    cut = crop(rolled, 0, 8, 16, 32)
    assert_matches_are_honest(cut)
    # The seam sits at local columns 5…11; targets beyond the crop's right edge leave it.
    assert not cut["valid"][:, 5:12].any() and not cut["valid"][:, 32 - 7 :].any()
    assert cut["valid"][:14, 12 : 32 - 7].all()
    with pytest.raises(ValueError, match="exceeds"):
        crop(original, 0, 40, 16, 32)


def test_mirror_keeps_every_match_honest_with_the_column_flow_negated() -> None:
    original = sample((2, 7), width=64)
    mirrored = mirror_columns(original)
    assert_matches_are_honest(mirrored)
    assert mirrored["valid"].sum() == original["valid"].sum()
    assert (mirrored["flow"][1][mirrored["valid"]] == -7).all() and (mirrored["flow"][0][mirrored["valid"]] == 2).all()
    twice = mirror_columns(mirrored)
    assert all(np.array_equal(twice[key], original[key]) for key in original)
    # Drawn only when asked for: about half of the samples, each one honest.
    flips = 0
    for k in range(40):
        augmented = Augmentation(mirror=True)(sample((1, 5), seed=k), np.random.default_rng(k))
        assert_matches_are_honest(augmented)
        flips += int((augmented["flow"][1][augmented["valid"]] < 0).all())
    assert 10 < flips < 30


def test_augmentation_is_seeded_and_validates_sizes() -> None:
    dataset = ArrayPairDataset([sample((1, -3), seed=k) for k in range(3)], Augmentation(8, 32), seed=5)
    a, b = dataset[1], dataset[1]
    assert all(np.array_equal(a[key], b[key]) for key in a)
    assert a["ref"].shape == (2, 8, 32) and a["valid"].shape == (8, 32)
    assert_matches_are_honest(a)
    dataset.set_epoch(1)
    assert not np.array_equal(dataset[1]["ref"], a["ref"])
    centred = Augmentation(None, 32, random=False)(sample((0, 0)), np.random.default_rng(0))
    np.testing.assert_array_equal(centred["ref"], sample((0, 0))["ref"][:, :, 16:48])
    with pytest.raises(ValueError, match="multiple of 8"):
        Augmentation(None, 30)
    with pytest.raises(ValueError, match="larger"):
        Augmentation(None, 128)(sample((0, 0)), np.random.default_rng(0))


class _Frame:
    def __init__(self, points: np.ndarray, pose: np.ndarray) -> None:
        self.points, self.pose = points, pose


class _Sequence(list):
    @property
    def poses(self) -> np.ndarray:
        return np.stack([frame.pose for frame in self])


class _RecordingGeometry:
    def __init__(self) -> None:
        self.motions: list[np.ndarray] = []

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.full((8, 16), float(points[0, 0]), np.float32), np.zeros((8, 16), np.float32)

    def ground_truth(self, ref_range, tgt_range, T_tgt_ref):  # type: ignore[no-untyped-def]
        self.motions.append(T_tgt_ref)
        return np.zeros((2, 8, 16), np.float32), np.ones((8, 16), bool)


def test_pair_dataset_uses_relative_motion_from_poses() -> None:
    rng = np.random.default_rng(0)
    poses = []
    for _ in range(3):
        angle = rng.uniform(-1, 1)
        pose = np.eye(4)
        pose[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
        pose[:3, 3] = rng.normal(size=3)
        poses.append(pose)
    frames = _Sequence(_Frame(np.full((5, 4), i, np.float32), poses[i]) for i in range(3))
    geometry = _RecordingGeometry()
    dataset = PairDataset([frames], geometry, Augmentation(yaw_roll=False))
    assert len(dataset) == 3 and dataset.pairs[1] == (0, 0, 2)
    item = dataset[1]
    assert item["ref"][0, 0, 0] == 0 and item["tgt"][0, 0, 0] == 2
    np.testing.assert_allclose(geometry.motions[-1], np.linalg.inv(poses[2]) @ poses[0], atol=1e-12)
    with pytest.raises(ValueError, match="no ground-truth poses"):
        PairDataset([_NoPoses()], geometry)


class _NoPoses(list):
    poses = None


def test_flow_error_sums_match_the_kitti_definition() -> None:
    gt = torch.tensor([[[10.0, 0.0, 100.0]], [[0.0, 0.0, 0.0]]]).unsqueeze(0)  # (1, 2, 1, 3)
    pred = gt + torch.tensor([[[2.0, 4.0, 4.0]], [[0.0, 0.0, 0.0]]]).unsqueeze(0)
    sums = FlowErrorSums()
    sums.add(pred, gt, torch.ones(1, 1, 3, dtype=torch.bool))
    # EPE 2 (not an outlier), 4 > 3 px and > 5 % of 0 (outlier), 4 > 3 px but < 5 % of 100 (not).
    assert sums.epe == pytest.approx(10 / 3) and sums.fl_all == pytest.approx(100 / 3)
    metrics = pytest.importorskip("dmlo.metrics")
    reference = metrics.flow_errors(pred[0].numpy(), gt[0].numpy(), np.ones((1, 3), bool))
    assert reference.epe == pytest.approx(sums.epe) and reference.fl_all == pytest.approx(sums.fl_all)


def tiny_run(tmp_path, **changes) -> TrainConfig:
    values = dict(out=str(tmp_path), epochs=2, batch_size=2, lr=1e-2, device="cpu", checkpoint_every=1, seed=3)
    values.update(changes)
    return TrainConfig(**values)


def tiny_data() -> ArrayPairDataset:
    shifts = [(1, 3), (-2, 5), (0, -6), (3, 1), (-1, -2), (2, 9)]
    return ArrayPairDataset([sample(s, seed=k, width=96) for k, s in enumerate(shifts)], Augmentation(None, 64))


def test_resume_continues_exactly_like_an_uninterrupted_run(tmp_path) -> None:
    whole = Trainer(TINY, tiny_run(tmp_path / "whole", max_steps=5), tiny_data(), progress=False)
    whole.run()
    first = Trainer(TINY, tiny_run(tmp_path / "cut", max_steps=2), tiny_data(), progress=False)
    first.run()
    state = load(tmp_path / "cut" / "last.pt")
    assert (state["epoch"], state["step_in_epoch"], state["global_step"]) == (0, 2, 2)
    assert not list((tmp_path / "cut").glob(".*tmp*"))
    # A fresh process: other global RNG use in between must not matter.
    torch.manual_seed(123)
    resumed = Trainer(TINY, tiny_run(tmp_path / "cut", max_steps=5), tiny_data(), resume=True, progress=False)
    assert resumed.global_step == 2
    resumed.run()
    assert resumed.global_step == whole.global_step == 5 and resumed.epoch == whole.epoch == 1
    for (name, a), (_, b) in zip(whole.model.state_dict().items(), resumed.model.state_dict().items(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0, msg=name)
    torch.testing.assert_close(
        whole.optimizer.state_dict()["state"][0]["momentum_buffer"],
        resumed.optimizer.state_dict()["state"][0]["momentum_buffer"], rtol=0, atol=0,
    )


def test_run_writes_configs_log_and_best_checkpoint(tmp_path) -> None:
    trainer = Trainer(TINY, tiny_run(tmp_path, epochs=2, lr_step_epochs=1), tiny_data(), val_set=tiny_data(), progress=False)
    row = trainer.run()
    assert MatcherConfig.load(tmp_path / "model.json") == TINY
    assert TrainConfig.from_dict(json.loads((tmp_path / "train.json").read_text())).epochs == 2
    rows = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [1, 2] and rows[-1] == row
    assert rows[1]["lr"] == pytest.approx(1e-2 * 0.01)  # ×0.1 per step of one epoch
    assert np.isfinite(row["val_epe"]) and 0 <= row["val_fl_all"] <= 100
    model = load_model(tmp_path / "best.pt")
    assert model.config == TINY


def test_trainer_rejects_too_little_data(tmp_path) -> None:
    with pytest.raises(ValueError, match="fewer than one batch"):
        Trainer(TINY, tiny_run(tmp_path, batch_size=8), tiny_data(), progress=False)


def test_command_line_errors_and_export(tmp_path, capsys) -> None:
    assert dmlo_main(["train", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "run")]) == 2
    assert "sequence folder not found" in capsys.readouterr().err
    assert dmlo_main(["export", str(tmp_path / "nothing.pt"), "--out", str(tmp_path / "onnx")]) == 2
    assert "checkpoint not found" in capsys.readouterr().err
    Trainer(TINY, tiny_run(tmp_path / "run", max_steps=1), tiny_data(), progress=False).run()
    code = dmlo_main(["export", str(tmp_path / "run"), "--out", str(tmp_path / "onnx"), "--height", "16", "--width", "64", "--graphs", "frame"])
    assert code == 0 and (tmp_path / "onnx" / "frame.onnx").is_file()
    assert dmlo_main(["export", str(tmp_path / "run"), "--out", str(tmp_path / "onnx"), "--height", "15"]) == 2
