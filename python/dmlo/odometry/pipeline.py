"""DMLO odometry (§III): project → encode → match → decode, NMS, RANSAC, SVD → pose.

`Odometry.register` runs the crate's per-frame loop (`dmlo_rs.Odometry`, `odometry::pipeline` in Rust,
which Rust users run without Python) over the networks in onnxruntime: the scan's checks, the reflectance
scale, the moving-object step, the motion model, the local map and the notices are the crate's; this module
opens the model's graphs, hands numpy arrays over and turns the crate's notices into Python warnings.
`register_pair`, `project` and `pose_from_flow` give the paper's steps one at a time.
"""

from __future__ import annotations

import functools
import json
import threading
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

import dmlo_rs
from dmlo.odometry.config import OdometryConfig
from dmlo.odometry.notices import warn
from dmlo.odometry.pair import PairResult
from dmlo.odometry.matcher import (
    FrameMatcherAdapter,
    Matcher,
    OnnxMatcher,
    available_cores,
    default_model_path,
    wide_graph_path,
)
from dmlo.odometry.moving import MovingObjectDetector, moving_objects_graph

Matrix4 = npt.NDArray[np.float64]


# What happened to one scan: the crate's record (`odometry::pipeline::FrameDiagnostics`), its fields as
# attributes, `to_dict()` its line of diagnostics.jsonl (docs/odometry.md lists the fields).
FrameDiagnostics = dmlo_rs.FrameDiagnostics


def _one_thread_at_a_time(method: Any) -> Any:
    """`method` of an `Odometry`, refused with a clear error while another thread runs one of them on the same
    odometry (the crate's loop would answer "Already borrowed")."""

    @functools.wraps(method)
    def guarded(self: Odometry, *args: Any, **kwargs: Any) -> Any:
        if not self._in_use.acquire(blocking=False):
            raise RuntimeError(
                f"Odometry.{method.__name__}: another thread is using this Odometry; an Odometry is not shared "
                "between threads (its scans are one drive, in order): use one per thread"
            )
        try:
            return method(self, *args, **kwargs)
        finally:
            self._in_use.release()

    return guarded


