"""Runs DMLO and the peers over the same in-memory scans and compares drift and speed."""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from dmlo.peers.peers import PEERS, FrameOdometry
from dmlo.datasets import ScanSequence
from dmlo.outputs import BENCH_FILES, RUN_FILES, atomic_output, check_output_folder, prepare_output_folder
from dmlo.poses import write_kitti_poses

REFERENCE_PEER = "KISS-ICP"


class PeerUnavailableWarning(UserWarning):
    """A peer that was asked for cannot run here; its row is left out."""


class UnknownPeerError(ValueError):
    """A peer name that `dmlo bench` does not know."""


@dataclass
class BenchRow:
    method: str
    hz: float
    metrics: dict[str, Any]


def benchmark_sequence(
    sequence: ScanSequence,
    dmlo_variants: Mapping[str, Callable[[], FrameOdometry]],
    out_dir: Path,
    peers: list[str] | None = None,
    max_frames: int | None = None,
    overwrite: bool = False,
) -> list[BenchRow]:
    """Every method sees the same scans (read once, before any timing) and starts from identity.

    `dmlo_variants` maps a row name to a factory of a DMLO odometry (e.g. with and without mapping).
    `out_dir` gets `ground_truth.txt` and one KITTI pose file per method; a folder with an earlier run's
    files raises `dmlo.outputs.OutputError` unless `overwrite` (which deletes them first).
    """
    from dmlo.metrics import evaluate_trajectory

    methods: list[tuple[str, Callable[[], FrameOdometry]]] = list(dmlo_variants.items())
    wanted = set(peers) if peers is not None else {p.name for p in PEERS if p.by_default}
    unknown = wanted - {p.name for p in PEERS}
    if unknown:
        raise UnknownPeerError(f"unknown peer(s): {', '.join(sorted(unknown))}; known: {', '.join(p.name for p in PEERS)}")
    for peer in PEERS:
        if peer.name not in wanted:
            continue
        if peer.available:
            methods.append((peer.name, peer.make))
        elif peers is not None:  # asked for by name: say why its row is missing
            warnings.warn(f"skipping {peer.name}: {peer.unavailable_reason}", PeerUnavailableWarning, stacklevel=2)

    check_output_folder(out_dir, BENCH_FILES, overwrite=overwrite, also_refuse=RUN_FILES)
    total = len(sequence) if max_frames is None else min(max_frames, len(sequence))
    scans = [sequence[i].points for i in tqdm(range(total), desc="reading", unit="scan")]
    ground_truth = sequence.poses
    assert ground_truth is not None
    ground_truth = np.linalg.inv(ground_truth[0]) @ ground_truth[:total]
    prepare_output_folder(out_dir, BENCH_FILES, overwrite=overwrite, also_refuse=RUN_FILES)
    with atomic_output(out_dir / "ground_truth.txt") as temporary:
        write_kitti_poses(temporary, ground_truth)

    rows = []
    for name, make in methods:
        odometry = make()
        poses = []
        start = time.perf_counter()
        for points in tqdm(scans, desc=name, unit="scan"):
            poses.append(odometry.register(points))
        seconds = time.perf_counter() - start
        estimate = np.stack(poses)
        with atomic_output(out_dir / f"{name.replace(' ', '_')}.txt") as temporary:
            write_kitti_poses(temporary, estimate)
        rows.append(BenchRow(name, total / seconds, evaluate_trajectory(ground_truth, estimate)))
    return rows


def format_table(rows: list[BenchRow]) -> str:
    """A markdown table; ratios are to KISS-ICP when it ran (speed: ×faster, drift: ×of its error)."""
    reference = next((r for r in rows if r.method == REFERENCE_PEER), None)
    long_enough = all(r.metrics.get("t_rel") is not None for r in rows)
    drift_key, drift_label = ("t_rel", "t_rel %") if long_enough else ("ate_rmse", "ATE m")
    header = f"| method | {drift_label} | {'r_rel °/100m' if long_enough else 'RPE t m'} | Hz | drift ×KISS | speed ×KISS |"
    lines = [header, "|---|---|---|---|---|---|"]
    for row in rows:
        second = row.metrics.get("r_rel") if long_enough else row.metrics.get("rpe_t_mean")
        drift = row.metrics.get(drift_key)
        drift_ratio = speed_ratio = "—"
        if reference is not None and drift is not None and reference.metrics.get(drift_key):
            drift_ratio = f"{drift / reference.metrics[drift_key]:.2f}"
            speed_ratio = f"{row.hz / reference.hz:.2f}"
        lines.append(f"| {row.method} | {_fmt(drift)} | {_fmt(second)} | {row.hz:.1f} | {drift_ratio} | {speed_ratio} |")
    return "\n".join(lines)


def _fmt(value: float | None) -> str:
    return "—" if value is None else f"{value:.4g}"
