"""The crate's motion model (`dmlo_rs.MotionModel`) and frame clock as `dmlo.Odometry` uses them: the
judgement of a pair against the constant-velocity prediction, checked against motions built with scipy, and
bad arguments named."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import dmlo_rs


def motion(forward_m: float, yaw_deg: float = 0.0) -> np.ndarray:
    """T_tgt_ref of a car that drove `forward_m` along x and turned by `yaw_deg`."""
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    pose[0, 3] = forward_m
    return np.linalg.inv(pose)


def moved(points: np.ndarray, transform: np.ndarray) -> np.ndarray:
    return points @ transform[:3, :3].T + transform[:3, 3]


@pytest.fixture
def driving() -> dmlo_rs.MotionModel:
    """A model that measured 1 m a frame."""
    model = dmlo_rs.MotionModel()
    model.update(np.eye(4), np.linalg.inv(motion(1.0)), 1)
    return model


def test_the_prediction_is_the_velocity_to_the_power_of_the_frames(driving: dmlo_rs.MotionModel) -> None:
    fresh = dmlo_rs.MotionModel()
    assert not fresh.measured and np.array_equal(fresh.predicted(5), np.eye(4))
    assert driving.measured
    np.testing.assert_allclose(driving.velocity, motion(1.0), atol=1e-12)
    turning = dmlo_rs.MotionModel()
    turning.update(np.eye(4), np.linalg.inv(motion(1.2, 3.0)), 1)
    for frames in (0, 1, 2, 5, 7):
        np.testing.assert_allclose(turning.predicted(frames), np.linalg.matrix_power(motion(1.2, 3.0), frames), atol=1e-12)
    gap = dmlo_rs.MotionModel()
    gap.update(np.eye(4), np.linalg.inv(motion(2.0)), 2)  # two frames apart: no per-frame velocity
    assert not gap.measured


def test_a_wrong_consensus_gives_way_to_the_matches_that_agree_with_the_prediction(driving: dmlo_rs.MotionModel) -> None:
    rng = np.random.default_rng(3)
    source = np.column_stack([rng.uniform(-20, 20, 90), rng.uniform(-15, 15, 90), rng.uniform(-1.7, 3, 90)])
    truth = motion(1.04, 0.1)
    target = moved(source, truth)
    target[::3] = source[::3]  # a third of the matches stand still, as locked road rings do
    standing = np.eye(4)
    judged, fallback = driving.judge(standing, 60, None, source, target, driving.predicted(1), 1)
    assert fallback == "guided_consensus"
    np.testing.assert_allclose(judged, truth, atol=1e-9)
    # Nothing agrees with the prediction: the prediction, but never twice in a row.
    judged, fallback = driving.judge(standing, 90, None, source, source, driving.predicted(1), 1)
    assert fallback == "implausible_motion" and driving.gated_last
    np.testing.assert_array_equal(judged, driving.predicted(1))
    judged, fallback = driving.judge(standing, 90, None, source, source, driving.predicted(1), 1)
    assert fallback is None and not driving.gated_last
    np.testing.assert_array_equal(judged, standing)


def test_few_inliers_and_road_votes_take_the_prediction(driving: dmlo_rs.MotionModel) -> None:
    nothing = np.zeros((0, 3))
    predicted = driving.predicted(1)
    assert driving.judge(motion(1.05), 9, None, nothing, nothing, predicted, 1)[1] == "constant_velocity"
    assert driving.judge(motion(1.05), 50, 4.0, nothing, nothing, predicted, 1)[1] == "degenerate_scene"
    judged, fallback = driving.judge(motion(1.05), 50, 6.0, nothing, nothing, predicted, 1)
    assert fallback is None
    np.testing.assert_array_equal(judged, motion(1.05))
    assert driving.implausible(motion(1.5), predicted, 1) and not driving.implausible(motion(1.5), predicted, 2)
    assert not driving.implausible(motion(5.0), driving.predicted(21), 21)  # beyond the prediction's horizon


def test_bad_arguments_are_named(driving: dmlo_rs.MotionModel) -> None:
    points = np.zeros((4, 3))
    with pytest.raises(ValueError, match="min_inliers"):
        dmlo_rs.MotionModel(min_inliers=2)
    with pytest.raises(ValueError, match="guided_fraction"):
        dmlo_rs.MotionModel(guided_fraction=2.0)
    with pytest.raises(ValueError, match="refit"):
        dmlo_rs.MotionModel(refit="icp")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="motion"):
        driving.judge(np.eye(3), 10, None, points, points, np.eye(4), 1)
    with pytest.raises(ValueError, match="predicted"):
        driving.judge(np.eye(4), 10, None, points, points, np.full((4, 4), np.nan), 1)
    with pytest.raises(ValueError, match="source and target"):
        driving.judge(np.eye(4), 10, None, points, points[:3], np.eye(4), 1)
    with pytest.raises(ValueError, match="gap"):
        driving.judge(np.eye(4), 10, None, points, points, np.eye(4), -1)
    with pytest.raises(ValueError, match="pose"):
        driving.update(np.eye(4), 2 * np.eye(4), 1)


def test_the_frame_clock_counts_missing_scans_from_timestamps() -> None:
    clock = dmlo_rs.FrameClock()
    assert clock.frame == -1 and clock.period is None
    assert [clock.advance(t)[0] for t in (0.0, 0.1, 0.2, 0.3, 0.6, 0.7, 1.3)] == [0, 1, 2, 3, 6, 7, 13]
    assert clock.period == pytest.approx(0.1)
    assert clock.advance(1.0) == (14, True)  # back in time: the next frame, flagged
    with pytest.raises(ValueError, match="timestamp"):
        clock.advance(float("nan"))
    assert clock.frame == 14
