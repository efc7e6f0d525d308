"""The network's encoder in two runtimes on the same real scan, in one run: onnxruntime (what `dmlo run` uses)
and tract (the crate's `inference` feature, pure Rust), both on the same number of threads (issue 24).

    .venv/bin/python benchmarks/encoder_runtimes.py [--scan SCAN.bin] [--threads 2] [--repeat 20]

Builds `cargo build --release --features inference --example encoder_speed` first when its binary is
missing; prints the median and fastest encode of each and tract's time over onnxruntime's.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ENCODER = ROOT / "python/dmlo/models/default/encoder.onnx"
DEFAULT_SCAN = ROOT.parent / "shared/data/kitti_real/odometry_03/velodyne/000000.bin"


def onnxruntime_ms(scan: Path, threads: int, repeat: int) -> tuple[float, float]:
    import onnxruntime as ort

    import dmlo_rs

    points = np.fromfile(scan, dtype=np.float32).reshape(-1, 4)
    projection = dmlo_rs.project(points, dmlo_rs.CylinderConfig.kitti())
    image = np.stack([projection.range, projection.reflectance]).astype(np.float32)[None]
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    session = ort.InferenceSession(str(ENCODER), options, providers=["CPUExecutionProvider"])
    for _ in range(3):
        session.run(None, {"scan": image})
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        session.run(None, {"scan": image})
        times.append((time.perf_counter() - start) * 1000)
    return float(np.median(times)), float(np.min(times))


def tract_ms(scan: Path, threads: int, repeat: int) -> tuple[float, float]:
    binary = ROOT / "target/release/examples/encoder_speed"
    if not binary.is_file():
        subprocess.run(["cargo", "build", "--release", "--features", "inference", "--example", "encoder_speed"],
                       cwd=ROOT, check=True)
    env = dict(os.environ, RAYON_NUM_THREADS=str(threads))
    out = subprocess.run([str(binary), str(ENCODER), str(scan), str(repeat)], env=env, check=True,
                         capture_output=True, text=True).stdout
    result = json.loads(out)
    return result["median_ms"], result["min_ms"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scan", type=Path, default=DEFAULT_SCAN)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=20)
    args = parser.parse_args()
    rows = {"onnxruntime": onnxruntime_ms(args.scan, args.threads, args.repeat),
            "tract": tract_ms(args.scan, args.threads, args.repeat)}
    print(f"encoder.onnx on {args.scan.name}, {args.threads} threads, {args.repeat} encodes each\n")
    print("| runtime | median ms | fastest ms |\n|---|---|---|")
    for name, (median, fastest) in rows.items():
        print(f"| {name} | {median:.1f} | {fastest:.1f} |")
    print(f"\ntract / onnxruntime (median): {rows['tract'][0] / rows['onnxruntime'][0]:.2f}")


if __name__ == "__main__":
    main()
