"""The whole odometry from Rust against `dmlo.Odometry` from Python, on the same scans in one run (issue 24):
`examples/odometry.rs` with the encoder in onnxruntime (`--onnxruntime`: the library of this Python's
`onnxruntime` wheel through `ort`), each scan encoded in turn (as `dmlo.Odometry`) and encoded while the scan
before it is registered (`--encode-ahead`: `EncodeAhead`), and in tract (in turn), against
`dmlo.Odometry` (onnxruntime from Python), with the same model, the same config and the same threads, in turns.

    .venv/bin/python benchmarks/rust_odometry.py [SCANS_DIR ...] [--rounds 3] [--threads 2] [--keep-moving]

Without folders: every set of `../shared/data/kitti_real`. Each set runs with the local map and frame to frame.
The moving-object network runs in all of them, in each side's runtime, as `dmlo run` runs it (`--keep-moving`:
in none); "encoded ahead" flags the next scan's moving points on the same thread as it encodes it.
Each side's time covers the same loop: reading each `.bin` scan and registering it, the model already open.
Prints each runtime's median rate (Hz) over the rounds, its rate over Python's, and how far its poses are from
Python's (the largest translation difference over the drive).
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED_REAL = ROOT.parent / "shared/data/kitti_real"
MODEL = ROOT / "python/dmlo/models/default"
EXAMPLE = ROOT / "target/release/examples/odometry"
RUST_RATE = re.compile(r"(\d+) scans in ([0-9.]+) s")


def scan_folders(given: list[Path]) -> list[Path]:
    if given:
        return given
    return sorted(path / "velodyne" for path in SHARED_REAL.iterdir() if (path / "velodyne").is_dir())


def python_run(scans: Path, config_path: Path) -> tuple[float, np.ndarray]:
    """Scans a second and the translations of `dmlo.Odometry` over the folder."""
    from dmlo.odometry import Odometry, OdometryConfig

    odometry = Odometry(MODEL / "frame.onnx", OdometryConfig.load(config_path))
    files = sorted(scans.glob("*.bin"))
    start = time.perf_counter()
    for path in files:
        odometry.register(np.fromfile(path, dtype=np.float32).reshape(-1, 4))
    seconds = time.perf_counter() - start
    return len(files) / seconds, np.stack([np.asarray(pose)[:3, 3] for pose in odometry.poses])


def rust_run(
    scans: Path, config_path: Path, threads: int, library: Path | None, encode_ahead: bool = False
) -> tuple[float, np.ndarray]:
    """Scans a second and the translations of `examples/odometry.rs` (tract, or onnxruntime's `library`;
    `encode_ahead`: each scan encoded while the one before it is registered)."""
    with tempfile.TemporaryDirectory() as out:
        command = [str(EXAMPLE), str(scans), "--out", out, "--model", str(MODEL), "--config", str(config_path),
                   "--threads", str(threads)]
        if library is not None:
            command += ["--onnxruntime", str(library)]
        if encode_ahead:
            command.append("--encode-ahead")
        printed = subprocess.run(command, check=True, capture_output=True, text=True).stdout
        match = RUST_RATE.search(printed)
        if match is None:
            raise RuntimeError(f"no rate in the example's output: {printed!r}")
        poses = np.loadtxt(Path(out) / "poses_kitti.txt", ndmin=2).reshape(-1, 3, 4)
    return int(match[1]) / float(match[2]), poses[:, :, 3]



def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scans", type=Path, nargs="*", help="folders of KITTI .bin scans")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--keep-moving", action="store_true", help="run no moving-object network")
    args = parser.parse_args()
    subprocess.run(["cargo", "build", "--release", "--features", "inference,onnxruntime", "--example", "odometry"],
                   cwd=ROOT, check=True)
    from dmlo.odometry import OdometryConfig
    from dmlo.odometry.matcher import onnxruntime_library

    library = onnxruntime_library()
    python_name = "dmlo.Odometry (Python, onnxruntime)"
    # name → (onnxruntime's library or None for tract, encoded ahead)
    rust = {
        "Rust, onnxruntime": (library, False),
        "Rust, onnxruntime, encoded ahead": (library, True),
        "Rust, tract": (None, False),
    }
    names = [python_name, *rust]
    print("| scans | mode | " + " | ".join(f"{name} Hz" for name in names)
          + " | " + " | ".join(f"{name} / Python" for name in rust)
          + " | largest difference from Python (m), " + " / ".join(rust) + " |")
    print("|---|---|" + "---|" * (len(names) + len(rust) + 1))
    with tempfile.TemporaryDirectory() as folder:
        for scans in scan_folders(args.scans):
            for mapping in (True, False):
                config = OdometryConfig()
                config.mapping.enabled = mapping
                config.moving_objects.detect = not args.keep_moving
                config.threads = args.threads
                config_path = Path(folder) / "config.json"
                config.save(config_path)
                rates: dict[str, list[float]] = {name: [] for name in names}
                translations: dict[str, np.ndarray] = {}
                for _ in range(args.rounds):
                    rate, translations[python_name] = python_run(scans, config_path)
                    rates[python_name].append(rate)
                    for name, (runtime, ahead) in rust.items():
                        rate, translations[name] = rust_run(scans, config_path, args.threads, runtime, ahead)
                        rates[name].append(rate)
                median = {name: statistics.median(values) for name, values in rates.items()}
                reference = translations[python_name]
                apart = [float(np.abs(translations[name] - reference).max()) for name in rust]
                label = scans.parent.name if scans.name == "velodyne" else scans.name
                print(f"| {label} | {'mapping' if mapping else 'frame to frame'} | "
                      + " | ".join(f"{median[name]:.1f}" for name in names)
                      + " | " + " | ".join(f"{median[name] / median[python_name]:.2f}" for name in rust)
                      + " | " + " / ".join(f"{value:.1e}" for value in apart) + " |", flush=True)


if __name__ == "__main__":
    main()
