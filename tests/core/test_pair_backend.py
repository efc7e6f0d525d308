"""`dmlo_rs.match_pair`, the crate's back end of one pair, against the same chain composed in numpy from the
crate's separate steps (coherence, decoding with NMS, tilt votes, voxel crowding, RANSAC) — the chain
`dmlo.Odometry` ran in Python before it moved into the crate — on a real KITTI pair matched by the bundled
model; and its arguments."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import dmlo_rs
from dmlo.datasets import open_sequence
from dmlo.odometry import Odometry
from support import projected


def composed_chain(ref_range, tgt_range, flow, confidence, cylinder, *, ref_points, leave_out, tilt_votes,
                   coherence_px, tilt_vote_floor, vote_voxel):
    """The pair's motion by the crate's separate steps, in numpy: (transform, inliers, inlier votes)."""
    if coherence_px is not None:
        confidence = dmlo_rs.coherent_confidence(flow, confidence, ref_range, cylinder, radius=2, scale_px=coherence_px)
    matches = dmlo_rs.decode_matches(ref_range, tgt_range, flow, confidence, cylinder, mask=leave_out, top_n=1000,
                                     nms_radius=1)
    votes = tilt = None
    if tilt_votes and tilt_vote_floor is not None:
        if ref_points is None:  # the virtual points at the cells' centres
            rows, cols = np.divmod(np.arange(ref_range.size, dtype=np.float64), ref_range.shape[1])
            ref_points = dmlo_rs.unproject(rows, cols, ref_range.reshape(-1).astype(np.float64), cylinder)
            ref_points[ref_range.reshape(-1) <= 0] = np.nan
            ref_points = ref_points.astype(np.float32).reshape(*ref_range.shape, 3)
        votes = tilt = dmlo_rs.horizontal_votes(ref_points, matches.cells[:, 0], matches.cells[:, 1], cylinder,
                                                floor=tilt_vote_floor)
    if tilt_votes and vote_voxel is not None:
        keys = np.floor(matches.source / vote_voxel).astype(np.int64)
        _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        votes = (1.0 if votes is None else votes) / np.sqrt(counts[inverse.ravel()])
    ransac = dmlo_rs.ransac_rigid(matches.source, matches.target, threshold=0.1, confidence=0.999, max_iterations=1000,
                                  seed=0, refit="ray_noise", range_ratio=4.0, bearing_threshold_deg=0.2, votes=votes)
    inlier_votes = None if tilt is None else float((tilt[ransac.inliers] - tilt_vote_floor).sum())
    return ransac.transform, ransac.inliers, inlier_votes


@pytest.fixture(scope="module")
def real_pair(shared_data: Path):
    """Two consecutive real KITTI scans (odometry 03), their images and the bundled model's flow."""
    sequence = open_sequence(shared_data / "kitti_real" / "odometry_03")
    odometry = Odometry.from_default()
    reference, target = sequence[3].points, sequence[4].points
    ref_image, ref_range, ref_points = projected(odometry, reference)
    tgt_image, tgt_range, _ = projected(odometry, target)
    output = odometry.matcher.frame(tgt_image, odometry.matcher.encode(ref_image))
    return odometry.cylinder, ref_range, tgt_range, output.flow, output.confidence, ref_points


@pytest.mark.parametrize(
    "points, leave_left, tilt_votes, coherence_px, tilt_vote_floor, vote_voxel",
    [
        (True, False, True, 0.5, 0.05, 2.0),  # the odometry's defaults
        (False, False, True, 0.5, 0.05, 2.0),  # virtual points
        (True, True, True, None, 0.1, None),  # a mask, no coherence, tilt votes alone
        (True, False, True, 0.5, None, 3.0),  # crowding alone
        (True, False, False, 0.5, 0.05, 2.0),  # one vote each
    ],
)
def test_the_crates_pair_equals_the_chain_of_its_steps(
    real_pair, points, leave_left, tilt_votes, coherence_px, tilt_vote_floor, vote_voxel
) -> None:
    cylinder, ref_range, tgt_range, flow, confidence, ref_points = real_pair
    leave_out = None
    if leave_left:
        leave_out = np.zeros(ref_range.shape, dtype=bool)
        leave_out[:, : ref_range.shape[1] // 2] = True
    settings = dict(ref_points=ref_points if points else None, leave_out=leave_out, tilt_votes=tilt_votes,
                    coherence_px=coherence_px, tilt_vote_floor=tilt_vote_floor, vote_voxel=vote_voxel)
    pair = dmlo_rs.match_pair(ref_range, tgt_range, flow, confidence, cylinder, **settings)
    transform, inliers, inlier_votes = composed_chain(ref_range, tgt_range, flow, confidence, cylinder, **settings)
    np.testing.assert_array_equal(pair.transform, transform)
    np.testing.assert_array_equal(pair.inliers, inliers)
    assert pair.num_inliers == inliers.sum() > 100
    if inlier_votes is None:
        assert pair.inlier_votes is None
    else:
        assert pair.inlier_votes == pytest.approx(inlier_votes, rel=1e-12)
    if leave_out is not None:
        assert not leave_out[pair.cells[:, 0], pair.cells[:, 1]].any()


def test_a_pair_without_matches_is_the_identity_and_bad_arguments_are_named(real_pair) -> None:
    cylinder, ref_range, tgt_range, flow, confidence, _ = real_pair
    nothing = dmlo_rs.match_pair(ref_range, tgt_range, flow, np.zeros_like(confidence), cylinder, coherence_px=None,
                                 min_confidence=0.5)
    assert np.array_equal(nothing.transform, np.eye(4)) and nothing.num_inliers == 0 and len(nothing.source) == 0
    for arguments, name in [
        (dict(max_matches=2), "max_matches"),
        (dict(tilt_vote_floor=0.0), "tilt_vote_floor"),
        (dict(vote_voxel=-1.0), "vote_voxel"),
        (dict(refit="icp"), "refit"),
        (dict(leave_out=np.zeros(ref_range.shape, dtype=np.uint8)), "leave_out"),
        (dict(ref_points=np.zeros((2, 3), dtype=np.float32)), "ref_points"),
        (dict(coherence_radius=-1), "coherence_radius"),
    ]:
        with pytest.raises((ValueError, TypeError), match=name):
            dmlo_rs.match_pair(ref_range, tgt_range, flow, confidence, cylinder, **arguments)
    with pytest.raises(ValueError, match="flow"):
        dmlo_rs.match_pair(ref_range, tgt_range, flow[:, :-1], confidence, cylinder)
