"""The poses the crate's `Odometry` over onnxruntime and tract must equal (`tests/fixtures/odometry_poses.json`)
are what `dmlo.Odometry` gives today: when the odometry's behaviour changes, the fixture must follow."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def test_the_crate_odometry_fixture_is_what_python_gives_today(shared_data: Path) -> None:
    """`odometry_poses.json`, the poses the crate's `Odometry` over onnxruntime and tract must equal (`cargo test
    --features inference,onnxruntime`), is what `dmlo.Odometry` gives today: a change of the odometry's behaviour
    shows in both. Within 1e-5 (metres, and rotation entries), the crate test's bound: the fixture may have been
    recorded on another processor, whose onnxruntime kernels round the features differently."""
    spec = importlib.util.spec_from_file_location("make_odometry_poses", FIXTURES / "make_odometry_poses.py")
    assert spec is not None and spec.loader is not None
    maker = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(maker)
    fixture = json.loads((FIXTURES / "odometry_poses.json").read_text())
    today = maker.odometry_poses(shared_data)
    assert fixture.keys() == today.keys()
    for key in fixture:
        np.testing.assert_allclose(fixture[key], today[key], rtol=0, atol=1e-5, err_msg=f"{key}: re-run {maker.__file__}")
