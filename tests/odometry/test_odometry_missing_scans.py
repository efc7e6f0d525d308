"""Pairs the network's window cannot span on its own — across missing scans, or a pair whose motion would
give way to the prediction — matched again from the constant-velocity prediction (`motion_model.rematch_gap`);
scans missing in time alone (no file missing) counted from the timestamps."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

import dmlo_rs

from dmlo.datasets import open_sequence
from dmlo.metrics import registration_errors
from dmlo.odometry import Odometry, OdometryConfig, TimestampWarning
from dmlo.run import run_sequence
from dmlo.odometry.matcher import default_model_path
from dmlo.simulator import simulate_sequence
from faults import corrupt
from support import frame_to_frame

GAP = 7  # frames between the scans before and after the missing ones


@pytest.fixture(scope="module")
def highway(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    # Along KITTI 04 (a highway, 1.3 m a frame): 7 frames are 9 m, beyond the network's own window.
    out = tmp_path_factory.mktemp("highway")
    simulate_sequence(out, frames=3 + GAP, seed=4, trajectory=shared_data / "kitti_gt_poses" / "04.txt", progress=False)
    return out


def across_the_gap(drive: Path, odometry: Odometry) -> tuple[np.ndarray, np.ndarray]:
    """Scans 0–2 registered, 3 … 2 + GAP − 1 missing, 2 + GAP registered: the odometry's motion across the
    gap and the true one (`T_tgt_ref`)."""
    sequence = open_sequence(drive)
    for index in range(3):
        odometry.register(sequence[index].points)
    for _ in range(GAP - 1):
        odometry.predict_skipped()
    odometry.register(sequence[2 + GAP].points)
    estimated = np.linalg.inv(odometry.poses[-1]) @ odometry.poses[2]
    truth = np.linalg.inv(sequence[2 + GAP].pose) @ sequence[2].pose
    return estimated, truth


def test_a_pair_across_missing_scans_is_matched_again_from_the_prediction(highway: Path) -> None:
    paper = frame_to_frame()
    paper.motion_model.rematch_gap = None
    paper.motion_model.match_from_prediction_m = None  # the paper's path: from the identity alone
    lost = Odometry.from_default(paper)
    lost_motion, truth = across_the_gap(highway, lost)
    assert np.linalg.norm(truth[:3, 3]) > 8.5
    lost_errors = registration_errors(lost_motion, truth)
    # The pair alone is out of the window: its motion gives way to the prediction, decimetres off.
    assert lost.diagnostics[-1].fallback in ("constant_velocity", "implausible_motion")
    assert lost_errors.translation_mean > 0.1, lost_errors
    assert lost.diagnostics[-1].rematch_rounds is None

    found = Odometry.from_default(frame_to_frame())
    motion, truth = across_the_gap(highway, found)
    errors = registration_errors(motion, truth)
    last = found.diagnostics[-1]
    assert last.fallback == "rematched_from_prediction" and last.rematch_rounds is not None and last.rematch_rounds >= 1
    # Measured: 5.3 cm and 0.14° against the prediction's 16 cm and 0.46°.
    assert errors.translation_mean < 0.08 and errors.angular_mean < 0.3, errors
    assert errors.translation_mean < 0.5 * lost_errors.translation_mean
    assert errors.angular_mean < 0.5 * lost_errors.angular_mean
    assert last.num_inliers >= 30 and "rematch" in last.timings_ms
    # Consecutive pairs that stand on their own are not matched again.
    assert [d.rematch_rounds for d in found.diagnostics[:3]] == [None, None, None]
    assert found.diagnostics[1].fallback is None and found.diagnostics[2].fallback is None


def test_the_rematched_motion_is_taken_only_with_more_inliers_than_the_pairs_own(highway: Path) -> None:
    # rematch_gap 1 matches every pair again; a consecutive pair's own motion is good, so which one is taken
    # follows the inlier counts (the re-projected scan usually shares more cells with its target).
    config = frame_to_frame()
    config.motion_model.rematch_gap = 1
    odometry = Odometry.from_default(config)
    sequence = open_sequence(highway)
    plain = Odometry.from_default(frame_to_frame())
    for index in range(4):
        odometry.register(sequence[index].points)
        plain.register(sequence[index].points)
    for ours, theirs in zip(odometry.diagnostics[2:], plain.diagnostics[2:]):
        assert ours.rematch_rounds is not None
        taken = ours.fallback == "rematched_from_prediction"
        assert taken == (ours.rematch_rounds > 0)
        assert ours.num_inliers > theirs.num_inliers if taken else ours.num_inliers == theirs.num_inliers


def wrong_first_pair(config: OdometryConfig, honest_poses: list[np.ndarray]) -> Odometry:
    """Fault injection: the pair's own matches of frame 3 all lie 1 m off (a wrong consensus no match
    contradicts); the re-matching's are honest."""
    honest = np.linalg.inv(honest_poses[3]) @ honest_poses[2]
    return corrupt(Odometry.from_default(config), honest, share=1.0, frame=3, calls=1)


