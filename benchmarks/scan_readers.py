"""Read times of the PLY / PCD scan readers: dmlo's numpy parsers against plyfile and pypcd4 (issue 23, item 5).

The files: the real Argoverse 1 sweep in ``../shared/data`` (binary PLY, 91k points) as it is, and real KITTI
HDL-64E scans (~120k points) written in every encoding the readers take (PLY ascii / binary, PCD ascii /
binary / binary_compressed, the last LZF-compressed by pypcd4 as PCL does). Each reader turns the file into
the same ``(N, 4)`` array (the library readers through dmlo's field mapping), checked equal, then is timed
(best of ``--repeat``)::

    .venv/bin/python benchmarks/scan_readers.py [--data ../shared/data] [--repeat 5]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dmlo.datasets import scan_files
from dmlo.datasets.scan_files import read_bin, read_pcd, read_ply


def _plyfile_reader(path: Path) -> np.ndarray:
    import plyfile

    vertex = plyfile.PlyData.read(str(path))["vertex"].data
    return scan_files._points_from_fields(path, {name: vertex[name] for name in vertex.dtype.names or ()})


def _pypcd4_reader(path: Path) -> np.ndarray:
    import pypcd4

    data = pypcd4.PointCloud.from_path(path).pc_data
    return scan_files._points_from_fields(path, {name: data[name] for name in data.dtype.names or ()})


def _write_files(data: Path, out: Path) -> list[Path]:
    import plyfile
    import pypcd4

    files = []
    argoverse = data / "argoverse1_layout" / "real_sweep_PC_315971347819783000.ply"
    if argoverse.is_file():
        files.append(argoverse)
        ply = plyfile.PlyData.read(str(argoverse))
        ply.text = True
        ply.write(str(out / "argoverse_ascii.ply"))
        files.append(out / "argoverse_ascii.ply")
    kitti = sorted((data / "kitti_real" / "odometry_02" / "velodyne").glob("*.bin"))[:1]
    for scan_path in kitti:
        points = read_bin(scan_path)
        vertex = np.zeros(len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4")])
        for i, name in enumerate(("x", "y", "z", "intensity")):
            vertex[name] = points[:, i]
        for text in (False, True):
            path = out / f"kitti_{'ascii' if text else 'binary'}.ply"
            plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")], text=text).write(str(path))
            files.append(path)
        cloud = pypcd4.PointCloud.from_points(
            [points[:, i] for i in range(4)], ("x", "y", "z", "intensity"), (np.float32,) * 4
        )
        for encoding in ("ascii", "binary", "binary_compressed"):
            path = out / f"kitti_{encoding}.pcd"
            cloud.save(path, encoding=pypcd4.Encoding(encoding))
            files.append(path)
    return files


def _best_of(reader: Callable[[Path], np.ndarray], path: Path, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        reader(path)
        best = min(best, time.perf_counter() - start)
    return best


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as temporary:
        files = _write_files(args.data, Path(temporary))
        if not files:
            print(f"no real scans under {args.data}", file=sys.stderr)
            return 1
        print("| file | points | MB | dmlo (ms) | library (ms) | library / dmlo |")
        print("|---|---|---|---|---|---|")
        for path in files:
            ours = read_ply if path.suffix == ".ply" else read_pcd
            library, name = (_plyfile_reader, "plyfile") if path.suffix == ".ply" else (_pypcd4_reader, "pypcd4")
            expected = ours(path)
            np.testing.assert_array_equal(library(path), expected)
            # The pure-Python LZF decoder takes seconds a scan: one read is enough to time it.
            repeat = 1 if b"binary_compressed" in path.read_bytes()[:500] else args.repeat
            t_ours, t_library = _best_of(ours, path, repeat), _best_of(library, path, args.repeat)
            print(
                f"| {path.name} | {len(expected)} | {path.stat().st_size / 1e6:.1f} | {t_ours * 1e3:.1f} | "
                f"{name} {t_library * 1e3:.1f} | {t_library / t_ours:.2f} |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
