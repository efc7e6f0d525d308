"""The sensor-variety augmentations: per-laser reflectance gains, partly empty rows and scans without their
reflectance, as on real sensors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dmlo.train import default_recipe
from dmlo.train.config import TrainConfig
from dmlo.train.dataset import Augmentation, drop_row_cells, scale_row_reflectance, without_reflectance

HEIGHT, WIDTH = 16, 256


def sample() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(5)
    scans = {
        key: np.stack((rng.uniform(2.0, 60.0, (HEIGHT, WIDTH)), rng.uniform(0.0, 0.9, (HEIGHT, WIDTH)))).astype(np.float32)
        for key in ("ref", "tgt")
    }
    flow = rng.normal(0.0, 3.0, (2, HEIGHT, WIDTH)).astype(np.float32)
    return {**scans, "flow": flow, "valid": rng.random((HEIGHT, WIDTH)) < 0.8}


def test_gains_scale_each_row_alike_in_both_scans_and_leave_range_and_flow() -> None:
    original = sample()
    scaled = scale_row_reflectance(original, 0.5, np.random.default_rng(0))
    for key in ("ref", "tgt"):
        np.testing.assert_array_equal(scaled[key][0], original[key][0])
        assert scaled[key][1].min() >= 0.0 and scaled[key][1].max() <= 1.0
    unclipped = (scaled["ref"][1] < 1.0) & (scaled["tgt"][1] < 1.0)
    ref_gain = scaled["ref"][1] / original["ref"][1]
    tgt_gain = scaled["tgt"][1] / original["tgt"][1]
    np.testing.assert_allclose(ref_gain[unclipped], tgt_gain[unclipped], rtol=1e-5)  # one sensor: one gain a laser
    row_gains = [np.unique(np.round(ref_gain[row][unclipped[row]], 4)) for row in range(HEIGHT)]
    assert all(len(gains) == 1 and 0.5 <= gains[0] <= 1.5 for gains in row_gains)
    assert len({float(gains[0]) for gains in row_gains}) == HEIGHT  # each laser its own gain
    np.testing.assert_array_equal(scaled["flow"], original["flow"])
    np.testing.assert_array_equal(scaled["valid"], original["valid"])
    np.testing.assert_array_equal(original["ref"], sample()["ref"])  # the input is not changed


def test_dropout_empties_cells_row_by_row_apart_in_the_two_scans_and_drops_their_ground_truth() -> None:
    original = sample()
    dropped = drop_row_cells(original, 0.4, np.random.default_rng(1))
    emptied = {key: (dropped[key][0] == 0) & (original[key][0] > 0) for key in ("ref", "tgt")}
    for key in ("ref", "tgt"):
        assert np.all(dropped[key][1][emptied[key]] == 0)  # empty as the projection leaves a cell: both channels 0
        kept = ~emptied[key]
        np.testing.assert_array_equal(dropped[key][:, kept], original[key][:, kept])
        assert np.all(emptied[key].mean(axis=1) <= 0.4 + 4 * np.sqrt(0.25 / WIDTH))
        assert emptied[key].mean() > 0.05
    assert not np.array_equal(emptied["ref"], emptied["tgt"])
    np.testing.assert_array_equal(dropped["valid"], original["valid"] & ~emptied["ref"])
    np.testing.assert_array_equal(dropped["flow"], original["flow"])


def test_reflectance_dropout_zeroes_both_scans_reflectance_in_its_share_of_the_pairs() -> None:
    original = sample()
    zeroed = without_reflectance(original)
    for key in ("ref", "tgt"):
        assert not zeroed[key][1].any()
        np.testing.assert_array_equal(zeroed[key][0], original[key][0])
    np.testing.assert_array_equal(zeroed["flow"], original["flow"])
    assert original["ref"][1].any()  # the input is not changed
    half = Augmentation(yaw_roll=False, reflectance_dropout=0.5)
    without = [not half(sample(), np.random.default_rng(seed))["ref"][1].any() for seed in range(200)]
    assert 0.35 < np.mean(without) < 0.65
    assert all(not Augmentation(yaw_roll=False, reflectance_dropout=1.0)(sample(), np.random.default_rng(s))["tgt"][1].any()
               for s in range(5))
    assert Augmentation(reflectance_dropout=1.0, random=False)(sample(), np.random.default_rng(0))["ref"][1].any()
    config = TrainConfig(reflectance_dropout=0.5)
    assert TrainConfig.from_dict(config.to_dict()) == config
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="reflectance_dropout"):
            Augmentation(reflectance_dropout=bad)


def test_the_augmentations_are_drawn_after_the_crop_so_runs_without_them_are_unchanged() -> None:
    plain = Augmentation(crop_width=128, mirror=True)
    varied = Augmentation(crop_width=128, mirror=True, laser_gain_spread=0.6, row_dropout=0.4, reflectance_dropout=0.5)
    for seed in range(6):
        a, b = plain(sample(), np.random.default_rng(seed)), varied(sample(), np.random.default_rng(seed))
        np.testing.assert_array_equal(a["flow"], b["flow"])  # the same roll, mirror and crop
        np.testing.assert_array_equal(a["ref"][0][b["ref"][0] > 0], b["ref"][0][b["ref"][0] > 0])
    validation = Augmentation(crop_width=128, laser_gain_spread=0.6, row_dropout=0.4, random=False)
    np.testing.assert_array_equal(validation(sample(), np.random.default_rng(0))["ref"], plain.__class__(
        crop_width=128, random=False)(sample(), np.random.default_rng(0))["ref"])
    for bad in ({"laser_gain_spread": -0.1}, {"laser_gain_spread": 1.0}, {"row_dropout": 1.0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            Augmentation(**bad)


def test_the_training_command_records_the_augmentations(tmp_path: Path) -> None:
    from dmlo.cli import main

    config = TrainConfig(laser_gain_spread=0.6, row_dropout=0.4)
    assert TrainConfig.from_dict(config.to_dict()) == config
    with pytest.raises(SystemExit):
        main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--laser-gain-spread", "x"])


def recipe_training_command(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, stage: str) -> list[str]:
    """The training command `default_recipe` runs for `stage` (its drives and the training stubbed out)."""
    calls: list[list[str]] = []
    monkeypatch.setattr(default_recipe, "simulate_drives", lambda data, poses: ([tmp_path / "t"], [tmp_path / "v"]))
    import dmlo.train.__main__ as train_entry

    monkeypatch.setattr(train_entry, "main", lambda argv: calls.append(list(argv)) or 0)
    assert default_recipe.main(["--data", str(tmp_path), "--out", str(tmp_path / "run"), stage]) == 0
    (argv,) = calls
    return argv


def test_the_recipe_fine_tunes_the_bundled_final_weights_with_sensor_variety(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    argv = recipe_training_command(monkeypatch, tmp_path, "--sensor-variety")
    assert argv[argv.index("--init") + 1] == str(default_recipe.BUNDLED_FINAL)
    assert argv[argv.index("--out") + 1] == str(tmp_path / "run" / "sensor_variety")
    assert float(argv[argv.index("--laser-gain-spread") + 1]) > 0 and float(argv[argv.index("--row-dropout") + 1]) > 0
    with pytest.raises(SystemExit):
        default_recipe.main(["--data", str(tmp_path), "--out", str(tmp_path / "run"), "--sensor-variety", "--range-only"])


def test_the_pose_stage_with_sensor_variety_trains_whole_images_with_the_pose_loss(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    argv = recipe_training_command(monkeypatch, tmp_path, "--sensor-variety-pose")
    run = tmp_path / "run"
    assert argv[argv.index("--init") + 1] == str(default_recipe.BUNDLED_FINAL)
    assert argv[argv.index("--out") + 1] == str(run / "sensor_variety_pose")
    assert argv[argv.index("--crop-width") + 1] == "0"  # whole images, as the bundled model's last stage
    assert float(argv[argv.index("--pose-loss-weight") + 1]) > 0
    assert float(argv[argv.index("--laser-gain-spread") + 1]) > 0 and float(argv[argv.index("--row-dropout") + 1]) > 0
    with pytest.raises(SystemExit):
        default_recipe.main(["--data", str(tmp_path), "--out", str(run), "--sensor-variety-pose", "--finetune"])
    with pytest.raises(SystemExit):
        default_recipe.main(["--data", str(tmp_path), "--out", str(run), "--sensor-variety-pose", "--init", str(tmp_path / "none.pt")])


def test_the_range_only_pose_stage_starts_from_the_range_only_weights(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    argv = recipe_training_command(monkeypatch, tmp_path, "--range-only-pose")
    assert argv[argv.index("--init") + 1] == str(default_recipe.BUNDLED_RANGE_ONLY)
    assert default_recipe.BUNDLED_RANGE_ONLY.is_file()
    assert argv[argv.index("--out") + 1] == str(tmp_path / "run" / "range_only_pose")
    assert "--no-reflectance" in argv and argv[argv.index("--crop-width") + 1] == "0"
    assert float(argv[argv.index("--pose-loss-weight") + 1]) > 0
