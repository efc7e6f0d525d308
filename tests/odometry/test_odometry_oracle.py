"""The geometric half of the pipeline alone: with the ground-truth flow of Eq. 5–8 in place of the network,
decoding, NMS, RANSAC and the SVD solve must recover the simulator's motion to within centimetres."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import dmlo_rs
from dmlo.datasets import open_sequence
from dmlo.metrics import registration_errors
from dmlo.odometry import Odometry
from dmlo.odometry.matcher import Features, FrameOutput
from dmlo.simulator import simulate_sequence
from support import frame_to_frame


class OracleMatcher:
    """Answers every frame with the exact ground-truth flow of the known motion, confidence 1."""

    def __init__(self, motions: list[np.ndarray]) -> None:
        self.path = Path("oracle")
        self.cylinder = dmlo_rs.CylinderConfig.kitti()
        self._motions = iter(motions)  # T_tgt_ref of each consecutive pair

    def frame(self, image: np.ndarray, previous: Features | None) -> FrameOutput:
        features = Features(coarse=image[:1], refine=image[:1])  # the range image stands in
        if previous is None:
            return FrameOutput(features, None, None)
        flow, valid = dmlo_rs.ground_truth_flow(previous.refine[0], image[0], next(self._motions), self.cylinder)
        confidence = valid.astype(np.float32)
        return FrameOutput(features, flow, confidence)


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("drive")
    simulate_sequence(out, frames=6, seed=21, progress=False)
    return out


def test_ground_truth_flow_recovers_the_motion(drive: Path) -> None:
    sequence = open_sequence(drive)
    assert sequence.poses is not None
    truth = [np.linalg.inv(b) @ a for a, b in zip(sequence.poses[:-1], sequence.poses[1:])]
    odometry = Odometry.from_default(frame_to_frame())
    odometry.matcher = OracleMatcher(truth)
    odometry.cylinder = odometry.matcher.cylinder
    for index in range(len(sequence)):
        odometry.register(sequence[index].points)
    assert all(d.fallback is None for d in odometry.diagnostics)
    estimated = [np.linalg.inv(b) @ a for a, b in zip(odometry.poses[:-1], odometry.poses[1:])]
    errors = registration_errors(np.stack(estimated), np.stack(truth))
    # The matches carry the cylinder grid's quantisation and 2 cm range noise, RANSAC averages them out.
    assert errors.translation_max < 0.03, errors
    assert errors.angular_max < 0.1, errors
    assert min(d.inlier_ratio for d in odometry.diagnostics[1:]) > 0.5


def test_pose_from_flow_is_the_back_end_alone(drive: Path) -> None:
    # The public step-by-step API: project both scans, hand any flow to the back end.
    sequence = open_sequence(drive)
    ref, tgt = sequence[2], sequence[3]
    assert ref.pose is not None and tgt.pose is not None
    T_tgt_ref = np.linalg.inv(tgt.pose) @ ref.pose
    odometry = Odometry.from_default(frame_to_frame())
    ref_image, ref_range = odometry.project(ref.points)
    _, tgt_range = odometry.project(tgt.points)
    assert ref_image.shape == (2, *ref_range.shape) and np.array_equal(ref_image[0], ref_range)
    flow, valid = dmlo_rs.ground_truth_flow(ref_range, tgt_range, T_tgt_ref, odometry.cylinder)
    pair = odometry.pose_from_flow(ref_range, tgt_range, flow, valid.astype(np.float64))
    errors = registration_errors(pair.T_tgt_ref[None], T_tgt_ref[None])
    assert errors.translation_max < 0.03 and errors.angular_max < 0.1, errors
    assert pair.num_matches == odometry.config.matching.max_matches and pair.inlier_ratio > 0.5
    with pytest.raises(ValueError, match="points"):
        odometry.project(np.zeros((5, 2), dtype=np.float32))
