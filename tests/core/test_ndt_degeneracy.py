"""Degeneracy-aware NDT (`NdtMap.align(..., degeneracy_threshold=...)`): directions the map does not
constrain keep the initial estimate (Zhang, Kaess & Singh 2016). A synthetic corridor, where the axis is
degenerate, and a simulated straight drive, where it is not (the along-track pull there is a bias of the
ground's ring sampling that carries 12–30 % of the best direction's information: see docs/measurements.md)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from scipy.spatial.transform import Rotation

import dmlo_rs
from dmlo.datasets import open_sequence
from dmlo.simulator import simulate_sequence
from support import frame_to_frame, rigid, transform_points

FloatArray = npt.NDArray[np.float64]


def corridor(count: int, x_range: tuple[float, float], seed: int) -> FloatArray:
    """Ground (|y| ≤ 6 m) and two 4 m walls at y = ±6 m, all parallel to x, with ±1 cm noise."""
    rng = np.random.default_rng(seed)
    half_width, height = 6.0, 4.0
    x = rng.uniform(*x_range, count)
    on_ground = rng.random(count) < half_width / (half_width + height)
    side = np.where(rng.random(count) < 0.5, -half_width, half_width)
    y = np.where(on_ground, rng.uniform(-half_width, half_width, count), side)
    z = np.where(on_ground, 0.0, rng.uniform(0.0, height, count))
    return np.column_stack([x, y, z]) + rng.uniform(-0.01, 0.01, (count, 3))


@pytest.fixture(scope="module")
def corridor_case() -> tuple[dmlo_rs.NdtMap, FloatArray, FloatArray, FloatArray]:
    ndt_map = dmlo_rs.NdtMap(voxel_size=1.0)
    ndt_map.insert(corridor(60_000, (-40.0, 40.0), seed=1))
    truth = rigid([2.0, 0.1, 0.05], [0.2, -0.3, 1.0])
    # The scan covers only the corridor's middle: no end wall tells where along x it is.
    source = transform_points(np.linalg.inv(truth), corridor(10_000, (-20.0, 20.0), seed=2))
    start = rigid([0.3, -0.08, 0.04], [0.3, -0.2, 0.8]) @ truth  # 0.3 m off along the axis
    return ndt_map, source, truth, start


def test_corridor_axis_keeps_the_initial_estimate(
    corridor_case: tuple[dmlo_rs.NdtMap, FloatArray, FloatArray, FloatArray],
) -> None:
    ndt_map, source, truth, start = corridor_case
    result = ndt_map.align(source, start)
    assert result.converged, result
    assert result.degenerate_directions == 1, result
    assert result.translation_eigenvalues[0] < 0.05 < result.translation_eigenvalues[1], result
    assert np.all(result.rotation_eigenvalues > 0.01), result
    estimate = result.transform
    # x stays where it started, everything else converges to the truth.
    assert estimate[0, 3] == pytest.approx(start[0, 3], abs=0.005)
    np.testing.assert_allclose(estimate[1:3, 3], truth[1:3, 3], atol=0.005)
    rotation_error = Rotation.from_matrix(estimate[:3, :3].T @ truth[:3, :3]).magnitude()
    assert np.degrees(rotation_error) < 0.02, result


def test_corridor_axis_is_pulled_without_the_analysis(
    corridor_case: tuple[dmlo_rs.NdtMap, FloatArray, FloatArray, FloatArray],
) -> None:
    ndt_map, source, _, start = corridor_case
    result = ndt_map.align(source, start, degeneracy_threshold=0.0, rotation_degeneracy_threshold=0.0)
    assert result.degenerate_directions == 0
    assert abs(result.transform[0, 3] - start[0, 3]) > 0.05, result


def test_thresholds_are_validated(
    corridor_case: tuple[dmlo_rs.NdtMap, FloatArray, FloatArray, FloatArray],
) -> None:
    ndt_map, source, _, start = corridor_case
    for bad in (-0.1, 1.0, float("nan")):
        with pytest.raises(ValueError, match="degeneracy_threshold: must lie in"):
            ndt_map.align(source, start, degeneracy_threshold=bad)
        with pytest.raises(ValueError, match="rotation_degeneracy_threshold: must lie in"):
            ndt_map.align(source, start, rotation_degeneracy_threshold=bad)


# ---- simulated straight drive --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def straight_drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("straight")
    simulate_sequence(out, frames=30, seed=1, progress=False)
    return out


def ground_truth_alignment_errors(drive: Path, **options: float) -> tuple[FloatArray, list[dmlo_rs.NdtResult]]:
    """Each of frames 20, 23, 26, 29 aligned from its true pose to a map of the 10 scans before it at their
    true poses (moving objects removed): the error of the result in the ego frame, cm."""
    sequence = open_sequence(drive)
    frames = {i: sequence[i] for i in range(10, 30)}

    def static_points(i: int) -> FloatArray:
        frame = frames[i]
        return frame.points[(frame.labels & 0xFFFF) < 252][:, :3].astype(np.float64)

    errors, results = [], []
    for i in (20, 23, 26, 29):
        ndt_map = dmlo_rs.NdtMap(voxel_size=1.0, max_scans=10)
        for j in range(i - 10, i):
            ndt_map.insert(transform_points(frames[j].pose, static_points(j)))
        result = ndt_map.align(static_points(i), frames[i].pose, **options)
        errors.append((np.linalg.inv(frames[i].pose) @ result.transform)[:3, 3] * 100)
        results.append(result)
    return np.array(errors), results


@pytest.mark.slow
def test_straight_drive_along_track_bias_goes_when_the_direction_is_held(straight_drive: Path) -> None:
    free, free_results = ground_truth_alignment_errors(straight_drive)
    # With the defaults nothing is degenerate: the along-track direction has a fifth of the information
    # of the best one, and NDT pulls the scan backwards (the map's rings were all sampled from behind).
    assert all(r.degenerate_directions == 0 for r in free_results)
    assert all(0.1 < r.translation_eigenvalues[0] < 0.4 for r in free_results)
    assert free[:, 0].mean() < -0.15, free
    # Declared degenerate, it is exactly the along-track direction that is held: x keeps the (true)
    # start, y and z are solved as before.
    held, held_results = ground_truth_alignment_errors(straight_drive, degeneracy_threshold=0.4)
    assert all(r.degenerate_directions == 1 for r in held_results)
    assert np.abs(held[:, 0]).mean() < 0.03, held
    np.testing.assert_allclose(held[:, 1:], free[:, 1:], atol=0.05)


# ---- the odometry's mapping stage ----------------------------------------------------------------------


def test_mapping_thresholds_reach_the_alignment_and_the_diagnostics(straight_drive: Path) -> None:
    from dmlo.odometry import Odometry

    sequence = open_sequence(straight_drive)
    scans = [sequence[i].points for i in range(4)]
    counts = {}
    for threshold in (0.05, 0.99):
        config = frame_to_frame()
        config.mapping.enabled = True
        config.mapping.degeneracy_threshold = threshold
        config.mapping.rotation_degeneracy_threshold = threshold
        odometry = Odometry.from_default(config)
        for points in scans:
            odometry.register(points)
        refined = odometry.diagnostics[1:]
        assert all(d.ndt_converged for d in refined)
        assert all(d.to_dict()["ndt_degenerate_directions"] == d.ndt_degenerate_directions for d in refined)
        counts[threshold] = [d.ndt_degenerate_directions for d in refined]
    assert odometry.diagnostics[0].ndt_degenerate_directions is None  # the first scan only builds the map
    # A street constrains every direction; at 0.99 all but the best translation and rotation are held.
    assert counts == {0.05: [0, 0, 0], 0.99: [4, 4, 4]}


@pytest.mark.parametrize("name", ["degeneracy_threshold", "rotation_degeneracy_threshold"])
def test_bad_mapping_threshold_stops_the_run_instead_of_silently_skipping_ndt(name: str) -> None:
    from dmlo.odometry import Odometry

    # Refused with the config, before any scan (the crate refuses it too, as a ValueError rather than a
    # RegistrationError that the odometry would take for a failed alignment: the bindings' test above).
    config = frame_to_frame()
    setattr(config.mapping, name, 1.5)
    with pytest.raises(ValueError, match=rf"^mapping\.{name}: must be a number >= 0 and < 1, got 1.5$") as refused:
        Odometry.from_default(config)
    assert not isinstance(refused.value, dmlo_rs.RegistrationError)


def test_map_keyframes_spaced_in_distance_take_away_the_slow_drive_pull(straight_drive: Path) -> None:
    from dmlo.metrics.trajectory import absolute_trajectory_error
    from dmlo.odometry import Odometry, OdometryConfig

    sequence = open_sequence(straight_drive)
    frames = [sequence[i] for i in range(len(sequence))]
    truth = np.array([frame.pose for frame in frames])
    errors, keyframes = {}, {}
    spaced = OdometryConfig().mapping.keyframe_distance
    # Measured: ATE 6.7 mm with every scan in the map, 1.6 mm with a keyframe every 2 m (7 of 30 scans).
    for distance in (0.0, spaced):
        config = frame_to_frame()
        config.mapping.enabled = True
        config.mapping.keyframe_distance = distance
        # The keyframes' spacing alone: a source thinned by range (the default) pulls less on this drive.
        config.mapping.far_range = math.inf
        odometry = Odometry.from_default(config)
        for frame in frames:
            odometry.register(frame.points, moving=(frame.labels & 0xFFFF) >= 252)
        errors[distance] = absolute_trajectory_error(truth, np.array(odometry.poses)).rmse
        keyframes[distance] = [d.map_keyframe for d in odometry.diagnostics]
    assert all(keyframes[0.0])
    assert keyframes[spaced][0] and 3 <= sum(keyframes[spaced]) <= len(frames) // 2, keyframes[spaced]
    assert errors[spaced] < 0.5 * errors[0.0], errors


def test_a_standing_car_adds_no_keyframes(straight_drive: Path) -> None:
    from dmlo.odometry import Odometry

    config = frame_to_frame()
    config.mapping.enabled = True
    odometry = Odometry.from_default(config)
    scan = open_sequence(straight_drive)[0].points
    for _ in range(4):
        odometry.register(scan)
    assert [d.map_keyframe for d in odometry.diagnostics] == [True, False, False, False]


@pytest.mark.parametrize(
    ("section", "name"),
    [
        ("mapping", "keyframe_distance"),
        ("mapping", "keyframe_angle_deg"),
        ("mapping", "ring_lock_distance"),
        ("mapping", "motion_model_start_distance"),
        ("mapping", "motion_model_start_angle_deg"),
        ("motion_model", "max_deviation"),
        ("motion_model", "max_deviation_deg"),
        ("motion_model", "guided_fraction"),
        ("matching", "consistency_px"),
    ],
)
def test_bad_distance_and_angle_limits_are_refused_up_front(section: str, name: str) -> None:
    from dmlo.odometry import Odometry

    config = frame_to_frame()
    setattr(getattr(config, section), name, -1.0)
    with pytest.raises(ValueError, match=rf"{section}\.{name}: must be a number >= 0\b.*, got -1.0"):
        Odometry.from_default(config)


def test_a_wrong_dmlo_pose_is_caught_by_aligning_from_the_motion_model_too(straight_drive: Path) -> None:
    from dmlo.odometry import Odometry
    from faults import corrupt

    sequence = open_sequence(straight_drive)
    frames = [sequence[i] for i in range(20)]
    step_errors = {}
    for distance in (0.3, np.inf):  # the default, and never a second start
        config = frame_to_frame()
        config.motion_model.max_deviation = np.inf  # the pure-DMLO gate would catch it first
        config.mapping.enabled = True
        config.mapping.motion_model_start_distance = distance
        config.mapping.motion_model_start_angle_deg = np.inf
        # Fault injection: every match of frame 15 lies 1.2 m off the true motion, like a wrong RANSAC consensus.
        truth = np.linalg.inv(frames[15].pose) @ frames[14].pose
        odometry = corrupt(Odometry.from_default(config), truth, share=1.0, frame=15, shift=(1.2, 0.0, 0.0))
        for frame in frames:
            odometry.register(frame.points, moving=(frame.labels & 0xFFFF) >= 252)
        truth_step = np.linalg.inv(frames[14].pose) @ frames[15].pose
        step = np.linalg.inv(odometry.poses[14]) @ odometry.poses[15]
        step_errors[distance] = np.linalg.norm((np.linalg.inv(truth_step) @ step)[:3, 3])
        starts = [d.ndt_start for d in odometry.diagnostics[1:]]
        if distance == 0.3:
            # Only the corrupted frame leaves the prediction behind; elsewhere NDT starts from DMLO alone.
            assert starts == ["dmlo"] * 14 + ["motion_model"] + ["dmlo"] * 4, starts
        else:
            assert set(starts) == {"dmlo"}
    assert step_errors[0.3] < 0.01, step_errors
    assert step_errors[np.inf] > 0.3, step_errors
