"""DMLO odometry (§III): project → encode → match → decode, NMS, RANSAC, SVD → pose.

`Odometry.register` reads like the paper's pipeline: each step is one call into `dmlo_rs` or the
network, with the paper's section next to it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

import dmlo_rs
from dmlo.odometry.config import OdometryConfig
from dmlo.odometry.matcher import Features, Matcher, OnnxMatcher, default_model_path

Matrix4 = npt.NDArray[np.float64]


@dataclass
class FrameDiagnostics:
    """What happened to one scan: counts, the fallback taken, and the time of every stage in ms."""

    index: int
    num_points: int
    num_matches: int = 0
    num_candidates: int = 0
    num_inliers: int = 0
    inlier_ratio: float = 0.0
    fallback: str | None = None  # "constant_velocity" when RANSAC found too few inliers
    ndt_converged: bool | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "num_points": self.num_points,
            "num_candidates": self.num_candidates,
            "num_matches": self.num_matches,
            "num_inliers": self.num_inliers,
            "inlier_ratio": round(self.inlier_ratio, 4),
            "fallback": self.fallback,
            "ndt_converged": self.ndt_converged,
            "timings_ms": {k: round(v, 3) for k, v in self.timings_ms.items()},
        }


@dataclass
class PairResult:
    """The motion between a reference and a target scan: `T_tgt_ref` with `p_tgt = T p_ref` (Eq. 7)."""

    T_tgt_ref: Matrix4
    num_candidates: int
    num_matches: int
    num_inliers: int
    source_points: npt.NDArray[np.float64]
    target_points: npt.NDArray[np.float64]
    inliers: npt.NDArray[np.bool_]

    @property
    def inlier_ratio(self) -> float:
        return self.num_inliers / self.num_matches if self.num_matches else 0.0


@dataclass
class _Scan:
    range: npt.NDArray[np.float32]
    features: Features


class _Stopwatch:
    def __init__(self, timings: dict[str, float]) -> None:
        self._timings = timings
        self._last = time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self._timings[stage] = (now - self._last) * 1e3
        self._last = now


class Odometry:
    """Frame-to-frame DMLO odometry with the paper's motion model and optional NDT mapping.

    >>> odometry = Odometry.from_default()
    >>> for points in scans:               # N×4 float32: x, y, z, reflectance
    ...     T_world_lidar = odometry.register(points)
    """

    def __init__(self, model_path: str | Path, config: OdometryConfig | None = None) -> None:
        self.config = config or OdometryConfig()
        self.matcher: Matcher = OnnxMatcher(Path(model_path), threads=self.config.threads)
        self.cylinder = self.matcher.cylinder
        self.poses: list[Matrix4] = []
        self.diagnostics: list[FrameDiagnostics] = []
        self._previous: _Scan | None = None
        self._motion = np.eye(4)  # T_tgt_ref of the last pair, for the constant-velocity model
        self._map = self._make_map() if self.config.mapping.enabled else None

    @classmethod
    def from_default(cls, config: OdometryConfig | None = None) -> Odometry:
        """The bundled model, trained on simulated HDL-64E drives."""
        return cls(default_model_path(), config)

    # -- one scan -------------------------------------------------------------------------------

    def register(self, points: npt.ArrayLike, moving: npt.ArrayLike | None = None) -> Matrix4:
        """Adds the next scan and returns its pose `T_world_lidar` (the first scan is the world).

        `moving` is an optional per-point boolean mask of points on moving objects (§III-D-c); they
        are left out of matching.
        """
        cloud = _as_scan(points, "points")
        diagnostics = FrameDiagnostics(index=len(self.poses), num_points=len(cloud))
        watch = _Stopwatch(diagnostics.timings_ms)
        if moving is not None:
            cloud = cloud[~_as_mask(moving, len(cloud))]

        scan = self._encode(cloud)  # Eq. 1 + the Siamese feature net, once per scan
        watch.lap("encode")

        if self._previous is None:
            pose = np.eye(4)
        else:
            motion = self._estimate_motion(self._previous, scan, diagnostics, watch)
            pose = self.poses[-1] @ np.linalg.inv(motion)  # T_world_t = T_world_{t-1} · T⁻¹
            if self._map is not None:
                pose = self._refine_with_map(cloud, pose, diagnostics)
                watch.lap("ndt")
            self._motion = np.linalg.inv(pose) @ self.poses[-1]
        if self._map is not None:
            self._map.insert(_transform(cloud[:, :3], pose))
            watch.lap("map_update")

        self._previous = scan
        self.poses.append(pose)
        self.diagnostics.append(diagnostics)
        return pose.copy()

    def register_pair(
        self, reference: npt.ArrayLike, target: npt.ArrayLike, coarse_window: int | None = None
    ) -> PairResult:
        """The motion between two scans, without any motion model or map (`T_tgt_ref`)."""
        ref = self._encode(_as_scan(reference, "reference"))
        tgt = self._encode(_as_scan(target, "target"))
        return self._match_pair(ref, tgt)

    # -- the paper's steps ----------------------------------------------------------------------

    def _encode(self, cloud: npt.NDArray[np.float32]) -> _Scan:
        projection = dmlo_rs.project(cloud, self.cylinder)
        image = np.stack([projection.range, projection.reflectance])
        return _Scan(range=projection.range, features=self.matcher.encode(image))

    def _match_pair(self, ref: _Scan, tgt: _Scan, watch: _Stopwatch | None = None) -> PairResult:
        flow, confidence = self.matcher.match(ref.features, tgt.features)  # §III-C
        if watch:
            watch.lap("match")
        m = self.config.matching
        decoded = dmlo_rs.decode_matches(
            ref.range, tgt.range, flow, confidence, self.cylinder, min_confidence=m.min_confidence
        )
        keep = dmlo_rs.nms(  # §III-D-a
            decoded.cells[:, 0], decoded.cells[:, 1], decoded.confidences, m.nms_radius, m.max_matches
        )
        src, dst = decoded.source_points[keep], decoded.target_points[keep]
        if watch:
            watch.lap("decode_nms")
        r = self.config.ransac
        if len(src) >= 3:
            ransac = dmlo_rs.ransac_rigid(  # §III-D-b: RANSAC around Eq. 12–14
                src, dst, threshold=r.threshold, confidence=r.confidence,
                max_iterations=r.max_iterations, seed=r.seed,
            )
            transform, inliers, num_inliers = ransac.transform, ransac.inliers, ransac.num_inliers
        else:
            transform, inliers, num_inliers = np.eye(4), np.zeros(len(src), bool), 0
        if watch:
            watch.lap("ransac")
        return PairResult(
            T_tgt_ref=np.asarray(transform, dtype=np.float64),
            num_candidates=len(decoded.confidences),
            num_matches=len(src),
            num_inliers=int(num_inliers),
            source_points=src,
            target_points=dst,
            inliers=np.asarray(inliers, dtype=bool),
        )

    def _estimate_motion(
        self, ref: _Scan, tgt: _Scan, diagnostics: FrameDiagnostics, watch: _Stopwatch
    ) -> Matrix4:
        try:
            pair: PairResult | None = self._match_pair(ref, tgt, watch)
        except ValueError:  # degenerate or all-outlier matches: the motion model takes over
            pair = None
        if pair is not None:
            diagnostics.num_candidates = pair.num_candidates
            diagnostics.num_matches = pair.num_matches
            diagnostics.num_inliers = pair.num_inliers
            diagnostics.inlier_ratio = pair.inlier_ratio
        if pair is None or pair.num_inliers < self.config.motion_model.min_inliers:
            diagnostics.fallback = "constant_velocity"  # §III-D-c motion model
            return self._motion.copy()
        return pair.T_tgt_ref

    # -- mapping --------------------------------------------------------------------------------

    def _make_map(self) -> Any:
        c = self.config.mapping
        return dmlo_rs.NdtMap(voxel_size=c.voxel_size, max_scans=c.max_scans)

    def _refine_with_map(
        self, cloud: npt.NDArray[np.float32], pose: Matrix4, diagnostics: FrameDiagnostics
    ) -> Matrix4:
        assert self._map is not None
        try:
            result = self._map.align(
                cloud[:, :3], pose, max_iterations=self.config.mapping.max_iterations
            )
        except ValueError:
            diagnostics.ndt_converged = False
            return pose
        diagnostics.ndt_converged = bool(result.converged)
        return np.asarray(result.transform, dtype=np.float64) if result.converged else pose


def _as_scan(points: npt.ArrayLike, name: str) -> npt.NDArray[np.float32]:
    cloud = np.asarray(points)
    if cloud.ndim != 2 or cloud.shape[1] not in (3, 4):
        raise ValueError(f"{name}: expected an N×4 (or N×3) array of x, y, z[, reflectance], got shape {cloud.shape}")
    if not np.issubdtype(cloud.dtype, np.floating):
        raise TypeError(f"{name}: expected floating-point points, got dtype {cloud.dtype}")
    if cloud.shape[1] == 3:
        cloud = np.concatenate([cloud, np.zeros((len(cloud), 1), cloud.dtype)], axis=1)
    return np.ascontiguousarray(cloud, dtype=np.float32)


def _as_mask(mask: npt.ArrayLike, count: int) -> npt.NDArray[np.bool_]:
    values = np.asarray(mask)
    if values.shape != (count,):
        raise ValueError(f"moving: expected a mask of {count} booleans, got shape {values.shape}")
    return values.astype(bool)


def _transform(xyz: npt.NDArray[np.floating], T: Matrix4) -> npt.NDArray[np.float64]:
    return xyz.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
