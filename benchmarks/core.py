"""Speed and accuracy of the Rust core against numpy references and Open3D, in one run.

    python benchmarks/core.py [--data DIR] [--repeats N]

Measures, on a real KITTI scan from ``kitti_raw_static`` and on synthetic correspondences: the cylinder
projection (one thread and all cores); NMS over a full 64×1792 confidence map; RANSAC on 500 / 2000 matches with 50 % / 80 %
outliers (dmlo_rs, a vectorised numpy RANSAC written here, and Open3D's
``registration_ransac_based_on_correspondence`` with the same threshold, confidence and iteration cap);
and one frame's post-processing (decode + NMS + RANSAC + solve). Prints a markdown table: median times,
ratios to dmlo_rs, and the accuracy of each estimate.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

import dmlo_rs

THRESHOLD = 0.1
CONFIDENCE = 0.999
MAX_ITERATIONS = 1000


def median_ms(function: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    """Median wall time in milliseconds over `repeats` calls (after one warm-up) and the last result."""
    result = function()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times), result


# ---- numpy references ----------------------------------------------------------------------------


def numpy_project(points: np.ndarray, config: dmlo_rs.CylinderConfig) -> np.ndarray:
    """Closest point per cell (ties: lower index) → the H×W index image, as dmlo_rs documents it."""
    h, w = config.height, config.width
    finite = np.isfinite(points).all(axis=1)
    ids = np.flatnonzero(finite)
    x, y, z = (points[finite, k].astype(np.float64) for k in range(3))
    horizontal = np.sqrt(x * x + y * y)
    rng = np.sqrt(horizontal * horizontal + z * z)
    row = np.floor(
        config.row_of_zero_elevation
        - np.arctan2(z, horizontal) / (config.vertical_resolution_deg * np.pi / 180.0)
        + 0.5
    )
    col = np.floor(
        config.col_of_zero_azimuth - np.arctan2(y, x) / (config.horizontal_resolution_deg * np.pi / 180.0) + 0.5
    )
    inside = (rng > 0) & (row >= 0) & (row < h) & (col >= 0) & (col < w)
    cell = (row[inside] * w + col[inside]).astype(np.int64)
    range32 = rng[inside].astype(np.float32)
    ids = ids[inside]
    order = np.lexsort((ids, range32, cell))
    cell, ids = cell[order], ids[order]
    first = np.ones(len(cell), dtype=bool)
    first[1:] = cell[1:] != cell[:-1]
    index = np.full(h * w, -1, np.int64)
    index[cell[first]] = ids[first]
    return index.reshape(h, w)


def numpy_nms(rows: np.ndarray, cols: np.ndarray, scores: np.ndarray, radius: int, top_n: int) -> list[int]:
    """Greedy NMS with a suppression grid: sort once, walk in order."""
    order = np.lexsort((np.arange(len(scores)), -scores))
    suppressed = np.zeros((rows.max() + 1, cols.max() + 1), bool)
    kept: list[int] = []
    for i in order:
        r, c = rows[i], cols[i]
        if suppressed[r, c]:
            continue
        kept.append(int(i))
        if len(kept) == top_n:
            break
        suppressed[max(r - radius, 0) : r + radius + 1, max(c - radius, 0) : c + radius + 1] = True
    return kept


def numpy_kabsch(p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched rigid solve: p, q (K, M, 3) → R (K, 3, 3), t (K, 3) with q ≈ R p + t."""
    p_mean, q_mean = p.mean(axis=1), q.mean(axis=1)
    H = np.einsum("kmi,kmj->kij", p - p_mean[:, None], q - q_mean[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("kji,klj->kil", Vt, U)))
    D = np.zeros((len(p), 3, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1
    D[:, 2, 2] = d
    R = np.einsum("kji,kjl,kml->kim", Vt, D, U)
    return R, q_mean - np.einsum("kij,kj->ki", R, p_mean)


def numpy_ransac(src: np.ndarray, dst: np.ndarray, seed: int = 0, batch: int = 128) -> np.ndarray:
    """Vectorised RANSAC with the same rules as dmlo_rs: samples of 3, adaptive count, refit."""
    rng = np.random.default_rng(seed)
    n = len(src)
    best = (-1, np.inf, np.eye(4))
    required, done = MAX_ITERATIONS, 0
    while done < required:
        k = min(batch, MAX_ITERATIONS - done)
        samples = np.array([rng.choice(n, 3, replace=False) for _ in range(k)])
        R, t = numpy_kabsch(src[samples], dst[samples])
        residual = np.einsum("kij,nj->kni", R, src) + t[:, None] - dst[None]
        d2 = np.einsum("kni,kni->kn", residual, residual)
        inlier = d2 < THRESHOLD**2
        counts, errors = inlier.sum(axis=1), np.where(inlier, d2, 0).sum(axis=1)
        for j in range(k):
            done += 1
            if counts[j] > best[0] or (counts[j] == best[0] and errors[j] < best[1]):
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = R[j], t[j]
                best = (int(counts[j]), float(errors[j]), T)
                w = counts[j] / n
                required = MAX_ITERATIONS if w**3 <= 0 else min(
                    MAX_ITERATIONS, int(np.ceil(np.log(1 - CONFIDENCE) / np.log(max(1 - w**3, 1e-300))))
                )
            if done >= required:
                break
    T = best[2]
    for _ in range(3):
        inlier = np.linalg.norm(src @ T[:3, :3].T + T[:3, 3] - dst, axis=1) < THRESHOLD
        R, t = numpy_kabsch(src[inlier][None], dst[inlier][None])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R[0], t[0]
    return T


def open3d_ransac(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    import open3d as o3d

    registration = o3d.pipelines.registration
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(dst))
    pairs = np.stack([np.arange(len(src)), np.arange(len(src))], axis=1).astype(np.int32)
    result = registration.registration_ransac_based_on_correspondence(
        source,
        target,
        o3d.utility.Vector2iVector(pairs),
        THRESHOLD,
        registration.TransformationEstimationPointToPoint(False),
        3,
        [],
        registration.RANSACConvergenceCriteria(MAX_ITERATIONS, CONFIDENCE),
    )
    return np.asarray(result.transformation)


# ---- scenes --------------------------------------------------------------------------------------


def known_motion() -> np.ndarray:
    yaw, pitch = np.radians(2.5), np.radians(0.3)
    Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    Ry = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry
    T[:3, 3] = [1.1, -0.04, 0.02]
    return T


def correspondences(scan: np.ndarray, n: int, outlier_ratio: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Real scan points moved by the known motion with 2 cm noise; outliers pair with random scan points."""
    rng = np.random.default_rng(seed)
    T = known_motion()
    src = scan[rng.choice(len(scan), n, replace=False), :3].astype(np.float64)
    dst = src @ T[:3, :3].T + T[:3, 3] + rng.normal(scale=0.02, size=(n, 3))
    outliers = rng.random(n) < outlier_ratio
    dst[outliers] = scan[rng.choice(len(scan), int(outliers.sum())), :3]
    return src, dst


def errors(T: np.ndarray) -> str:
    truth = known_motion()
    cos = (np.trace(T[:3, :3].T @ truth[:3, :3]) - 1) / 2
    rotation = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    translation = np.linalg.norm(T[:3, 3] - truth[:3, 3])
    return f"{rotation:.3f}° / {translation * 100:.1f} cm"


# ---- the run -------------------------------------------------------------------------------------


def ratio(other: float | None, ours: float) -> str:
    return "—" if other is None else f"{other / ours:.1f}×"


def main(argv: list[str] | None = None) -> None:
    repo = Path(__file__).resolve().parents[1]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=repo.parent / "shared" / "data" / "kitti_raw_static")
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args(argv)
    try:
        import open3d  # noqa: F401

        have_open3d = True
    except ImportError:
        have_open3d = False

    scans = sorted(args.data.glob("*.bin"))
    if not scans:
        raise SystemExit(f"no .bin scans in {args.data}")
    scan = np.fromfile(scans[0], dtype=np.float32).reshape(-1, 4)
    config = dmlo_rs.CylinderConfig.kitti()
    rows: list[list[str]] = []

    # Projection of a real scan: one thread (the target) and the module's pool (all cores).
    reference, index = median_ms(lambda: numpy_project(scan, config), max(3, args.repeats // 3))
    for threads, label in [(1, "1 thread"), (None, f"{os.cpu_count()} threads")]:
        ours, image = median_ms(lambda: dmlo_rs.project(scan, config, num_threads=threads), args.repeats)
        same = np.mean(image.index == index) * 100
        rows.append(
            [f"projection, {len(scan) / 1000:.0f}k points → 64×1792, {label}", f"{ours:.2f}", f"{reference:.2f}",
             "—", ratio(reference, ours), "—", f"{same:.2f} % cells identical to numpy"]
        )

    # NMS over a full confidence map.
    confidence = np.random.default_rng(0).random((64, 1792)).astype(np.float32)
    cell_rows, cell_cols = (a.ravel().astype(np.int64) for a in np.indices(confidence.shape))
    scores = confidence.ravel()
    ours, kept = median_ms(lambda: dmlo_rs.nms(cell_rows, cell_cols, scores, 1, 1000), args.repeats)
    reference, kept_ref = median_ms(lambda: numpy_nms(cell_rows, cell_cols, scores, 1, 1000), 3)
    rows.append(
        ["NMS r=1, top 1000 of 64×1792", f"{ours:.2f}", f"{reference:.2f}", "—", ratio(reference, ours), "—",
         "same kept set" if kept.tolist() == kept_ref else "DIFFERENT kept set"]
    )

    # RANSAC on synthetic correspondences.
    for n, outlier_ratio in [(500, 0.5), (500, 0.8), (2000, 0.5), (2000, 0.8)]:
        src, dst = correspondences(scan, n, outlier_ratio, seed=n + int(outlier_ratio * 10))
        ours, result = median_ms(lambda: dmlo_rs.ransac_rigid(src, dst, THRESHOLD, CONFIDENCE, MAX_ITERATIONS), args.repeats)
        reference, T_numpy = median_ms(lambda: numpy_ransac(src, dst), 3)
        o3d_ms, T_o3d = (median_ms(lambda: open3d_ransac(src, dst), 5) if have_open3d else (None, None))
        accuracy = f"dmlo_rs {errors(result.transform)}; numpy {errors(T_numpy)}"
        if T_o3d is not None:
            accuracy += f"; Open3D {errors(T_o3d)}"
        rows.append(
            [f"RANSAC {n} matches, {outlier_ratio:.0%} outliers", f"{ours:.2f}", f"{reference:.2f}",
             "—" if o3d_ms is None else f"{o3d_ms:.2f}", ratio(reference, ours), ratio(o3d_ms, ours), accuracy]
        )

    # One frame's post-processing: decode (ground-truth flow stands in for the network) + NMS + RANSAC.
    T = known_motion()
    moved = scan.copy()
    moved[:, :3] = (scan[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
    ref, tgt = dmlo_rs.project(scan, config), dmlo_rs.project(moved, config)
    flow, valid = dmlo_rs.ground_truth_flow(ref.range, tgt.range, T, config)
    rng = np.random.default_rng(1)
    flow = flow + rng.normal(scale=0.3, size=flow.shape).astype(np.float32)
    wrong = rng.random(valid.shape) < 0.3  # 30 % of the cells get a wrong flow
    flow[:, wrong] += rng.uniform(-20, 20, size=(2, int(wrong.sum()))).astype(np.float32)
    frame_confidence = np.where(valid | wrong, rng.uniform(0.2, 1.0, valid.shape), 0).astype(np.float32)

    def frame() -> np.ndarray:
        matches = dmlo_rs.decode_matches(ref.range, tgt.range, flow, frame_confidence, config, 0.3)
        keep = dmlo_rs.nms(matches.cells[:, 0], matches.cells[:, 1], matches.confidence, 1, 1000)
        return dmlo_rs.ransac_rigid(matches.source[keep], matches.target[keep]).transform

    def fused_frame() -> np.ndarray:
        matches = dmlo_rs.decode_matches(ref.range, tgt.range, flow, frame_confidence, config, 0.3, top_n=1000)
        return dmlo_rs.ransac_rigid(matches.source, matches.target).transform

    ours, T_frame = median_ms(frame, args.repeats)
    rows.append(
        ["frame: decode all, NMS (top 1000), RANSAC + solve", f"{ours:.2f}", "—", "—", "—", "—",
         f"dmlo_rs {errors(T_frame)}"]
    )
    ours, T_frame = median_ms(fused_frame, args.repeats)
    rows.append(
        ["frame: decode fused with NMS (`top_n=1000`), RANSAC + solve", f"{ours:.2f}", "—", "—", "—", "—",
         f"dmlo_rs {errors(T_frame)}"]
    )

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        f"dmlo_rs core benchmark — {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC, {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cores, load average {load:.1f}; median of {args.repeats} runs (numpy/Open3D fewer); "
        f"RANSAC threshold {THRESHOLD} m, confidence {CONFIDENCE}, at most {MAX_ITERATIONS} iterations for all three\n"
    )
    header = ["task", "dmlo_rs ms", "numpy ms", "Open3D ms", "numpy / dmlo_rs", "Open3D / dmlo_rs", "accuracy (rotation / translation error)"]
    print("| " + " | ".join(header) + " |")
    print("|" + "|".join("---" for _ in header) + "|")
    for row in rows:
        print("| " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
