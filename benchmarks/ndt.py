"""Scan-to-map NDT (`dmlo_rs.NdtMap`, the mapping stage's registration) on real scans of a standing car.

    python benchmarks/ndt.py [--data ../shared/data/kitti_raw_static] [--repeats 15]

Times `insert` of one scan into a fresh map and `align` of the next scan to it, from the identity (the
scans were taken from the same spot) and from a start 0.3 m and 2° off, on one thread and on two; the
error of each alignment is its distance from the identity. Medians over the repeats.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np
from scipy.spatial.transform import Rotation

import dmlo_rs

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared/data/kitti_raw_static"
Result = TypeVar("Result")


def timed(function: Callable[[], Result], repeats: int) -> tuple[float, Result]:
    """The median milliseconds of `repeats` (at least one) calls and the last call's result."""
    times = []
    for _ in range(max(repeats, 1)):
        start = time.perf_counter()
        result = function()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times), result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    files = sorted(args.data.glob("*.bin"))
    if len(files) < 2:
        parser.error(f"{args.data}: expected at least two .bin scans")
    first, second = (np.fromfile(path, dtype=np.float32).reshape(-1, 4) for path in files[:2])
    off = np.eye(4)
    off[:3, :3] = Rotation.from_euler("z", 2.0, degrees=True).as_matrix()
    off[:3, 3] = [0.3, 0.0, 0.0]
    print(f"{len(first)} points a scan; median of {args.repeats}")
    print("| threads | insert ms | align from the identity ms | its steps | its error mm | "
          "align from 0.3 m / 2° off ms | its steps | its error mm |")
    print("|---|---|---|---|---|---|---|---|")
    for threads in (1, 2):
        def fresh_map() -> dmlo_rs.NdtMap:
            ndt_map = dmlo_rs.NdtMap()
            ndt_map.insert(first, num_threads=threads)
            return ndt_map

        insert_ms, ndt_map = timed(fresh_map, args.repeats)
        near_ms, near = timed(lambda: ndt_map.align(second, np.eye(4), num_threads=threads), args.repeats)
        far_ms, far = timed(lambda: ndt_map.align(second, off, num_threads=threads), args.repeats)
        near_mm = np.linalg.norm(near.transform[:3, 3]) * 1e3
        far_mm = np.linalg.norm(far.transform[:3, 3]) * 1e3
        print(f"| {threads} | {insert_ms:.1f} | {near_ms:.1f} | {near.iterations} | {near_mm:.1f} | {far_ms:.1f} "
              f"| {far.iterations} | {far_mm:.1f} |")


if __name__ == "__main__":
    main()
