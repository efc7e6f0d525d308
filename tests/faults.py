"""Fault injection in the network, for the tests of what the odometry does when a pair's matches lie: the
odometry's per-frame loop runs in the crate, so a fault enters where a real one would, in the flow."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

import dmlo_rs
from dmlo.odometry import Odometry


@dataclass
class Encoded:
    """A scan's features, with the range image the fault's flow is computed from."""

    range: np.ndarray
    features: Any


class CorruptedFlow:
    """The odometry's own matcher, except that while it registers frame `frame` a `share` of the cells (whole
    sectors of 32 columns, each cell with the confidence the network gave it) match as if the scans had moved
    by `honest` (`T_tgt_ref` of frame `frame - 1` to `frame`) with `shift` metres more — the wrong consensus of
    a network misreading the scene once the share outnumbers the true matches; with `share` 1 no match agrees
    with the true motion (the cells the wrong motion cannot carry onto the target scan lose their confidence). `calls`: only that many of the frame's first matchings lie (None: every one)."""

    def __init__(
        self,
        odometry: Odometry,
        honest: np.ndarray,
        share: float,
        frame: int,
        shift: tuple[float, float, float] = (1.0, 0.0, 0.0),
        calls: int | None = None,
    ) -> None:
        inner = odometry.matcher
        self.path, self.cylinder = inner.path, inner.cylinder
        self.matching_stage, self.uses_reflectance = inner.matching_stage, inner.uses_reflectance  # type: ignore[attr-defined]
        self._inner, self._odometry = inner, odometry
        self._wrong = np.array(honest, dtype=np.float64)
        self._wrong[:3, 3] += shift
        self._share, self._frame, self._calls_left = share, frame, calls

    def encode(self, image: np.ndarray) -> Encoded:
        return Encoded(image[0].copy(), self._inner.encode(image))

    def match(self, reference: Encoded, target: Encoded) -> tuple[np.ndarray, np.ndarray]:
        flow, confidence = self._inner.match(reference.features, target.features)
        if len(self._odometry.poses) != self._frame or self._calls_left == 0:
            return flow, confidence
        if self._calls_left is not None:
            self._calls_left -= 1
        wrong_flow, valid = dmlo_rs.ground_truth_flow(reference.range, target.range, self._wrong, self.cylinder)
        sectors = np.random.default_rng(0).random(valid.shape[1] // 32 + 1) < self._share
        cells = valid & np.repeat(sectors, 32)[None, : valid.shape[1]]
        if self._share >= 1:  # the cells the wrong motion does not reach match nothing either
            confidence = np.where(cells, confidence, np.float32(0))
        return np.where(cells, wrong_flow, flow).astype(np.float32), confidence


def corrupt(odometry: Odometry, honest: np.ndarray, share: float, frame: int, **settings: Any) -> Odometry:
    """`odometry` (before its first scan) over `CorruptedFlow`."""
    odometry.matcher = CorruptedFlow(odometry, honest, share, frame, **settings)  # type: ignore[assignment]
    return odometry
