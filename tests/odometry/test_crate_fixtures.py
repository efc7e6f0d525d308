"""The fixtures the crate's odometry is tested against are what Python gives today: the config its
`odometry::config` reads (`tests/fixtures/odometry_config.json`, as `OdometryConfig.save` writes it) and the poses
its `Odometry` over tract must equal (`tests/fixtures/odometry_poses.json`). When a setting is added, renamed or
its default changes, or the odometry's behaviour does, the fixtures (and the crate) must follow."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import dmlo_rs
import numpy as np
import pytest

from dmlo.odometry.config import ConfigError, OdometryConfig

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def test_the_crate_config_fixture_is_what_python_saves_today() -> None:
    spec = importlib.util.spec_from_file_location("make_odometry_config", FIXTURES / "make_odometry_config.py")
    assert spec is not None and spec.loader is not None
    maker = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(maker)
    assert (FIXTURES / "odometry_config.json").read_text() == maker.odometry_config_text(), f"re-run {maker.__file__}"


def test_the_python_defaults_are_the_crates(tmp_path: Path) -> None:
    """Every default the crate holds (`OdometryConfig::default()`, written by `dmlo_rs.odometry_config_json`)
    equals Python's, key for key."""
    crate = json.loads(dmlo_rs.odometry_config_json())
    assert crate == json.loads(json.dumps(OdometryConfig().to_dict()))


def test_the_crate_reads_what_python_saves_and_writes_it_back_alike() -> None:
    text = (FIXTURES / "odometry_config.json").read_text()
    assert json.loads(dmlo_rs.odometry_config_json(text)) == json.loads(text)
    assert OdometryConfig.from_dict(json.loads(dmlo_rs.odometry_config_json(text))) == OdometryConfig.load(
        FIXTURES / "odometry_config.json"
    )


@pytest.mark.parametrize(
    ("settings", "key"),
    [
        ({"ransac": {"treshold": 0.2}}, "ransac.treshold"),
        ({"ransac": {"threshold": 0}}, "ransac.threshold"),
        ({"matching": {"symmetric": 1}}, "matching.symmetric"),
        ({"matching": {"nms_radius": 1.5}}, "matching.nms_radius"),
        ({"motion_model": {"rematch_gap": 0}}, "motion_model.rematch_gap"),
        ({"mapping": {"keyframe_distance": -1.0}}, "mapping.keyframe_distance"),
        ({"mapping": {"voxel_size": float("inf")}}, "mapping.voxel_size"),
        ({"large_motion": {"search_ahead_m": []}}, "large_motion.search_ahead_m"),
        ({"reflectance": "bright"}, "reflectance"),
        ({"mapping": [1]}, "mapping"),
    ],
)
def test_the_crate_refuses_what_python_refuses_naming_the_same_key(settings: dict[str, object], key: str) -> None:
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        OdometryConfig.from_dict(settings)
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        dmlo_rs.odometry_config_json(json.dumps(settings))


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
