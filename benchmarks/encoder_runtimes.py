"""The network's encoder in three runtimes on the same real scan, in one run: onnxruntime from Python (what
`dmlo run` uses), tract from Rust (the crate's `inference` feature, pure Rust) and the same onnxruntime library
from Rust (the crate's `onnxruntime` feature: `ort`, the library loaded at run time), all on the same number of
threads (issue 24).

    .venv/bin/python benchmarks/encoder_runtimes.py [--scan SCAN.bin] [--threads 2] [--repeat 20]

Builds `cargo build --release --features inference,onnxruntime --example encoder_speed` first; prints the
median and fastest encode of each and each one's time over Python onnxruntime's.
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
    from dmlo.odometry.matcher import session_options

    # The odometry's own options (no spinning between calls), as `OrtEncoder` sets them.
    session = ort.InferenceSession(str(ENCODER), session_options(threads), providers=["CPUExecutionProvider"])
    for _ in range(3):
        session.run(None, {"scan": image})
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        session.run(None, {"scan": image})
        times.append((time.perf_counter() - start) * 1000)
    return float(np.median(times)), float(np.min(times))


def rust_ms(scan: Path, threads: int, repeat: int, onnxruntime: bool) -> tuple[float, float]:
    """The encoder timed by `examples/encoder_speed.rs`: tract, or with `onnxruntime` the library of this
    Python's `onnxruntime` wheel through `ort`."""
    subprocess.run(["cargo", "build", "--release", "--features", "inference,onnxruntime", "--example", "encoder_speed"],
                   cwd=ROOT, check=True)
    command = [str(ROOT / "target/release/examples/encoder_speed"), str(ENCODER), str(scan), str(repeat)]
    if onnxruntime:
        from dmlo.odometry.matcher import onnxruntime_library

        command += ["--onnxruntime", str(onnxruntime_library()), str(threads)]
    env = dict(os.environ, RAYON_NUM_THREADS=str(threads))
    out = subprocess.run(command, env=env, check=True, capture_output=True, text=True).stdout
    result = json.loads(out)
    return result["median_ms"], result["min_ms"]



def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scan", type=Path, default=DEFAULT_SCAN)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=20)
    args = parser.parse_args()
    rows = {
        "onnxruntime (Python)": onnxruntime_ms(args.scan, args.threads, args.repeat),
        "tract (Rust)": rust_ms(args.scan, args.threads, args.repeat, onnxruntime=False),
        "onnxruntime (Rust, ort)": rust_ms(args.scan, args.threads, args.repeat, onnxruntime=True),
    }
    print(f"encoder.onnx on {args.scan.name}, {args.threads} threads, {args.repeat} encodes each\n")
    print("| runtime | median ms | fastest ms | median / Python onnxruntime's |\n|---|---|---|---|")
    python_median = rows["onnxruntime (Python)"][0]
    for name, (median, fastest) in rows.items():
        print(f"| {name} | {median:.1f} | {fastest:.1f} | {median / python_median:.2f} |")


if __name__ == "__main__":
    main()
