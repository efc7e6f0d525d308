"""Registration of scans far apart, with no initial guess (§IV-D, and beyond it: see `LargeMotionConfig`).

The wide-window graph matches the pair from several starts — the reference moved as if the target lay
some metres ahead and turned by some yaw — and the start whose matches have the most RANSAC inliers goes
on: the reference moved by the estimate so far is matched again with the model's own window until a round
corrects less than the configured steps.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from dmlo.metrics.trajectory import pose_difference
from dmlo.odometry.config import LargeMotionConfig
from dmlo.odometry.matcher import Features, Matcher
from dmlo.odometry.pair import PairResult

Matrix4 = npt.NDArray[np.float64]
Image = npt.NDArray[np.float32]


def register_far(
    reference: npt.NDArray[np.float32],
    tgt_image: Image,
    tgt_range: Image,
    *,
    wide: Matcher,
    matcher: Matcher,
    project: Callable[[npt.NDArray[np.float32]], tuple[Image, Image, Image]],
    match: Callable[..., PairResult],
    config: LargeMotionConfig,
    min_inliers: int,
    starts: list[Matrix4] | None = None,
) -> PairResult:
    """`T_tgt_ref` of the N×4 `reference` scan and the projected target: `wide` (the wide-window graph) from
    every start (`T_tgt_ref` guesses; default the configured search), then rounds of `matcher` (the model's
    own window), `project` and `match` the odometry's projection and back end. A round with fewer than
    `min_inliers` inliers keeps the estimate before it. RANSAC counts inliers here, one vote each
    (`ransac.vote_by_tilt` is for consecutive scans, whose road rings lock): starts and rounds are compared
    by their inlier counts, and from a start near the motion the road's matches are as right as any."""
    best: tuple[PairResult, Matrix4] | None = None
    for start in starts or search_starts(config.search_ahead_m, config.search_yaw_deg):
        ref_image, ref_range, _ = project(moved(reference, start))
        output = wide.frame(tgt_image, matcher.encode(ref_image))
        assert output.flow is not None and output.confidence is not None
        pair = match(ref_range, tgt_range, output.flow, output.confidence, tilt_votes=False)
        if best is None or pair.num_inliers > best[0].num_inliers:
            best = (pair, start)
    assert best is not None, "at least one start (checked with the config)"
    refined = rematch(
        reference, best[0].T_tgt_ref @ best[1], tgt_range, output.features, rounds=range(2, config.max_rounds + 1),
        last_correction=best[0].T_tgt_ref, matcher=matcher, project=project, match=match, config=config,
        min_inliers=min_inliers,
    )
    return refined or in_given_frames(best[0], best[1], rounds=1)


def rematch(
    reference: npt.NDArray[np.float32],
    estimate: Matrix4,
    tgt_range: Image,
    tgt_features: Features,
    *,
    rounds: range,
    last_correction: Matrix4 | None,
    matcher: Matcher,
    project: Callable[[npt.NDArray[np.float32]], tuple[Image, Image, Image]],
    match: Callable[..., PairResult],
    config: LargeMotionConfig,
    min_inliers: int,
    tilt_votes: bool = False,
) -> PairResult | None:
    """Rounds of matching the reference moved by the `estimate` so far (`T_tgt_ref`) against the target's
    features with the model's own window, until a round — or the `last_correction` that led to `estimate` —
    corrects less than the configured steps. None when not one round kept `min_inliers` inliers: a round with
    fewer lost the scene, and the estimate before it is the better one. `tilt_votes`: RANSAC votes as for
    consecutive scans (`ransac.vote_by_tilt`), the moved reference's own points giving the surfaces."""
    result: PairResult | None = None
    correction = last_correction
    for round_ in rounds:
        if correction is not None:
            moved_m, turned_deg = pose_difference(np.eye(4), correction)
            if moved_m < config.min_step and turned_deg < config.min_step_deg:
                break
        ref_image, ref_range, ref_points = project(moved(reference, estimate))
        flow, confidence = matcher.match(matcher.encode(ref_image), tgt_features)
        pair = match(ref_range, tgt_range, flow, confidence, ref_points=ref_points, tilt_votes=tilt_votes)
        if pair.num_inliers < min_inliers:
            break
        result, correction = in_given_frames(pair, estimate, rounds=round_), pair.T_tgt_ref
        estimate = result.T_tgt_ref
    return result


def search_starts(ahead_m: tuple[float, ...], yaw_deg: tuple[float, ...]) -> list[Matrix4]:
    """The guesses `T_tgt_ref` of a target `ahead` metres along the reference's x axis, turned by `yaw`."""
    starts: list[Matrix4] = []
    for yaw in yaw_deg:
        for ahead in ahead_m:
            cos, sin = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
            T_ref_tgt = np.eye(4)
            T_ref_tgt[:2, :2] = [[cos, -sin], [sin, cos]]
            T_ref_tgt[0, 3] = ahead
            starts.append(np.linalg.inv(T_ref_tgt).astype(np.float64))
    return starts


def in_given_frames(pair: PairResult, start: Matrix4, rounds: int) -> PairResult:
    """A pair matched with the reference moved by `start`, as the motion between the scans given: the
    motion composed with `start`, the matches' reference points moved back."""
    back = np.linalg.inv(start)
    return dataclasses.replace(
        pair,
        T_tgt_ref=pair.T_tgt_ref @ start,
        source_points=pair.source_points @ back[:3, :3].T + back[:3, 3],
        rounds=rounds,
    )


def moved(cloud: npt.NDArray[np.float32], transform: Matrix4) -> npt.NDArray[np.float32]:
    """An N×4 scan with its points moved by `transform` (reflectance kept)."""
    if np.array_equal(transform, np.eye(4)):
        return cloud
    out = cloud.copy()
    # In float32, as the points are stored (a float64 product and the casts around it took several times as
    # long on every frame matched from the prediction), and term by term in the crate's order
    # (`odometry::pipeline`'s moved cloud): a matrix product's summation order and fused multiply-adds round
    # differently, and the two odometries must give the same poses.
    m = transform[:3].astype(np.float32)
    x, y, z = cloud[:, 0], cloud[:, 1], cloud[:, 2]
    for axis in range(3):
        out[:, axis] = x * m[axis, 0] + y * m[axis, 1] + z * m[axis, 2] + m[axis, 3]
    return out