class Odometry:
    """DMLO odometry with the paper's motion model and, by default, its scan-to-map NDT refinement
    (`mapping.enabled = False`: frame-to-frame DMLO).

    >>> odometry = Odometry.from_default()
    >>> for points in scans:               # N×4 float32: x, y, z, reflectance
    ...     T_world_lidar = odometry.register(points)

    The config is read when the odometry is built (and checked whole then): set it before.
    """

    def __init__(self, model_path: str | Path, config: OdometryConfig | None = None) -> None:
        if config is not None and not isinstance(config, OdometryConfig):
            raise TypeError(
                f"config: expected an OdometryConfig or None (the defaults), got {type(config).__name__}; "
                "OdometryConfig.from_dict(dict) or OdometryConfig.load(path) reads one"
            )
        self._in_use = threading.Lock()
        self.config = config or OdometryConfig()
        self.config.validate()  # the whole schema again: a config's fields may change after loading
        matcher = OnnxMatcher(
            Path(model_path),
            threads=self.config.threads,
            match_graph=self.config.matching.symmetric,
            matching_stage=self.config.matching_stage,
        )
        self.poses: list[Matrix4] = []
        self.diagnostics: list[FrameDiagnostics] = []
        # The range-only model beside this one (run by the crate from the first scan without usable reflectance
        # on), unless this one is range-only. It opens now, so that a broken one fails before the first scan.
        folder = matcher.path.parent / dmlo_rs.ModelFolder.RANGE_ONLY
        beside = matcher.uses_reflectance and (folder / dmlo_rs.ModelFolder.FRAME).is_file()
        self._range_only = self._open_range_only(folder, matcher) if beside else None
        self._use_matcher(matcher)

    @property
    def matcher(self) -> Matcher:
        """The network the odometry runs (the range-only model from the first scan without reflectance on)."""
        if self._range_only is not None and self._loop.runs_range_only:
            return self._range_only
        return self._matcher

    @matcher.setter
    def matcher(self, matcher: Matcher) -> None:
        """Another matcher (`dmlo.odometry.matcher.Matcher`) in place of the model's, before the first scan."""
        if self.poses:
            raise RuntimeError("matcher: replaced after the first scan; make a new Odometry")
        self._use_matcher(matcher)

    def _use_matcher(self, matcher: Matcher) -> None:
        """`matcher` run by the crate's per-frame loop (`dmlo_rs.Odometry`), made again over it."""
        self._matcher = matcher
        self.cylinder = matcher.cylinder
        settings = self.config.to_dict()
        if self._available_rematch_gap() is None:  # the graphs it needs are missing (warned)
            settings["motion_model"].update(rematch_gap=None, match_from_prediction_m=None, start_check_m=None)
        self._loop_matcher = FrameMatcherAdapter(matcher, self.config.threads, self.config.matching_stage)
        range_only = None if self._range_only is None else FrameMatcherAdapter(
            self._range_only, self._beside_threads(), self.config.matching_stage
        )
        # Scans without reflectance and no range-only model run on zeros, with the crate's notice that their
        # poses cannot be trusted (the crate alone would refuse them).
        self._loop = dmlo_rs.Odometry(
            self._loop_matcher, json.dumps(settings), range_only=range_only, allow_zero_reflectance=True,
            moving_objects=self._open_moving_objects(),
        )

    def _open_moving_objects(self) -> MovingObjectDetector | None:
        """The moving-object network beside the model, when `moving_objects.detect` asks for it and it is there."""
        graph = moving_objects_graph(self._matcher.path) if self.config.moving_objects.detect else None
        return None if graph is None else MovingObjectDetector(graph, threads=self._beside_threads())

    def _beside_threads(self) -> int:
        """`threads` for the graphs opened beside the model, bounded to the cores without a second warning
        (the model's matcher already gave one)."""
        return min(self.config.threads, available_cores())

    def _available_rematch_gap(self) -> int | None:
        """`motion_model.rematch_gap`, or None with a warning when the model lacks the graphs it needs."""
        motion = self.config.motion_model
        graphs = (dmlo_rs.ModelFolder.ENCODER, dmlo_rs.ModelFolder.MATCH)
        missing = [name for name in graphs if not self._matcher.path.with_name(name).is_file()]
        moved = (motion.rematch_gap, motion.match_from_prediction_m, motion.start_check_m)
        if missing and any(setting is not None for setting in moved):
            warnings.warn(
                f"{self._matcher.path.parent} has no {' or '.join(missing)}: pairs across missing scans are not matched "
                "again from the prediction (motion_model.rematch_gap), nor pairs beyond the network's window "
                "(motion_model.match_from_prediction_m), nor the first pair from other starts "
                "(motion_model.start_check_m); `dmlo export CHECKPOINT --out DIR` writes every graph",
                stacklevel=4,
            )
            return None
        return motion.rematch_gap

    def _open_range_only(self, folder: Path, model: OnnxMatcher) -> OnnxMatcher:
        """The range-only model beside `model`, checked like it and by the crate's rule for a range-only model."""
        matcher = OnnxMatcher(
            folder, threads=self._beside_threads(), match_graph=self.config.matching.symmetric,
            matching_stage=self.config.matching_stage,
        )
        matcher.metadata.check_range_only_for(model.metadata, str(matcher.path), str(model.path))
        return matcher

    @classmethod
    def from_default(cls, config: OdometryConfig | None = None) -> Odometry:
        """The bundled model, trained on simulated HDL-64E drives."""
        return cls(default_model_path(), config)

    # -- one scan -------------------------------------------------------------------------------

    @_one_thread_at_a_time
    def register(
        self,
        points: npt.ArrayLike,
        moving: npt.ArrayLike | None = None,
        timestamp: float | None = None,
        point_times: npt.ArrayLike | None = None,
    ) -> Matrix4:
        """Adds the next scan and returns its pose `T_world_lidar` (the first scan is the world).

        `points`: N×4 (x, y, z, reflectance) or N×3 floating-point. `moving` is an optional per-point
        boolean mask of points on moving objects (§III-D-c); they are left out of matching. Without it,
        the moving-object network beside the model flags them (`moving_objects`). `timestamp` (seconds,
        or any increasing unit) lets the motion model see scans the sensor or the log dropped: a scan two
        median sensor periods after the previous one comes after one missing scan. With
        `config.deskew.enabled`, `point_times` (one per point, in sensor periods, 0 at the moment the pose
        refers to, e.g. −0.5…0.5 over a sweep centred on it) says when each point was measured; without it
        the time comes from the point's azimuth. Points at the origin (no return) or farther than 1 km are
        left out, as non-finite rows are; a scan fewer than half of whose returns lie 0.01 m to 1 km from the
        sensor (millimetres, a world frame) raises ValueError. A scan with fewer than `min_points` points left
        is not matched: its pose comes from the motion model and the diagnostics say so.

        Every step runs in the crate (`dmlo_rs.Odometry`, `odometry::pipeline` in Rust), the networks in
        onnxruntime; what the crate says about the scans (the reflectance scale, a sensor the model was not
        made for, timestamps going back) comes as warnings (`dmlo.odometry.notices`).
        """
        cloud = _as_scan(points, "points")
        times = None if point_times is None else _as_point_times(point_times, len(cloud))
        mask = None if moving is None else _as_mask(moving, len(cloud))
        pose = self._loop.register(cloud, moving=mask, timestamp=timestamp, point_times=times)
        return self._record(pose, self._newest_diagnostics())

    @_one_thread_at_a_time
    def reset(self) -> None:
        """Forgets the drive: the next scan is the world again, with a fresh motion model, local map, clock
        and reflectance scale; the model and the config stay."""
        self._loop.reset()
        self.poses.clear()
        self.diagnostics.clear()

    @_one_thread_at_a_time
    def predict_skipped(self, reason: str = "unreadable_scan") -> Matrix4:
        """Records a scan that could not be read: its pose comes from the motion model."""
        return self._record(self._loop.predict_skipped(reason), self._newest_diagnostics())

    def _newest_diagnostics(self) -> FrameDiagnostics:
        """The crate's diagnostics of the newest frame, its notices said as warnings (where the frame graph
        encodes a scan while matching it, `matching_stage` "graph", the crate counts both as the network)."""
        diagnostics = self._loop.last_diagnostics
        assert diagnostics is not None  # a frame was just recorded
        warn([(notice["kind"], notice["message"]) for notice in diagnostics.notices], stacklevel=4)
        return diagnostics

    def _record(self, pose: Matrix4, diagnostics: FrameDiagnostics) -> Matrix4:
        self.poses.append(pose)
        self.diagnostics.append(diagnostics)
        return pose.copy()

    @_one_thread_at_a_time
    def register_pair(
        self, reference: npt.ArrayLike, target: npt.ArrayLike, large_motion: bool = False
    ) -> PairResult:
        """The motion `T_tgt_ref` between two scans, with no motion model or initial guess.

        With `mapping.enabled` (the default), a consecutive pair's motion is refined by NDT of the target
        against the reference scan as its map (`dmlo_rs.LocalMap.refine_pair`), when RANSAC found at least
        `motion_model.min_inliers` inliers; `map_refined` says whether it converged. A pair that moved less
        than `mapping.ring_lock_distance` is aligned as a scan near its keyframe is (its upright surfaces
        first: the reference's ground rings would hold it together), and a pair that stands still by
        projective point-to-plane ICP (NDT's voxels leave millimetres where the planes are exact; a scan with
        itself is the identity). `large_motion`
        matches with the model's wide-window graph (the paper's D = 40 at inference,
        §IV-D) for scans far apart, e.g. several frames or metres, and then again with the reference moved
        by the estimate (`config.large_motion`); it matches one way only, whatever `matching.symmetric`
        says. Points on moving objects (`moving_objects`) are left out of a consecutive pair, not of a
        large-motion one. The result's points are in the frames of the scans given. A scan with fewer than
        `config.min_points` finite points is refused (ValueError): with no motion model to fall back on,
        the identity would be a silent wrong answer; so is a scan that is not plausible (most of its returns
        beyond a sensor's ranges), and a pair with fewer than `motion_model.min_inliers` inliers warns
        (`PairWarning`). A scan registered with itself is the identity. The pair runs in the crate (`Odometry::register_pair` in
        Rust), the network in onnxruntime; the drive's poses are untouched, and the reflectance scale is
        chosen on the pair when no scan chose it before.
        """
        reference_cloud, target_cloud = _as_scan(reference, "reference"), _as_scan(target, "target")
        if large_motion and isinstance(self.matcher, OnnxMatcher):
            wide_graph_path(self.matcher.path)  # a model without the wide-window graph: ModelError saying so
        transform, matches, map_refined, rounds, notices = self._loop.register_pair(
            reference_cloud, target_cloud, large_motion=large_motion
        )
        warn(notices, stacklevel=3)
        return PairResult(
            T_tgt_ref=transform,
            num_matches=len(matches.source),
            num_inliers=int(matches.num_inliers),
            source_points=matches.source,
            target_points=matches.target,
            inliers=np.asarray(matches.inliers, dtype=bool),
            rounds=rounds,
            inlier_votes=matches.inlier_votes,
            map_refined=map_refined,
        )

    @property
    def reflectance_scale(self) -> str | None:
        """The reflectance scale the crate chose on the first matched scan ("unit", "0-255", "0-65535", or
        "none": not used, the range-only model running when there is one); None before it."""
        return self._loop.reflectance_scale

    # -- the paper's steps ----------------------------------------------------------------------

    def project(self, points: npt.ArrayLike) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """The network input `[2, H, W]` (range, reflectance) of a scan and its range image `[H, W]` (Eq. 1)."""
        return self._loop.network_image(_as_scan(points, "points"))

    def pose_from_flow(
        self,
        ref_range: npt.ArrayLike,
        tgt_range: npt.ArrayLike,
        flow: npt.ArrayLike,
        confidence: npt.ArrayLike,
    ) -> PairResult:
        """The back end alone: matches from any flow `[2, H, W]` and confidence `[H, W]` between two range
        images → NMS → RANSAC around the SVD solve, with this odometry's settings (§III-D).

        For evaluating the geometry on other flows (ground truth, another network) or one step at a time.
        Without the scans, the surfaces under the matches (`ransac.vote_by_tilt`) are those of the virtual
        points at the reference's cell centres.
        """
        def as_f32(array: npt.ArrayLike) -> npt.NDArray[np.float32]:
            return np.ascontiguousarray(array, dtype=np.float32)

        return self._match(as_f32(ref_range), as_f32(tgt_range), as_f32(flow), as_f32(confidence))

    def _match(
        self,
        ref_range: npt.NDArray[np.float32],
        tgt_range: npt.NDArray[np.float32],
        flow: npt.NDArray[np.float32],
        confidence: npt.NDArray[np.float32],
        leave_out: npt.NDArray[np.bool_] | None = None,
        ref_points: npt.NDArray[np.float32] | None = None,
        tilt_votes: bool = True,
    ) -> PairResult:
        """The pair's motion from a flow (§III-D) by the crate's back end with this odometry's settings
        (`dmlo_rs.Odometry.pose_from_flow`); `ref_points` is the reference's point image (H×W×3, NaN where
        empty), None: the virtual points of `ref_range`'s cells. `tilt_votes`: RANSAC weighs matches by the
        tilt of their surface as `ransac.vote_by_tilt` says; False: one vote each."""
        pair = self._loop.pose_from_flow(
            ref_range, tgt_range, flow, confidence, ref_points=ref_points, leave_out=leave_out, tilt_votes=tilt_votes
        )
        return PairResult(
            T_tgt_ref=np.asarray(pair.transform, dtype=np.float64),
            num_matches=len(pair.source),
            num_inliers=int(pair.num_inliers),
            source_points=pair.source,
            target_points=pair.target,
            inliers=np.asarray(pair.inliers, dtype=bool),
            inlier_votes=pair.inlier_votes,
        )


