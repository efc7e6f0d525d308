"""A matching network measured through the odometry's own code path (the figures of
`benchmarks/matching.py` and of the training ablation, `dmlo.train.ablation`).

For pairs of consecutive scans: EPE and Fl-all of the network's flow over every cell with ground truth
(Eq. 5–8) and over the NMS-kept matches the pose is solved from, the pair's pose error after RANSAC, and
the per-frame time of the network and of the whole pair.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

import dmlo_rs
from dmlo.datasets import open_sequence
from dmlo.metrics.flow import flow_errors
from dmlo.metrics.registration import registration_errors
from dmlo.odometry import Odometry, OdometryConfig


def evaluate(model: Path, drives: list[Path], pairs_per_drive: int, coherence: bool = True) -> dict[str, float]:
    config = OdometryConfig()
    if not coherence:
        config.matching.coherence_px = None
    odometry = Odometry(model, config)
    cylinder = odometry.cylinder
    epe, fl, kept_epe, kept_fl, network_ms, pair_ms = [], [], [], [], [], []
    estimates, truths = [], []
    for drive in drives:
        sequence = open_sequence(drive)
        assert sequence.poses is not None, f"{drive} has no ground truth"
        for start in np.linspace(0, len(sequence) - 2, pairs_per_drive).round().astype(int):
            ref, tgt = sequence[int(start)], sequence[int(start) + 1]
            assert ref.pose is not None and tgt.pose is not None
            T_tgt_ref = np.linalg.inv(tgt.pose) @ ref.pose
            ref_image, ref_range = odometry.project(ref.points)
            tgt_image, tgt_range = odometry.project(tgt.points)
            began = time.perf_counter()
            features = odometry.matcher.frame(ref_image, None).features
            middle = time.perf_counter()
            output = odometry.matcher.frame(tgt_image, features)
            network_ms.append((time.perf_counter() - middle) * 1e3)
            assert output.flow is not None and output.confidence is not None
            pair = odometry.pose_from_flow(ref_range, tgt_range, output.flow, output.confidence)
            pair_ms.append((time.perf_counter() - began) * 1e3 - (middle - began) * 1e3)
            gt_flow, valid = dmlo_rs.ground_truth_flow(ref_range, tgt_range, T_tgt_ref, cylinder)
            all_cells = flow_errors(output.flow, gt_flow, valid)
            epe.append(all_cells.epe)
            fl.append(all_cells.fl_all)
            kept = np.zeros_like(valid)
            cells = _cells_of(pair.source_points, cylinder)
            kept[cells[:, 0], cells[:, 1]] = True
            if (kept & valid).any():
                kept_cells = flow_errors(output.flow, gt_flow, kept & valid)
                kept_epe.append(kept_cells.epe)
                kept_fl.append(kept_cells.fl_all)
            estimates.append(pair.T_tgt_ref)
            truths.append(T_tgt_ref)
    pose = registration_errors(np.stack(estimates), np.stack(truths))
    return {
        "epe": float(np.mean(epe)),
        "fl_all": float(np.mean(fl)),
        "kept_epe": float(np.mean(kept_epe)) if kept_epe else float("nan"),
        "kept_fl_all": float(np.mean(kept_fl)) if kept_fl else float("nan"),
        "rotation_deg": pose.angular_mean,
        "translation_m": pose.translation_mean,
        "network_ms": float(np.median(network_ms)),
        "pair_ms": float(np.median(pair_ms)),
    }


def _cells_of(points: np.ndarray, cylinder: dmlo_rs.CylinderConfig) -> np.ndarray:
    """The cylinder cells the reference points p'_r sit at (cell centres, so exact)."""
    projection = dmlo_rs.project(points.astype(np.float32), cylinder)
    rows, cols = np.nonzero(projection.index >= 0)
    return np.stack([rows, cols], axis=1)