def test_a_consecutive_pair_that_would_give_way_is_matched_again(highway: Path) -> None:
    sequence = open_sequence(highway)
    scans = [sequence[index].points for index in range(5)]
    honest = Odometry.from_default(frame_to_frame())
    honest_poses = [honest.register(p) for p in scans]
    paper = frame_to_frame()
    paper.motion_model.rematch_gap = None
    paper.motion_model.match_from_prediction_m = None
    gated = wrong_first_pair(paper, honest_poses)
    for points in scans:
        gated.register(points)
    assert gated.diagnostics[3].fallback == "implausible_motion"  # the prediction, as without re-matching
    odometry = wrong_first_pair(frame_to_frame(), honest_poses)
    poses = [odometry.register(p) for p in scans]
    assert odometry.diagnostics[3].fallback == "rematched_from_prediction"
    step = np.linalg.inv(poses[3]) @ poses[2]
    honest_step = np.linalg.inv(honest_poses[3]) @ honest_poses[2]
    truth = np.linalg.inv(sequence[3].pose) @ sequence[2].pose
    # Measured again from the scans: as close to the truth as the honest pair, far from the injected metre.
    assert registration_errors(step, truth).translation_mean < 0.05
    assert registration_errors(step, honest_step).translation_mean < 0.05
    assert [d.fallback for d in odometry.diagnostics[4:]] == [None]


def test_a_model_without_the_graphs_to_rematch_warns_and_bridges_gaps_as_the_paper(highway: Path, tmp_path: Path) -> None:
    shutil.copy(default_model_path() / "frame.onnx", tmp_path / "frame.onnx")
    with pytest.warns(UserWarning, match=r"no encoder.onnx or match.onnx: pairs across missing scans are not matched again"):
        odometry = Odometry(tmp_path, frame_to_frame())
    across_the_gap(highway, odometry)
    assert odometry.diagnostics[-1].rematch_rounds is None


def test_the_wide_window_from_the_prediction_takes_over_when_the_models_own_finds_nothing(highway: Path, tmp_path: Path) -> None:
    # Fault injection: the first re-matching pass returns noise (as when the prediction is too far off for the
    # model's window); the wide-window graph, started from the prediction, then leads the rounds.
    for graph in ("frame.onnx", "encoder.onnx", "match.onnx"):
        shutil.copy(default_model_path() / graph, tmp_path / graph)
    results = {}
    for name, model in (("with wide graph", default_model_path()), ("without", tmp_path)):
        odometry = Odometry(model, frame_to_frame())
        honest_match = odometry.matcher.match
        calls = []

        def noisy_first_round(reference, target, cells=None):  # type: ignore[no-untyped-def]
            flow, confidence = honest_match(reference, target, cells)
            if len(odometry.poses) == 2 + GAP:  # the scan after the gap: its own pair, then the rounds
                calls.append(1)
                if len(calls) == 2:
                    flow = np.random.default_rng(0).uniform(-40, 40, flow.shape).astype(np.float32)
            return flow, confidence

        odometry.matcher.match = noisy_first_round  # type: ignore[method-assign]
        motion, truth = across_the_gap(highway, odometry)
        results[name] = (odometry.diagnostics[-1], registration_errors(motion, truth), len(calls) - 1)
    found, errors, calls = results["with wide graph"]
    assert found.fallback == "rematched_from_prediction" and found.rematch_rounds is not None and found.rematch_rounds >= 2
    assert errors.translation_mean < 0.08 and errors.angular_mean < 0.3, errors
    assert calls >= 2  # the noisy pass, then the rounds after the wide one
    lost, lost_errors, calls = results["without"]
    assert lost.fallback in ("constant_velocity", "implausible_motion") and lost.rematch_rounds == 0 and calls == 1
    assert lost_errors.translation_mean > 0.1


@pytest.mark.parametrize("mapping", [False, True], ids=["dmlo", "mapping"])
def test_beyond_the_prediction_horizon_the_prediction_is_only_a_guess(highway: Path, mapping: bool) -> None:
    # A 4 s pause in the log (40 periods) after which the car has moved one frame on, as if it had stopped:
    # the prediction says 50 m; the scans say 1.3 m.
    sequence = open_sequence(highway)
    truth = np.linalg.inv(sequence[3].pose) @ sequence[2].pose
    errors = {}
    for horizon in (20, 100):
        config = frame_to_frame()
        config.motion_model.prediction_horizon = horizon
        config.mapping.enabled = mapping
        odometry = Odometry.from_default(config)
        for index, time in ((0, 0.0), (1, 0.1), (2, 0.2), (3, 4.2)):
            odometry.register(sequence[index].points, timestamp=time)
        assert odometry.diagnostics[3].gap == 40
        motion = np.linalg.inv(odometry.poses[3]) @ odometry.poses[2]
        errors[horizon] = registration_errors(motion, truth)
    # Judged against the 50 m guess, the true motion is implausible, and the guess wins.
    assert errors[100].translation_mean > 10
    assert errors[20].translation_mean < 0.05 and errors[20].angular_mean < 0.3, errors[20]


