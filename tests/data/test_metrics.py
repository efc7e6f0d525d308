"""Metrics against the official KITTI devkit numbers, evo, scipy and hand-computed cases."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dmlo import metrics as M
from dmlo.poses import read_kitti_poses

# Official devkit (evaluate_odometry.cpp) on KITTI 00, from shared/data/README.md: segments, t_rel (%),
# r_rel (deg/m), and evo_ape --align RMSE (m).
REFERENCE = {
    "ORB": (3283, 0.699733, 0.00253352, 1.3034497),
    "SPTAM": (3283, 1.486966, 0.00557728, 3.7384879),
}


@pytest.fixture(scope="module")
def kitti00(shared_data: Path) -> dict[str, np.ndarray]:
    folder = shared_data / "kitti_metric_reference"
    return {
        "gt": read_kitti_poses(folder / "KITTI_00_gt.txt"),
        "ORB": read_kitti_poses(folder / "KITTI_00_ORB.txt"),
        "SPTAM": read_kitti_poses(folder / "KITTI_00_SPTAM.txt"),
        "folder": folder,  # type: ignore[dict-item]
    }


def straight_line(count: int, step: float = 1.0) -> np.ndarray:
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, 0, 3] = np.arange(count) * step
    return poses


def noisy_copy(poses: np.ndarray, seed: int, sigma_t: float = 0.02, sigma_r: float = 0.002) -> np.ndarray:
    """Chain the ground-truth motions with noise: an odometry-like estimate that drifts."""
    rng = np.random.default_rng(seed)
    motions = np.linalg.inv(poses[:-1]) @ poses[1:]
    noise = np.tile(np.eye(4), (len(motions), 1, 1))
    noise[:, :3, :3] = Rotation.from_rotvec(rng.normal(scale=sigma_r, size=(len(motions), 3))).as_matrix()
    noise[:, :3, 3] = rng.normal(scale=sigma_t, size=(len(motions), 3))
    estimate = [poses[0]]
    for motion in motions @ noise:
        estimate.append(estimate[-1] @ motion)
    return np.stack(estimate)


# ---------------------------------------------------------------------------------------------------
# KITTI devkit metrics


@pytest.mark.parametrize("method", ["ORB", "SPTAM"])
def test_kitti_metrics_match_the_official_devkit(kitti00, method: str) -> None:
    segments, t_rel, r_rel_deg_per_m, _ = REFERENCE[method]
    result = M.kitti_odometry_errors(kitti00["gt"], kitti00[method])
    assert result.segments == segments
    assert round(result.t_rel, 6) == pytest.approx(t_rel, abs=1e-12)
    # To the printed digit: the devkit takes acos of a float32 cosine, which moves the 6th digit of r_rel;
    # the float64 angle would give 0.00253349 and 0.00557726.
    assert round(result.r_rel / 100.0, 8) == pytest.approx(r_rel_deg_per_m, abs=1e-12)


def test_kitti_ground_truth_against_itself_is_zero(kitti00) -> None:
    result = M.kitti_odometry_errors(kitti00["gt"], kitti00["gt"])
    assert result.segments == 3283
    assert result.t_rel == pytest.approx(0.0, abs=1e-9)
    assert result.r_rel == pytest.approx(0.0, abs=1e-5)


def devkit_loop(gt: np.ndarray, est: np.ndarray) -> tuple[list[tuple[int, int, float]], float, float]:
    """A literal, loop-by-loop transcription of evaluate_odometry.cpp (float32 distances)."""
    distances = [np.float32(0.0)]
    for i in range(1, len(gt)):
        dx, dy, dz = (np.float32(v) for v in gt[i - 1, :3, 3] - gt[i, :3, 3])
        distances.append(np.float32(distances[-1] + np.sqrt(np.float32(dx * dx + dy * dy + dz * dz))))
    segments, t_errors, r_errors = [], [], []
    for first in range(0, len(gt), 10):
        for length in (100, 200, 300, 400, 500, 600, 700, 800):
            last = next(
                (i for i in range(first, len(gt)) if distances[i] > distances[first] + np.float32(length)), -1
            )
            if last == -1:
                continue
            error = np.linalg.inv(np.linalg.inv(est[first]) @ est[last]) @ (np.linalg.inv(gt[first]) @ gt[last])
            a, b, c = (np.float32(error[i, i]) for i in range(3))  # float a = pose_error.val[0][0]; …
            d = np.float32(0.5 * (float(a + b + c) - 1.0))  # float d = 0.5*(a+b+c-1.0);
            r_errors.append(float(np.arccos(max(min(d, np.float32(1.0)), np.float32(-1.0)))) / length)
            t_errors.append(np.linalg.norm(error[:3, 3]) / length)
            segments.append((first, last, float(length)))
    return segments, float(np.mean(t_errors)) * 100, float(np.degrees(np.mean(r_errors))) * 100


def test_kitti_vectorised_equals_a_literal_loop(shared_data: Path) -> None:
    gt = read_kitti_poses(shared_data / "kitti_gt_poses" / "04.txt")  # 271 frames, ~390 m
    est = noisy_copy(gt, seed=4)
    segments, t_rel, r_rel = devkit_loop(gt, est)
    result = M.kitti_odometry_errors(gt, est)
    assert list(zip(result.segment_first, result.segment_last, result.segment_length)) == segments
    assert result.t_rel == pytest.approx(t_rel, rel=1e-12)
    assert result.r_rel == pytest.approx(r_rel, rel=1e-12)
    per_length = result.by_length()
    assert sorted(per_length) == [100.0, 200.0, 300.0]
    assert sum(count for _, _, count in per_length.values()) == result.segments


def test_kitti_scale_error_is_its_percentage() -> None:
    gt = straight_line(1001)  # 1000 m along x
    est = gt.copy()
    est[:, :3, 3] *= 1.02  # 2 % too long everywhere
    result = M.kitti_odometry_errors(gt, est)
    # Starts every 10 frames; an L m segment from frame f ends at f + L + 1 (strictly greater distance),
    # so it covers L + 1 m and its error is 2 % of that, divided by L.
    covered = result.segment_last - result.segment_first
    np.testing.assert_array_equal(covered, result.segment_length + 1)
    assert len(result.segment_first) == sum(len(range(0, 1001 - int(length) - 1, 10)) for length in M.KITTI_LENGTHS)
    assert result.t_rel == pytest.approx(np.mean(2.0 * covered / result.segment_length), rel=1e-9)
    assert 2.0 < result.t_rel < 2.02
    assert result.r_rel == pytest.approx(0.0, abs=1e-9)


def test_kitti_constant_yaw_rate_rotation_error() -> None:
    gt = straight_line(1001)
    est = gt.copy()
    # The estimate turns 0.01° per metre where the ground truth goes straight; the segment error's angle
    # is then exactly 0.01° per metre covered (L + 1 m for an L m segment), divided by L.
    est[:, :3, :3] = Rotation.from_euler("z", np.arange(1001)[:, None] * 0.01, degrees=True).as_matrix()
    result = M.kitti_odometry_errors(gt, est)
    covered = result.segment_last - result.segment_first
    # rel 1e-4: the float32 cosine of a ~1° angle resolves it to ~3e-6 rad (the devkit's rounding).
    assert result.r_rel == pytest.approx(np.mean(100 * 0.01 * covered / result.segment_length), rel=1e-4)


def test_kitti_short_sequence_has_no_segments() -> None:
    result = M.kitti_odometry_errors(straight_line(50), straight_line(50))
    assert result.segments == 0 and result.t_rel is None and result.r_rel is None
    assert result.path_length == pytest.approx(49.0)


def test_kitti_metric_errors() -> None:
    with pytest.raises(ValueError, match="poses_gt has 5 poses but poses_est has 4"):
        M.kitti_odometry_errors(straight_line(5), straight_line(4))
    bad = straight_line(5)
    bad[2, 0, 0] = np.nan
    with pytest.raises(ValueError, match="poses_est contains NaN"):
        M.kitti_odometry_errors(straight_line(5), bad)
    with pytest.raises(ValueError, match=r"poses_gt must have shape \(N, 4, 4\)"):
        M.kitti_odometry_errors(np.zeros((5, 3, 4)), straight_line(5))


# ---------------------------------------------------------------------------------------------------
# ATE, RPE


@pytest.mark.parametrize("method", ["ORB", "SPTAM"])
def test_ate_matches_reference_and_evo(kitti00, method: str) -> None:
    pytest.importorskip("evo")
    from evo.core import metrics as evo_metrics
    from evo.tools import file_interface

    rmse_reference = REFERENCE[method][3]
    result = M.absolute_trajectory_error(kitti00["gt"], kitti00[method], alignment="se3")
    assert result.rmse == pytest.approx(rmse_reference, abs=5e-7)

    folder = kitti00["folder"]
    reference = file_interface.read_kitti_poses_file(str(folder / "KITTI_00_gt.txt"))
    for alignment, correct_scale in (("se3", False), ("sim3", True)):
        estimate = file_interface.read_kitti_poses_file(str(folder / f"KITTI_00_{method}.txt"))
        estimate.align(reference, correct_scale=correct_scale)
        ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
        ape.process_data((reference, estimate))
        ours = M.absolute_trajectory_error(kitti00["gt"], kitti00[method], alignment=alignment)
        assert ours.rmse == pytest.approx(ape.get_statistic(evo_metrics.StatisticsType.rmse), rel=1e-9)
        assert ours.mean == pytest.approx(ape.get_statistic(evo_metrics.StatisticsType.mean), rel=1e-9)
        assert ours.max == pytest.approx(ape.get_statistic(evo_metrics.StatisticsType.max), rel=1e-9)
        np.testing.assert_allclose(ours.aligned_poses[:, :3, 3], estimate.positions_xyz, atol=1e-6)


def test_umeyama_recovers_a_similarity() -> None:
    rng = np.random.default_rng(2)
    source = rng.normal(size=(100, 3)) * 10
    rotation = Rotation.random(random_state=3).as_matrix()
    translation, scale = np.array([1.0, -2.0, 3.0]), 1.7
    target = scale * source @ rotation.T + translation
    r, t, s = M.umeyama_alignment(source, target, with_scale=True)
    np.testing.assert_allclose(r, rotation, atol=1e-12)
    np.testing.assert_allclose(t, translation, atol=1e-10)
    assert s == pytest.approx(scale, rel=1e-12)
    r, t, s = M.umeyama_alignment(source, source @ rotation.T + translation)
    np.testing.assert_allclose(r, rotation, atol=1e-12)
    assert s == 1.0


def test_umeyama_errors() -> None:
    with pytest.raises(ValueError, match="at least one"):
        M.umeyama_alignment(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        M.umeyama_alignment(np.zeros((5, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="all identical"):
        M.umeyama_alignment(np.ones((4, 3)), np.zeros((4, 3)), with_scale=True)
    # Collinear points: the rotation about the line is free, but the fit is still exact.
    line = np.outer(np.arange(5.0), [1.0, 0.0, 0.0])
    rotation = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    r, t, _ = M.umeyama_alignment(line, line @ rotation.T + 1.0)
    np.testing.assert_allclose(line @ r.T + t, line @ rotation.T + 1.0, atol=1e-12)


def test_ate_without_alignment_and_on_a_straight_line() -> None:
    gt = straight_line(20)
    est = gt.copy()
    est[:, 1, 3] += 0.5
    result = M.absolute_trajectory_error(gt, est, alignment=None)
    assert result.rmse == pytest.approx(0.5) and result.max == pytest.approx(0.5)
    # A straight line: the SE(3) alignment removes the constant offset.
    assert M.absolute_trajectory_error(gt, est).rmse == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="alignment must be"):
        M.absolute_trajectory_error(gt, est, alignment="affine")  # type: ignore[arg-type]


@pytest.mark.parametrize("delta", [1, 10])
def test_rpe_matches_evo(kitti00, delta: int) -> None:
    pytest.importorskip("evo")
    from evo.core import metrics as evo_metrics
    from evo.tools import file_interface

    folder = kitti00["folder"]
    reference = file_interface.read_kitti_poses_file(str(folder / "KITTI_00_gt.txt"))
    estimate = file_interface.read_kitti_poses_file(str(folder / "KITTI_00_ORB.txt"))
    ours = M.relative_pose_error(kitti00["gt"], kitti00["ORB"], delta=delta)
    for relation, mean, maximum in (
        (evo_metrics.PoseRelation.translation_part, ours.t_mean, ours.t_max),
        (evo_metrics.PoseRelation.rotation_angle_deg, ours.r_mean, ours.r_max),
    ):
        # Ours uses every pair (i, i + delta): evo's all_pairs=True.
        rpe = evo_metrics.RPE(relation, delta=delta, delta_unit=evo_metrics.Unit.frames, all_pairs=True)
        rpe.process_data((reference, estimate))
        assert mean == pytest.approx(rpe.get_statistic(evo_metrics.StatisticsType.mean), rel=1e-6)
        assert maximum == pytest.approx(rpe.get_statistic(evo_metrics.StatisticsType.max), rel=1e-6)


def test_rpe_hand_case_and_errors() -> None:
    gt = straight_line(11)
    est = gt.copy()
    est[:, 0, 3] *= 1.1  # each 1 m step estimated as 1.1 m
    result = M.relative_pose_error(gt, est)
    np.testing.assert_allclose(result.t_errors, 0.1, atol=1e-12)
    assert result.r_max == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="delta must be"):
        M.relative_pose_error(gt, est, delta=0)
    with pytest.raises(ValueError, match="needs more than 11 poses"):
        M.relative_pose_error(gt, est, delta=11)


def test_rotation_angle_small_and_large() -> None:
    angles = np.array([1e-7, 1e-3, 0.5, 90.0, 179.9])
    rotations = Rotation.from_rotvec(np.radians(angles)[:, None] * np.array([[0.0, 0.6, 0.8]])).as_matrix()
    np.testing.assert_allclose(M.rotation_angle_deg(rotations), angles, rtol=1e-9)


# ---------------------------------------------------------------------------------------------------
# Registration errors (Table IV)


def test_registration_errors_definition() -> None:
    rng = np.random.default_rng(7)
    gt = np.tile(np.eye(4), (50, 1, 1))
    gt[:, :3, :3] = Rotation.random(50, random_state=8).as_matrix()
    gt[:, :3, 3] = rng.normal(size=(50, 3))
    est = gt.copy()
    perturbation = Rotation.from_rotvec(rng.normal(scale=0.1, size=(50, 3)))
    est[:, :3, :3] = gt[:, :3, :3] @ perturbation.as_matrix()
    est[:, :3, 3] += rng.normal(scale=0.05, size=(50, 3))
    result = M.registration_errors(est, gt)
    # 2·asin(‖R − R̄‖_F / 2√2) is the geodesic angle between the rotations.
    np.testing.assert_allclose(result.angular, np.degrees(perturbation.magnitude()), rtol=1e-9)
    np.testing.assert_allclose(result.translation, np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1))
    assert result.angular_max == pytest.approx(result.angular.max())
    assert result.translation_mean == pytest.approx(result.translation.mean())
    single = M.registration_errors(est[0], gt[0])
    assert single.angular_mean == pytest.approx(result.angular[0])


def test_registration_hand_case_and_errors() -> None:
    est = np.eye(4)
    est[:3, :3] = Rotation.from_euler("z", 10, degrees=True).as_matrix()
    est[:3, 3] = [3.0, 4.0, 0.0]
    result = M.registration_errors(est, np.eye(4))
    assert result.angular_mean == pytest.approx(10.0, rel=1e-12)
    assert result.translation_mean == pytest.approx(5.0)
    with pytest.raises(ValueError, match="transforms_est has 2 transforms but transforms_gt has 1"):
        M.registration_errors(np.stack([est, est]), np.eye(4))
    with pytest.raises(ValueError, match=r"transforms_gt must have shape"):
        M.registration_errors(est, np.eye(3))


# ---------------------------------------------------------------------------------------------------
# Flow (Table V)


def test_epe_and_fl_all_hand_case() -> None:
    gt = np.zeros((2, 2, 3))
    gt[0] = [[0.0, 100.0, 10.0], [1.0, 0.0, 50.0]]
    pred = gt.copy()
    pred[0, 0, 0] += 4.0  # EPE 4 > 3 and > 5 % of 0            → outlier
    pred[0, 0, 1] += 4.0  # EPE 4 > 3 but < 5 % of 100 = 5      → inlier
    pred[1, 0, 2] += 3.0  # EPE 3 is not > 3                     → inlier
    pred[1, 1, 0] += 2.0  # EPE 2                                → inlier
    pred[0, 1, 2] += 6.0  # EPE 6 > 3, > 2.5, but masked out
    valid = np.ones((2, 3), dtype=bool)
    valid[1, 2] = False
    result = M.flow_errors(pred, gt, valid)
    assert result.valid_pixels == 5 and result.outliers == 1
    assert result.epe == pytest.approx((4 + 4 + 3 + 2 + 0) / 5)
    assert result.fl_all == pytest.approx(20.0)
    assert M.end_point_error(pred, gt, valid) == result.epe
    assert M.fl_all(pred, gt, valid) == result.fl_all
    # Batched input: the same pixels twice give the same averages.
    batched = M.flow_errors(np.stack([pred, pred]), np.stack([gt, gt]), np.stack([valid, valid]))
    assert batched.valid_pixels == 10 and batched.fl_all == pytest.approx(20.0)


def test_flow_errors_bad_input() -> None:
    flow = np.zeros((2, 4, 5))
    with pytest.raises(ValueError, match="no valid pixels"):
        M.flow_errors(flow, flow, np.zeros((4, 5), dtype=bool))
    with pytest.raises(TypeError, match="boolean mask"):
        M.flow_errors(flow, flow, np.ones((4, 5)))
    with pytest.raises(ValueError, match=r"valid has shape \(4, 4\)"):
        M.flow_errors(flow, flow, np.ones((4, 4), dtype=bool))
    with pytest.raises(ValueError, match="flow_gt has shape"):
        M.flow_errors(flow, np.zeros((2, 4, 4)))
    with pytest.raises(ValueError, match=r"flow_pred must be \(2, H, W\)"):
        M.flow_errors(np.zeros((3, 4, 5)), np.zeros((3, 4, 5)))
    bad = flow.copy()
    bad[0, 1, 1] = np.nan
    with pytest.raises(ValueError, match="flow_pred has NaN"):
        M.flow_errors(bad, flow)
    mask = np.ones((4, 5), dtype=bool)
    mask[1, 1] = False
    assert M.flow_errors(bad, flow, mask).epe == 0.0  # NaN outside the mask is ignored
    assert copy.copy(M.flow_errors(flow, flow)).fl_all == 0.0


# ---------------------------------------------------------------------------------------------------
# The summary dict used by `dmlo eval`, `dmlo run` and the benchmark


def test_evaluate_trajectory_summary(kitti00) -> None:
    summary = M.evaluate_trajectory(kitti00["gt"], kitti00["ORB"])
    kitti = M.kitti_odometry_errors(kitti00["gt"], kitti00["ORB"])
    rpe = M.relative_pose_error(kitti00["gt"], kitti00["ORB"])
    assert summary["t_rel"] == kitti.t_rel and summary["r_rel"] == kitti.r_rel
    assert summary["ate_rmse"] == pytest.approx(1.3034497, abs=5e-7)
    assert summary["rpe_t_mean"] == rpe.t_mean and summary["rpe_r_max"] == rpe.r_max
    assert summary["note"] is None and summary["ate_alignment"] == "se3"


def test_evaluate_trajectory_degenerate_inputs() -> None:
    single = M.evaluate_trajectory(np.eye(4)[None], np.eye(4)[None])
    assert single["t_rel"] is None and single["rpe_t_mean"] is None and single["ate_rmse"] == 0.0
    assert "shorter than the 100 m" in single["note"] and "RPE over 1 frame(s)" in single["note"]
    with pytest.raises(ValueError, match="poses_gt has 2 poses but poses_est has 1"):
        M.evaluate_trajectory(straight_line(2), straight_line(1))
    with pytest.raises(ValueError, match="delta must be"):
        M.evaluate_trajectory(straight_line(2), straight_line(2), delta=0)


def test_signed_rotation_errors_per_axis_are_scipys_rotation_vector() -> None:
    estimate = Rotation.random(50, random_state=3)
    truth = Rotation.random(50, random_state=4)
    axes = M.rotation_error_axes_deg(estimate.as_matrix(), truth.as_matrix())
    np.testing.assert_allclose(axes, np.degrees((truth.inv() * estimate).as_rotvec()), atol=1e-9)
    np.testing.assert_allclose(
        np.linalg.norm(axes, axis=1), M.rotation_error_deg(estimate.as_matrix(), truth.as_matrix()), atol=1e-9
    )
    small = Rotation.from_rotvec([0.0, 1e-9, 0.0]).as_matrix()
    np.testing.assert_allclose(M.rotation_error_axes_deg(small, np.eye(3)), [0.0, np.degrees(1e-9), 0.0], atol=1e-15)
    with pytest.raises(ValueError, match="rotations"):
        M.rotation_error_axes_deg(np.eye(3), np.eye(4))
