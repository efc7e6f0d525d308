"""Runs the odometry over a whole sequence and writes everything a user asked for as it goes.

Poses are appended line by line (KITTI and TUM) and diagnostics one JSON line per frame, all three
together (`dmlo.outputs.FrameFiles`), so an interrupted run or a full disk leaves valid files that hold
the same frames, every frame done; metrics and the plot are written at the end when the sequence has
ground truth. A folder that holds an earlier run's files is refused unless `overwrite`.
"""

from __future__ import annotations

import json
import time
import warnings
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from dmlo.datasets import DatasetError, ScanSequence, moving_mask
from dmlo.odometry.pipeline import Odometry
from dmlo.outputs import BENCH_FILES, RUN_FILES, FrameFiles, atomic_output, prepare_output_folder
from dmlo.poses import _as_transform, _format_kitti, _format_tum, write_kitti_poses


@dataclass
class RunSummary:
    frames: int
    skipped: list[int]
    fallbacks: dict[str, int]  # `FrameDiagnostics.fallback` reason (constant_velocity, rematched_from_prediction, …) → frames
    seconds: float
    metrics: dict[str, Any] | None
    out_dir: Path
    # mean share of a scan's points the moving-object network left out, over the scans it ran on; None: it never ran
    moving_share: float | None = None
    # frames whose motion another start also explained (`FrameDiagnostics.ambiguous_start`): the first pair of a
    # drive that began at speed along a repeating scene
    ambiguous_starts: int = 0

    @property
    def hz(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("nan")


def run_sequence(
    sequence: ScanSequence,
    odometry: Odometry,
    out_dir: Path,
    *,
    remove_moving: bool = True,
    max_frames: int | None = None,
    progress: bool = True,
    on_frame: Callable[[int, np.ndarray], None] | None = None,
    overwrite: bool = False,
) -> RunSummary:
    """Registers every scan of `sequence`, writing into `out_dir`:

    `poses_kitti.txt` / `poses_tum.txt` (T_world_lidar, world = the first scan, readable by evo),
    `diagnostics.jsonl`, `config.json`, and with ground truth `ground_truth_kitti.txt`,
    `metrics.json` and `trajectory.png` (skipped with a warning without matplotlib, the `plot` extra).
    `max_frames` (≥ 1) stops after that many scans. A folder with an earlier run's files raises
    `OutputError` unless `overwrite` (which deletes them first); so does any failure to write, naming the
    file.
    """
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames: must be at least 1, got {max_frames}")
    out_dir = prepare_output_folder(out_dir, RUN_FILES, overwrite=overwrite, also_refuse=BENCH_FILES)
    with atomic_output(out_dir / "config.json") as temporary:
        odometry.config.save(temporary)
    total = len(sequence) if max_frames is None else min(max_frames, len(sequence))
    timestamps: list[float] = []
    skipped: list[int] = []
    start = time.perf_counter()
    with FrameFiles([out_dir / "poses_kitti.txt", out_dir / "poses_tum.txt", out_dir / "diagnostics.jsonl"]) as files:
        bar = tqdm(range(total), desc=sequence.name, unit="scan", disable=not progress)
        for index in bar:
            try:
                frame = sequence[index]
            except DatasetError as err:
                # A missing or truncated scan is skipped and recorded; the motion model bridges it.
                skipped.append(index)
                pose = odometry.predict_skipped()
                record: dict[str, Any] = {"index": index, "skipped": str(err)}
                timestamp = float(index)
            else:
                moving = None
                if remove_moving and frame.labels is not None:
                    moving = moving_mask(frame.labels)
                pose = odometry.register(frame.points, moving=moving, timestamp=frame.timestamp)
                record = odometry.diagnostics[-1].to_dict()
                timestamp = float(frame.timestamp) if frame.timestamp is not None else float(index)
            timestamps.append(timestamp)
            matrix = _as_transform(pose, "pose")
            files.append([_format_kitti(matrix), _format_tum(timestamp, matrix), json.dumps(record) + "\n"])
            if on_frame:
                on_frame(index, pose)
            elapsed = time.perf_counter() - start
            bar.set_postfix(Hz=f"{(index + 1) / elapsed:.1f}")
    seconds = time.perf_counter() - start

    metrics = None
    ground_truth = sequence.poses
    if ground_truth is not None:
        metrics = _evaluate(ground_truth[:total], np.stack(odometry.poses), out_dir, sequence.name)
    fallbacks = Counter(d.fallback for d in odometry.diagnostics if d.fallback is not None)
    shares = [d.num_moving_predicted / d.num_points for d in odometry.diagnostics
              if d.num_moving_predicted is not None and d.num_points]
    moving_share = float(np.mean(shares)) if shares else None
    ambiguous = sum(d.ambiguous_start is True for d in odometry.diagnostics)
    return RunSummary(total, skipped, dict(fallbacks), seconds, metrics, out_dir, moving_share, ambiguous)


def _evaluate(ground_truth: np.ndarray, estimate: np.ndarray, out_dir: Path, name: str) -> dict[str, Any] | None:
    from dmlo.metrics import evaluate_trajectory
    from dmlo.plot import PlotUnavailable, plot_trajectories

    # Both trajectories start at the identity, so they compare without any alignment.
    ground_truth = np.linalg.inv(ground_truth[0]) @ ground_truth
    with atomic_output(out_dir / "ground_truth_kitti.txt") as temporary:
        write_kitti_poses(temporary, ground_truth)
    try:
        metrics = evaluate_trajectory(ground_truth, estimate)
    except ValueError as err:  # an estimate gone far beyond any drive: the poses stay written, as they are
        warnings.warn(f"metrics.json and trajectory.png skipped: {err}", stacklevel=2)
        return None
    with atomic_output(out_dir / "metrics.json") as temporary:
        temporary.write_text(json.dumps(metrics, indent=2) + "\n")
    try:
        with atomic_output(out_dir / "trajectory.png") as temporary:
            # LiDAR frame, z up: the top view is the x–y plane.
            plot_trajectories(ground_truth, estimate, temporary, title=name, axes=(0, 1))
    except PlotUnavailable as err:  # plots are optional: the poses and metrics are what the run is for
        warnings.warn(f"trajectory.png skipped: {err}", stacklevel=2)
    return metrics