@pytest.mark.parametrize("gap", [0, -2, 1.5, True, "2"])
def test_a_bad_rematch_gap_is_refused_up_front(gap: object) -> None:
    config = frame_to_frame()
    config.motion_model.rematch_gap = gap  # type: ignore[assignment]
    with pytest.raises(ValueError, match=r"motion_model.rematch_gap: must be an integer >= 1"):
        Odometry.from_default(config)


def test_frames_are_counted_from_the_timestamps() -> None:
    def frames(clock: dmlo_rs.FrameClock, times: tuple[float | None, ...]) -> list[int]:
        return [clock.advance(t)[0] for t in times]

    clock = dmlo_rs.FrameClock()
    assert frames(clock, (0.0, 0.1, 0.2, 0.5, 0.6)) == [0, 1, 2, 5, 6]  # two scans dropped
    assert clock.period == pytest.approx(0.1)
    # Jitter of a few per cent is still one frame; an unstamped scan counts one; the first interval may
    # itself span a gap, the median of the later ones corrects the period.
    assert frames(dmlo_rs.FrameClock(), (10.0, 10.104, 10.199, 10.305, None, 10.498, 10.9)) == [0, 1, 2, 3, 4, 5, 9]
    assert frames(dmlo_rs.FrameClock(), (0.0, 0.7, 0.8, 0.9, 1.0, 1.1, 1.4)) == [0, 1, 2, 3, 4, 5, 8]
    unstamped = dmlo_rs.FrameClock()
    assert frames(unstamped, (None, None)) == [0, 1] and unstamped.period is None
    backwards = dmlo_rs.FrameClock()
    backwards.advance(1.0)
    assert backwards.advance(1.0) == (1, True)


def test_a_timestamp_not_after_the_previous_is_warned_once_and_a_bad_one_refused() -> None:
    odometry = Odometry.from_default(frame_to_frame())
    few = np.ones((10, 4), np.float32)  # bridged by the motion model: the clock alone is tested
    odometry.register(few, timestamp=1.0)
    odometry.register(few)
    with pytest.warns(TimestampWarning, match="not after the previous scan's 1.0: taken for the next frame"):
        odometry.register(few, timestamp=np.float32(1.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        odometry.register(few, timestamp=0.5)  # warned once
    assert [d.index for d in odometry.diagnostics] == [0, 1, 2, 3]
    for bad in (float("nan"), float("inf"), "0.1", True):
        with pytest.raises(ValueError, match="timestamp: expected a finite number"):
            odometry.register(few, timestamp=bad)  # type: ignore[arg-type]
    assert len(odometry.poses) == 4


def test_scans_dropped_in_time_alone_are_bridged_like_missing_files(highway: Path, tmp_path: Path) -> None:
    # The log kept scans 0–2 and 2 + GAP with their times: no file is missing, the timestamps say 6 scans are.
    sequence = open_sequence(highway)
    kept = [0, 1, 2, 2 + GAP]
    (tmp_path / "velodyne").mkdir()
    for new, old in enumerate(kept):
        shutil.copy(highway / "velodyne" / f"{old:06d}.bin", tmp_path / "velodyne" / f"{new:06d}.bin")
    times = (highway / "times.txt").read_text().split()
    (tmp_path / "times.txt").write_text("".join(f"{times[old]}\n" for old in kept))
    dropped = open_sequence(tmp_path)
    assert len(dropped) == 4 and dropped[3].timestamp == pytest.approx(float(times[2 + GAP]))

    summary = run_sequence(dropped, Odometry.from_default(frame_to_frame()), tmp_path / "run", progress=False)
    rows = [json.loads(line) for line in (tmp_path / "run" / "diagnostics.jsonl").read_text().splitlines()]
    assert [row["gap"] for row in rows] == [None, 1, 1, GAP]
    assert rows[3]["fallback"] == "rematched_from_prediction" and summary.fallbacks == {"rematched_from_prediction": 1}
    poses = np.loadtxt(tmp_path / "run" / "poses_kitti.txt").reshape(-1, 3, 4)
    assert len(poses) == 4  # one pose per scan given, none for the dropped ones
    last, before = (np.vstack([poses[i], [0, 0, 0, 1]]) for i in (3, 2))
    truth = np.linalg.inv(sequence[2 + GAP].pose) @ sequence[2].pose
    errors = registration_errors(np.linalg.inv(last) @ before, truth)
    assert errors.translation_mean < 0.08 and errors.angular_mean < 0.3, errors
    # Without the timestamps the same scans look consecutive: a 9 m step the prediction of one frame cannot
    # explain, so the pair gives way to it.
    blind = Odometry.from_default(frame_to_frame())
    for index in range(4):
        blind.register(dropped[index].points)
    assert blind.diagnostics[3].gap == 1 and blind.diagnostics[3].fallback in ("constant_velocity", "implausible_motion")


@pytest.mark.parametrize("horizon", [0, 2.5, None])
def test_a_bad_prediction_horizon_is_refused_up_front(horizon: object) -> None:
    config = frame_to_frame()
    config.motion_model.prediction_horizon = horizon  # type: ignore[assignment]
    with pytest.raises(ValueError, match=r"motion_model.prediction_horizon: must be an integer >= 1"):
        Odometry.from_default(config)
