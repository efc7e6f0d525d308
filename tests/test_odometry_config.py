"""The odometry config: defaults are the paper's, files round-trip, typos are rejected by name."""

from __future__ import annotations

from pathlib import Path

import pytest

from dmlo.odometry.config import OdometryConfig


def test_defaults_are_the_papers() -> None:
    config = OdometryConfig()
    assert config.matching.nms_radius == 1.0  # r = 1 (§IV-B)
    assert config.ransac.threshold == 0.1  # 0.1 m inlier threshold
    assert config.motion_model.min_inliers == 10  # fewer than 10 inliers → motion model
    assert config.matching_stage == "auto"  # beyond the paper: where the matching runs, not what it computes
    # Beyond the paper: RANSAC's refits weigh each match by its ray (ransac.refit = "point_to_point" is Eq. 12–14).
    assert config.ransac.refit == "ray_noise"


def test_round_trip_through_a_file(tmp_path: Path) -> None:
    config = OdometryConfig()
    config.ransac.seed = 7
    config.mapping.enabled = True
    config.large_motion.search_yaw_deg = (0.0, 90.0)  # tuples come back from JSON's lists
    config.save(tmp_path / "config.json")
    assert OdometryConfig.load(tmp_path / "config.json") == config


def test_unknown_setting_is_named() -> None:
    with pytest.raises(ValueError, match=r"config\.ransac: unknown setting\(s\) treshold"):
        OdometryConfig.from_dict({"ransac": {"treshold": 0.2}})


def test_section_must_be_a_mapping() -> None:
    with pytest.raises(ValueError, match=r"config\.mapping: expected a mapping"):
        OdometryConfig.from_dict({"mapping": True})
