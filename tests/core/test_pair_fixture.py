"""The fixture of the crate's learned pair from Rust (`cargo test --features inference`) is what the Python
odometry's back end gives today: when the model or a default setting of the pair changes, the fixture must too.
Within 1e-6: the fixture may have been recorded on another processor, whose onnxruntime kernels round the
features differently (the Rust test holds tract's pair to the same bound)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def test_the_rust_pair_fixture_matches_the_python_odometry_today(shared_data: Path) -> None:
    spec = importlib.util.spec_from_file_location("make_pair_motion", FIXTURES / "make_pair_motion.py")
    assert spec is not None and spec.loader is not None
    maker = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(maker)
    fixture = json.loads((FIXTURES / "pair_motion.json").read_text())
    today = maker.pair_motion(shared_data)
    np.testing.assert_allclose(fixture["T_tgt_ref"], today["T_tgt_ref"], rtol=0, atol=1e-6, err_msg=f"re-run {maker.__file__}")
    assert (fixture["num_matches"], fixture["num_inliers"]) == (today["num_matches"], today["num_inliers"])
    assert 0.9 < -today["T_tgt_ref"][0][3] < 1.0  # the car drove about 0.95 m forward
