"""`PairResult`, the motion found between two scans: made by the pipeline (`Odometry.register_pair`,
`pose_from_flow`) and by the large-motion search (`large_motion`), so it lives apart from both."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

Matrix4 = npt.NDArray[np.float64]


@dataclass
class PairResult:
    """The motion between a reference and a target scan: `T_tgt_ref` with `p_tgt = T p_ref` (Eq. 7)."""

    T_tgt_ref: Matrix4
    num_matches: int
    num_inliers: int
    source_points: npt.NDArray[np.float64]
    target_points: npt.NDArray[np.float64]
    inliers: npt.NDArray[np.bool_]
    rounds: int = 1  # with `large_motion`: matching rounds whose estimate was kept (`LargeMotionConfig`)
    inlier_votes: float | None = None  # the inliers' summed votes above the floor when RANSAC voted (`ransac.vote_by_tilt`)
    map_refined: bool | None = None  # `register_pair` with mapping: NDT against the reference converged (None: not tried)

    @property
    def inlier_ratio(self) -> float:
        return self.num_inliers / self.num_matches if self.num_matches else 0.0
