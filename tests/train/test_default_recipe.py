"""The bundled model's recipe: the training command of each stage, and the committed training state it made."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dmlo.train import default_recipe
from dmlo.train.config import TrainConfig

TRAINING_STATE = Path(default_recipe.__file__).resolve().parents[1] / "models" / "default" / "training"


@pytest.fixture
def captured(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> list[list[str]]:
    calls: list[list[str]] = []
    drives = ([tmp_path / "train_00"], [tmp_path / "val_07"])
    monkeypatch.setattr(default_recipe, "simulate_drives", lambda data, poses: drives)
    import dmlo.train.__main__ as train_entry

    monkeypatch.setattr(train_entry, "main", lambda argv: calls.append(list(argv)) or 0)
    return calls


def option(argv: list[str], name: str) -> str:
    return argv[argv.index(name) + 1]


def test_first_stage_trains_into_the_run_folder(captured: list[list[str]], tmp_path: Path) -> None:
    assert default_recipe.main(["--data", str(tmp_path), "--out", str(tmp_path / "run")]) == 0
    (argv,) = captured
    assert option(argv, "--out") == str(tmp_path / "run")
    assert "--init" not in argv and "--pose-loss-weight" not in argv
    assert option(argv, "--crop-width") == "448"


def test_finetune_starts_from_the_first_stages_best_checkpoint(captured: list[list[str]], tmp_path: Path) -> None:
    run = tmp_path / "run"
    with pytest.raises(SystemExit):
        default_recipe.main(["--data", str(tmp_path), "--out", str(run), "--finetune"])
    assert captured == []
    run.mkdir()
    (run / "best.pt").write_bytes(b"")
    assert default_recipe.main(["--data", str(tmp_path), "--out", str(run), "--finetune"]) == 0
    (argv,) = captured
    assert option(argv, "--init") == str(run / "best.pt")
    assert option(argv, "--out") == str(run / "finetune")
    assert float(option(argv, "--pose-loss-weight")) > 0 and option(argv, "--crop-width") == "0"


def test_range_only_fine_tunes_the_bundled_final_weights_without_reflectance(captured: list[list[str]], tmp_path: Path) -> None:
    run = tmp_path / "run"
    assert default_recipe.main(["--data", str(tmp_path), "--out", str(run), "--range-only"]) == 0
    (argv,) = captured
    assert option(argv, "--init") == str(default_recipe.BUNDLED_FINAL)
    assert default_recipe.BUNDLED_FINAL == TRAINING_STATE / "finetune" / "best.pt"
    assert option(argv, "--out") == str(run / "range_only")
    assert "--no-reflectance" in argv and "--resume" in argv


def test_range_only_refuses_a_missing_start_and_the_finetune_stage_beside_it(captured: list[list[str]], tmp_path: Path) -> None:
    for extra in (["--init", str(tmp_path / "missing.pt")], ["--finetune"]):
        with pytest.raises(SystemExit):
            default_recipe.main(["--data", str(tmp_path), "--out", str(tmp_path / "run"), "--range-only", *extra])
    assert captured == []


@pytest.mark.skipif(not (TRAINING_STATE / "finetune" / "train.json").is_file(), reason="no fine-tune state committed")
def test_committed_finetune_state_was_made_by_the_recipe() -> None:
    config = TrainConfig.from_dict(json.loads((TRAINING_STATE / "finetune" / "train.json").read_text()))
    arguments = default_recipe.FINETUNE_ARGUMENTS
    assert config.pose_loss_weight == float(option(arguments, "--pose-loss-weight"))
    assert config.crop_width is None and config.val_width is None  # "--crop-width 0": the whole image
    assert config.lr == float(option(arguments, "--lr")) and config.epochs == int(option(arguments, "--epochs"))
    assert config.batch_size == int(option(arguments, "--batch-size")) and config.mirror
    assert config.init is not None and Path(config.init).name == "best.pt"


@pytest.mark.skipif(not (TRAINING_STATE / "range_only" / "train.json").is_file(), reason="no range-only state committed")
def test_committed_range_only_state_was_made_by_the_recipe() -> None:
    config = TrainConfig.from_dict(json.loads((TRAINING_STATE / "range_only" / "train.json").read_text()))
    model = json.loads((TRAINING_STATE / "range_only" / "model.json").read_text())
    arguments = default_recipe.RANGE_ONLY_ARGUMENTS
    assert config.no_reflectance and model["use_reflectance"] is False
    assert config.init is not None and config.init.endswith("finetune/best.pt")
    assert config.crop_width == int(option(arguments, "--crop-width")) and config.mirror
    assert config.lr == float(option(arguments, "--lr")) and config.epochs == int(option(arguments, "--epochs"))
    assert config.batch_size == int(option(arguments, "--batch-size"))


@pytest.fixture
def scene_drives(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """One training and one held-out scene drive, not simulated."""
    scenes = ([tmp_path / "scenes_highway"], [tmp_path / "val_scenes_jam"])
    monkeypatch.setattr(default_recipe, "simulate_scene_drives", lambda data, poses: scenes)


@pytest.mark.usefixtures("scene_drives")
def test_scenes_stage_fine_tunes_on_the_recipes_drives_and_the_scene_drives(
    captured: list[list[str]], tmp_path: Path
) -> None:
    run = tmp_path / "run"
    assert default_recipe.main(["--data", str(tmp_path), "--out", str(run), "--scenes"]) == 0
    (argv,) = captured
    assert option(argv, "--init") == str(default_recipe.BUNDLED_FINAL)
    assert option(argv, "--out") == str(run / "scenes")
    data, val = argv[argv.index("--data") + 1 : argv.index("--val")], argv[argv.index("--val") + 1 : argv.index("--out")]
    assert data == [str(tmp_path / "train_00"), str(tmp_path / "scenes_highway")]
    assert val == [str(tmp_path / "val_07"), str(tmp_path / "val_scenes_jam")]
    assert option(argv, "--crop-width") == "448" and "--resume" in argv
    with pytest.raises(SystemExit):
        default_recipe.main(["--data", str(tmp_path), "--out", str(run), "--scenes", "--range-only"])


@pytest.mark.usefixtures("scene_drives")
def test_scenes_pose_stage_trains_whole_images_from_the_scenes_stage(
    captured: list[list[str]], tmp_path: Path
) -> None:
    run = tmp_path / "run"
    with pytest.raises(SystemExit):  # the scenes stage has not run: nothing to start from
        default_recipe.main(["--data", str(tmp_path), "--out", str(run), "--scenes-pose"])
    assert captured == []
    (run / "scenes").mkdir(parents=True)
    (run / "scenes" / "best.pt").write_bytes(b"weights")
    assert default_recipe.main(["--data", str(tmp_path), "--out", str(run), "--scenes-pose"]) == 0
    (argv,) = captured
    assert option(argv, "--init") == str(run / "scenes" / "best.pt")
    assert option(argv, "--out") == str(run / "scenes_pose")
    data = argv[argv.index("--data") + 1 : argv.index("--val")]
    assert data == [str(tmp_path / "train_00"), str(tmp_path / "scenes_highway")]
    assert option(argv, "--crop-width") == "0" and float(option(argv, "--pose-loss-weight")) > 0


def test_scene_drives_cover_the_failing_scenes_and_stay_off_the_benchmarks_drives() -> None:
    options = [drive[5] for drive in default_recipe.SCENE_DRIVES if not drive[0].startswith("val")]
    assert any(o.get("scene") == "highway" and float(o.get("laser_gain_spread", 0)) >= 0.4 for o in options)  # type: ignore[arg-type]
    assert any(o.get("escorts") for o in options) and any(o.get("scene") == "stop-and-go" for o in options)
    seeds = [drive[3] for drive in default_recipe.SCENE_DRIVES]
    assert len(set(seeds)) == len(seeds) and not set(seeds) & {1, 2, 3, 31, 32, 33, 41, 42}
    for name, sequence, start, _, _, _ in default_recipe.SCENE_DRIVES:
        if sequence == "01":  # the odometry benchmark's highway drives KITTI 01's first 300 poses
            assert start >= 300, name
    names = [drive[0] for drive in (*default_recipe.DRIVES, *default_recipe.SCENE_DRIVES)]
    assert len(set(names)) == len(names)


def test_scene_drives_without_kitti_poses_keep_only_the_generated_routes(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import dmlo.simulator

    written: list[tuple[Path, dict[str, object]]] = []

    def simulate(out: Path, **kwargs: object) -> None:
        written.append((out, kwargs))
        out.mkdir(parents=True)
        (out / "poses.txt").write_text("")

    monkeypatch.setattr(dmlo.simulator, "simulate_sequence", simulate)
    train, val = default_recipe.simulate_scene_drives(tmp_path, None)
    generated = [d for d in default_recipe.SCENE_DRIVES if d[1] is None]
    assert [out.name for out, _ in written] == [d[0] for d in generated]
    assert all(kwargs["trajectory"] is None for _, kwargs in written)
    assert len(train) + len(val) == len(generated) and all(p.name.startswith("val") for p in val)
    written.clear()
    assert default_recipe.simulate_scene_drives(tmp_path, None) == (train, val)  # written once
    assert written == []


@pytest.fixture
def kitti_drives(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> tuple[list[Path], list[Path]]:
    drives = ([tmp_path / "kitti_reflectance" / "train_00"], [tmp_path / "kitti_reflectance" / "val_07"])
    monkeypatch.setattr(default_recipe, "simulate_kitti_reflectance_drives", lambda data, poses: drives)
    return drives


def test_kitti_reflectance_stage_trains_on_the_calibrated_drives(
    captured: list[list[str]], kitti_drives: tuple[list[Path], list[Path]], tmp_path: Path
) -> None:
    run = tmp_path / "run"
    assert default_recipe.main(["--data", str(tmp_path), "--out", str(run), "--kitti-reflectance"]) == 0
    (argv,) = captured
    assert option(argv, "--data") == str(kitti_drives[0][0]) and option(argv, "--val") == str(kitti_drives[1][0])
    assert option(argv, "--init") == str(default_recipe.BUNDLED_FINAL)
    assert option(argv, "--out") == str(run / "kitti_reflectance")
    assert option(argv, "--crop-width") == "448" and "--resume" in argv and "--no-reflectance" not in argv


def test_kitti_reflectance_pose_stage_starts_from_the_crop_stage(
    captured: list[list[str]], kitti_drives: tuple[list[Path], list[Path]], tmp_path: Path
) -> None:
    run = tmp_path / "run"
    with pytest.raises(SystemExit):  # no crop stage yet
        default_recipe.main(["--data", str(tmp_path), "--out", str(run), "--kitti-reflectance-pose"])
    (run / "kitti_reflectance").mkdir(parents=True)
    (run / "kitti_reflectance" / "best.pt").write_bytes(b"")
    assert default_recipe.main(["--data", str(tmp_path), "--out", str(run), "--kitti-reflectance-pose"]) == 0
    (argv,) = captured
    assert option(argv, "--init") == str(run / "kitti_reflectance" / "best.pt")
    assert option(argv, "--out") == str(run / "kitti_reflectance_pose")
    assert option(argv, "--crop-width") == "0" and float(option(argv, "--pose-loss-weight")) > 0
    with pytest.raises(SystemExit):
        default_recipe.main(["--data", str(tmp_path), "--out", str(run), "--kitti-reflectance", "--range-only"])


def test_kitti_reflectance_drives_are_the_recipes_drives_with_the_calibrated_reflectance(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import dmlo.simulator

    calls: list[tuple[Path, dict[str, object]]] = []
    monkeypatch.setattr(dmlo.simulator, "simulate_sequence", lambda out, **kw: calls.append((Path(out), kw)))
    train, val = default_recipe.simulate_kitti_reflectance_drives(tmp_path, None)
    assert [p.name for p in train + val] == sorted((d[0] for d in default_recipe.DRIVES), key=lambda n: n.startswith("val"))
    assert all(p.parent == tmp_path / "kitti_reflectance" for p in train + val)
    assert len(calls) == len(default_recipe.DRIVES) and all(kw["reflectance"] == "kitti" for _, kw in calls)
    seeds = {name: seed for name, _, seed, _, _ in default_recipe.DRIVES}
    assert all(kw["seed"] == seeds[out.name] for out, kw in calls)
    calls.clear()
    default_recipe.simulate_drives(tmp_path / "plain", None)
    assert calls and all("reflectance" not in kw for _, kw in calls)  # the recipe's own drives as before


@pytest.mark.skipif(not (TRAINING_STATE / "kitti_reflectance" / "train.json").is_file(),
                    reason="no kitti-reflectance state committed")
def test_committed_kitti_reflectance_state_was_made_by_the_recipe() -> None:
    config = TrainConfig.from_dict(json.loads((TRAINING_STATE / "kitti_reflectance" / "train.json").read_text()))
    arguments = default_recipe.KITTI_REFLECTANCE_ARGUMENTS
    assert config.laser_gain_spread == float(option(arguments, "--laser-gain-spread"))
    assert config.lr == float(option(arguments, "--lr")) and config.epochs == int(option(arguments, "--epochs"))
    assert config.crop_width == int(option(arguments, "--crop-width")) and config.mirror
    assert config.init is not None and config.init.endswith("finetune/best.pt")
    names = {name for name, *_ in default_recipe.DRIVES}
    assert all(Path(p).parent.name == default_recipe.KITTI_REFLECTANCE_DATA and Path(p).name in names
               for p in config.data + config.val)
    assert not config.no_reflectance and config.reflectance_remap == 0 and config.reflectance_dropout == 0
