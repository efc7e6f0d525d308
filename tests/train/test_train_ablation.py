"""The Table V driver: each variant changes exactly its ablated setting, and finished variants are kept."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import pytest

from dmlo.commands.train import add_arguments, model_config_from_args
from dmlo.train import ablation


def _config(name: str) -> Any:
    import argparse

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    options = [*ablation.BASE_ARGUMENTS, *ablation.VARIANTS[name][1]]
    return model_config_from_args(parser.parse_args(["--data", "x", "--out", "y", *options]))


@pytest.mark.parametrize(
    ("name", "changed"),
    [
        ("no_norm", {"normalize_features": False}),
        ("one_hot", {"subpixel_loss": False}),
    ],
)
def test_loss_and_normalisation_ablations_change_one_setting(name: str, changed: dict[str, Any]) -> None:
    assert _config(name) == dataclasses.replace(_config("fast"), **changed)


def test_refine_variants_differ_in_the_refine_stage_only() -> None:
    base = _config("fast")
    assert base.refine_deformable_layers == 0 and base.normalize_features and base.subpixel_loss
    for name in ("light", "paper"):
        config = _config(name)
        assert config.refine_deformable_layers > 0
        assert config.coarse_window == base.coarse_window == 15
        assert (config.normalize_features, config.subpixel_loss) == (True, True)


def test_finished_variants_are_skipped_and_rows_collected(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    measured = {"epe": 9.0, "fl_all": 60.0, "kept_epe": 4.0, "kept_fl_all": 20.0, "rotation_deg": 0.1,
                "translation_m": 0.012, "network_ms": 60.0, "pair_ms": 65.0}
    done = {"fast": {"change": "x", "epochs": 1, "steps": 519, "val_epe": 10.0, "val_fl_all": 65.0, **measured}}
    (tmp_path / "ablation.json").write_text(json.dumps(done))
    trained: list[str] = []

    def train(name: str, train: list[Path], val: list[Path], run: Path, epochs: int) -> None:
        trained.append(name)
        run.mkdir(parents=True)
        (run / "log.jsonl").write_text(json.dumps({"epoch": 1, "step": 519, "val_epe": 11.5, "val_fl_all": 70.0}) + "\n")

    monkeypatch.setattr(ablation, "simulate_drives", lambda data, poses: ([tmp_path], [tmp_path]))
    monkeypatch.setattr(ablation, "train_variant", train)
    monkeypatch.setattr(ablation, "export_variant", lambda run: run)
    monkeypatch.setattr("dmlo.metrics.matching.evaluate", lambda model, drives, pairs: measured)
    assert ablation.main(["--data", str(tmp_path), "--out", str(tmp_path), "--variants", "fast", "no_norm"]) == 0
    assert trained == ["no_norm"]
    results = json.loads((tmp_path / "ablation.json").read_text())
    assert results["no_norm"]["val_epe"] == 11.5 and results["fast"]["val_epe"] == 10.0
    table = (tmp_path / "ablation.md").read_text().splitlines()
    assert table[2].startswith("| fast |") and table[3].startswith("| no_norm |") and "| 1.20 |" in table[3]
