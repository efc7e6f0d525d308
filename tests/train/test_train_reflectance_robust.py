"""The reflectance augmentations of the reflectance-robust stage: a random monotone calibration curve, a fade
with range and dark cells, as a real sensor's reflectance differs from the simulator's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dmlo.train import default_recipe
from dmlo.train.config import TrainConfig
from dmlo.train.dataset import (
    Augmentation,
    fade_reflectance_with_range,
    remap_reflectance,
    zero_reflectance_cells,
)

HEIGHT, WIDTH = 16, 256


def sample() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(5)
    scans = {
        key: np.stack((rng.uniform(2.0, 80.0, (HEIGHT, WIDTH)), rng.uniform(0.0, 1.0, (HEIGHT, WIDTH)))).astype(np.float32)
        for key in ("ref", "tgt")
    }
    scans["ref"][:, :8] = 0.0  # empty cells: range and reflectance 0
    flow = rng.normal(0.0, 3.0, (2, HEIGHT, WIDTH)).astype(np.float32)
    return {**scans, "flow": flow, "valid": rng.random((HEIGHT, WIDTH)) < 0.8}


def assert_geometry_kept(changed: dict[str, np.ndarray], original: dict[str, np.ndarray]) -> None:
    for key in ("ref", "tgt"):
        np.testing.assert_array_equal(changed[key][0], original[key][0])
        assert changed[key][1].min() >= 0.0 and changed[key][1].max() <= 1.0
    np.testing.assert_array_equal(changed["flow"], original["flow"])
    np.testing.assert_array_equal(changed["valid"], original["valid"])
    np.testing.assert_array_equal(original["ref"], sample()["ref"])  # the input is not changed


@pytest.mark.parametrize("seed", range(5))
def test_remap_is_one_monotone_curve_for_both_scans_in_steps_of_a_hundredth(seed: int) -> None:
    original = sample()
    remapped = remap_reflectance(original, np.random.default_rng(seed))
    assert_geometry_kept(remapped, original)
    before = np.concatenate([original[key][1].ravel() for key in ("ref", "tgt")])
    after = np.concatenate([remapped[key][1].ravel() for key in ("ref", "tgt")])
    order = np.argsort(before, kind="stable")
    assert np.all(np.diff(after[order]) >= 0)  # brighter stays at least as bright, across both scans: one curve
    np.testing.assert_allclose(after * 100, np.round(after * 100), atol=1e-4)  # KITTI's 0.01 steps
    assert np.all(after[before == 0] == 0)  # empty returns stay dark
    assert not np.allclose(after, np.round(before * 100) / 100, atol=0.02)  # a curve, not the identity


def test_falloff_fades_each_cell_by_its_own_range() -> None:
    original = sample()
    faded = fade_reflectance_with_range(original, np.random.default_rng(3))
    assert_geometry_kept(faded, original)
    for key in ("ref", "tgt"):
        distance, before, after = original[key][0], original[key][1], faded[key][1]
        assert np.all(after <= before + 1e-7)
        np.testing.assert_array_equal(after[distance < 15.0], before[distance < 15.0])  # near: untouched
        assert np.all(after[distance > 75.0] == 0)  # beyond the fade: dark
        lit = before > 0.05
        factor = after[lit] / before[lit]
        by_range = np.argsort(distance[lit])
        assert np.all(np.diff(factor[by_range]) <= 1e-5)  # the farther, the dimmer


def test_zeros_darken_cells_apart_in_the_two_scans_and_keep_their_range() -> None:
    original = sample()
    zeroed = zero_reflectance_cells(original, 0.3, np.random.default_rng(2))
    assert_geometry_kept(zeroed, original)
    dark = {key: (zeroed[key][1] == 0) & (original[key][1] > 0) for key in ("ref", "tgt")}
    for key in ("ref", "tgt"):
        assert dark[key].mean() <= 0.3 + 0.02
        kept = ~dark[key]
        np.testing.assert_array_equal(zeroed[key][1][kept], original[key][1][kept])
    assert not np.array_equal(dark["ref"], dark["tgt"])


def test_augmentation_applies_them_by_their_shares_and_leaves_runs_without_them_unchanged() -> None:
    plain = Augmentation(crop_width=128, mirror=True, laser_gain_spread=0.5, reflectance_dropout=0.3)
    robust = Augmentation(crop_width=128, mirror=True, laser_gain_spread=0.5, reflectance_dropout=0.3,
                          reflectance_remap=1.0, reflectance_falloff=1.0, reflectance_zeros=0.1)
    for seed in range(10):
        a = plain(sample(), np.random.default_rng(seed))
        b = robust(sample(), np.random.default_rng(seed))
        for key in ("ref", "tgt"):
            np.testing.assert_array_equal(a[key][0], b[key][0])  # the same roll, mirror and crop
        np.testing.assert_array_equal(a["flow"], b["flow"])
        np.testing.assert_array_equal(a["valid"], b["valid"])
    remapped = Augmentation(yaw_roll=False, reflectance_remap=0.5)
    stepped = [np.allclose(remapped(sample(), np.random.default_rng(s))["ref"][1] * 100,
                           np.round(remapped(sample(), np.random.default_rng(s))["ref"][1] * 100), atol=1e-4)
               for s in range(100)]
    assert 0.3 < np.mean(stepped) < 0.7
    validation = Augmentation(reflectance_remap=1.0, reflectance_falloff=1.0, reflectance_zeros=0.5, random=False)
    np.testing.assert_array_equal(validation(sample(), np.random.default_rng(0))["ref"], sample()["ref"])
    for name in ("reflectance_remap", "reflectance_falloff", "reflectance_zeros"):
        with pytest.raises(ValueError, match=name):
            Augmentation(**{name: 1.5})


def test_train_config_records_them_and_builds_the_augmentation() -> None:
    config = TrainConfig(crop_width=448, mirror=True, **default_recipe.REFLECTANCE_ROBUST_AUGMENTATION)
    assert TrainConfig.from_dict(config.to_dict()) == config
    augmentation = config.augmentation()
    assert augmentation.crop_width == 448 and augmentation.mirror
    for name, value in default_recipe.REFLECTANCE_ROBUST_AUGMENTATION.items():
        assert getattr(augmentation, name) == value


def test_the_stage_fine_tunes_the_bundled_weights_with_the_augmentations(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    calls: list[tuple[list[str], dict[str, object]]] = []
    monkeypatch.setattr(default_recipe, "simulate_drives", lambda data, poses: ([tmp_path / "t"], [tmp_path / "v"]))
    import dmlo.train.__main__ as train_entry

    monkeypatch.setattr(train_entry, "main", lambda argv, options=None: calls.append((argv, options)) or 0)
    out = tmp_path / "run"
    assert default_recipe.main(["--data", str(tmp_path), "--out", str(out), "--reflectance-robust", "--device", "cpu"]) == 0
    ((argv, options),) = calls
    assert argv[argv.index("--out") + 1] == str(out / "reflectance_robust")
    assert argv[argv.index("--init") + 1] == str(default_recipe.BUNDLED_FINAL)
    assert "--resume" in argv and argv[argv.index("--device") + 1] == "cpu"
    assert argv[argv.index("--crop-width") + 1] == "448"
    assert options == default_recipe.REFLECTANCE_ROBUST_AUGMENTATION
    with pytest.raises(SystemExit):
        default_recipe.main(["--data", str(tmp_path), "--out", str(out), "--reflectance-robust", "--range-only"])


STATE = Path(default_recipe.__file__).resolve().parents[1] / "models" / "default" / "training" / "reflectance_robust"


@pytest.mark.skipif(not (STATE / "train.json").is_file(), reason="no reflectance-robust state committed")
def test_committed_reflectance_robust_state_was_made_by_the_recipe() -> None:
    import json

    config = TrainConfig.from_dict(json.loads((STATE / "train.json").read_text()))
    arguments = default_recipe.REFLECTANCE_ROBUST_ARGUMENTS
    for name, value in default_recipe.REFLECTANCE_ROBUST_AUGMENTATION.items():
        assert getattr(config, name) == value
    assert config.laser_gain_spread == float(arguments[arguments.index("--laser-gain-spread") + 1])
    assert config.reflectance_dropout == float(arguments[arguments.index("--reflectance-dropout") + 1])
    assert config.crop_width == int(arguments[arguments.index("--crop-width") + 1]) and config.mirror
    assert config.lr == float(arguments[arguments.index("--lr") + 1])
    assert config.init is not None and config.init.endswith("finetune/best.pt")
    assert not config.no_reflectance


def test_the_pose_stage_trains_whole_images_from_the_crop_stage_with_the_same_augmentations(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    calls: list[tuple[list[str], dict[str, object]]] = []
    monkeypatch.setattr(default_recipe, "simulate_drives", lambda data, poses: ([tmp_path / "t"], [tmp_path / "v"]))
    import dmlo.train.__main__ as train_entry

    monkeypatch.setattr(train_entry, "main", lambda argv, options=None: calls.append((argv, options)) or 0)
    out = tmp_path / "run"
    with pytest.raises(SystemExit):  # the crop stage has not run
        default_recipe.main(["--data", str(tmp_path), "--out", str(out), "--reflectance-robust-pose"])
    (out / "reflectance_robust").mkdir(parents=True)
    (out / "reflectance_robust" / "best.pt").write_bytes(b"")
    assert default_recipe.main(["--data", str(tmp_path), "--out", str(out), "--reflectance-robust-pose"]) == 0
    ((argv, options),) = calls
    assert argv[argv.index("--out") + 1] == str(out / "reflectance_robust_pose")
    assert argv[argv.index("--init") + 1] == str(out / "reflectance_robust" / "best.pt")
    assert argv[argv.index("--crop-width") + 1] == "0" and float(argv[argv.index("--pose-loss-weight") + 1]) > 0
    assert "--resume" in argv and "--device" not in argv
    assert options == default_recipe.REFLECTANCE_ROBUST_AUGMENTATION


@pytest.mark.skipif(not (STATE.parent / "reflectance_robust_pose" / "train.json").is_file(),
                    reason="no reflectance-robust pose state committed")
def test_committed_reflectance_robust_pose_state_was_made_by_the_recipe() -> None:
    import json

    config = TrainConfig.from_dict(json.loads((STATE.parent / "reflectance_robust_pose" / "train.json").read_text()))
    arguments = default_recipe.REFLECTANCE_ROBUST_POSE_ARGUMENTS
    for name, value in default_recipe.REFLECTANCE_ROBUST_AUGMENTATION.items():
        assert getattr(config, name) == value
    assert config.pose_loss_weight == float(arguments[arguments.index("--pose-loss-weight") + 1])
    assert config.crop_width is None and config.val_width is None  # "--crop-width 0": the whole image
    assert config.init is not None and Path(config.init).parent.name == "reflectance_robust"


class _Stop(Exception):
    """Raised by the stubbed data set: the training command got as far as building its augmentation."""


def test_dmlo_train_takes_the_three_reflectance_augmentations_on_its_command_line(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from dmlo.cli import main
    from dmlo.train import PairDataset

    seen: list[Augmentation] = []

    def from_paths(*args: object, augmentation: Augmentation, **kwargs: object) -> None:
        seen.append(augmentation)
        raise _Stop

    monkeypatch.setattr(PairDataset, "from_paths", from_paths)
    (tmp_path / "train").mkdir()
    base = ["train", "--data", str(tmp_path / "train"), "--out", str(tmp_path / "run")]
    with pytest.raises(_Stop):
        main([*base, "--reflectance-remap", "0.75", "--reflectance-falloff", "0.5", "--reflectance-zeros", "0.15"])
    with pytest.raises(_Stop):
        main(base)
    tuned, plain = seen
    assert (tuned.reflectance_remap, tuned.reflectance_falloff, tuned.reflectance_zeros) == (0.75, 0.5, 0.15)
    assert (plain.reflectance_remap, plain.reflectance_falloff, plain.reflectance_zeros) == (0.0, 0.0, 0.0)
    assert main([*base, "--reflectance-zeros", "1.5"]) == 2  # out of [0, 1]: a user error, no training
    with pytest.raises(SystemExit):
        main([*base, "--reflectance-remap", "x"])
