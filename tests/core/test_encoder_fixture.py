"""The fixture of the crate's tract encoder test (`cargo test --features inference`) is what onnxruntime
computes today with the bundled encoder: when the model is exported again, the fixture must be too."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
ENCODER = Path(__file__).resolve().parents[2] / "python/dmlo/models/default/encoder.onnx"


def test_the_tract_encoder_fixture_matches_onnxruntime_today(shared_data: Path) -> None:
    spec = importlib.util.spec_from_file_location("make_encoder_features", FIXTURES / "make_encoder_features.py")
    assert spec is not None and spec.loader is not None
    maker = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(maker)
    fixture = json.loads((FIXTURES / "encoder_features.json").read_text())
    today = maker.features(shared_data, ENCODER)
    assert fixture["coarse_shape"] == today["coarse_shape"] == [32, 16, 224]
    assert fixture["refine_shape"] == today["refine_shape"] == [8, 64, 1792]
    for key in ("coarse", "refine"):
        np.testing.assert_allclose(fixture[key], today[key], atol=1e-5, err_msg=f"re-run {maker.__file__}")
        assert abs(fixture[f"{key}_sum"] - today[f"{key}_sum"]) < 1e-2