def _as_scan(points: npt.ArrayLike, name: str) -> npt.NDArray[np.float32]:
    cloud = np.asarray(points)
    if cloud.ndim != 2 or cloud.shape[1] not in (3, 4):
        raise ValueError(f"{name}: expected an N×4 (or N×3) array of x, y, z[, reflectance], got shape {cloud.shape}")
    if not np.issubdtype(cloud.dtype, np.floating):
        raise TypeError(f"{name}: expected floating-point points, got dtype {cloud.dtype}")
    return np.ascontiguousarray(cloud, dtype=np.float32)


def _as_point_times(times: npt.ArrayLike, count: int) -> npt.NDArray[np.float64]:
    values = np.asarray(times)
    if values.shape != (count,):
        raise ValueError(f"point_times: expected shape ({count},), one per point, got {values.shape}")
    if not np.issubdtype(values.dtype, np.number) or np.issubdtype(values.dtype, np.complexfloating):
        raise TypeError(f"point_times: expected real numbers (sensor periods), got {values.dtype}")
    values = values.astype(np.float64)
    if not np.isfinite(values).all():
        raise ValueError(f"point_times: entry {int(np.argmin(np.isfinite(values)))} is not finite")
    return values


def _as_mask(mask: npt.ArrayLike, count: int) -> npt.NDArray[np.bool_]:
    values = np.asarray(mask)
    if values.shape != (count,):
        raise ValueError(f"moving: expected a mask of {count} booleans, got shape {values.shape}")
    if values.dtype == np.bool_:
        return values
    if not np.issubdtype(values.dtype, np.integer):
        raise TypeError(
            f"moving: expected booleans (or integers 0 and 1), one per point, got dtype {values.dtype}; "
            "threshold a probability first (e.g. probability > 0.5)"
        )
    if ((values != 0) & (values != 1)).any():
        raise ValueError(
            f"moving: expected booleans (or integers 0 and 1), got {values[(values != 0) & (values != 1)][0]} "
            f"at point {int(np.argmax((values != 0) & (values != 1)))}"
        )
    return values.astype(bool)
