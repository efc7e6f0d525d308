"""Speed of the simulator: `python benchmarks/simulator.py [--frames N] [--trajectory FILE]`.

Reports the scene size and build time, the Rust ray casting time of one 64 × 2083 scan (static scene
plus moving cars), and the whole frame including the measurement model and writing the files. Run it
with `RAYON_NUM_THREADS=1` for single-core numbers.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from dmlo.simulator.sequence import simulate_sequence


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--trajectory")
    parser.add_argument("--start", type=int, default=0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as out:
        began = time.perf_counter()
        result = simulate_sequence(
            out, args.frames, args.seed, trajectory=args.trajectory, start=args.start, progress=False
        )
        total = time.perf_counter() - began
    cast = np.asarray(result.cast_seconds[1:] or result.cast_seconds) * 1000
    frame = np.asarray(result.frame_seconds[1:] or result.frame_seconds) * 1000
    print(
        f"threads (RAYON_NUM_THREADS): {os.environ.get('RAYON_NUM_THREADS', 'all')}, cpus: {os.cpu_count()}"
    )
    print(
        f"scene: {result.static_primitives} static primitives, "
        f"generated + BVH in {result.scene_seconds:.2f} s"
    )
    print(f"points per scan: {np.mean(result.points_per_frame):.0f} (of {64 * 2083} rays)")
    print(f"ray casting per scan: median {np.median(cast):.1f} ms (min {cast.min():.1f})")
    frame_cpu = np.asarray(result.frame_cpu_seconds[1:] or result.frame_cpu_seconds) * 1000
    print(
        f"whole frame incl. moving cars, noise model and writing: wall median {np.median(frame):.1f} ms "
        f"(min {frame.min():.1f}), CPU median {np.median(frame_cpu):.1f} ms"
    )
    print(f"total for {args.frames} frames: {total:.2f} s")
    _cast_only(args)


def _cast_only(args: argparse.Namespace) -> None:
    """Ray casting alone on the static scene, wall and CPU time (CPU time is robust to a busy machine)."""
    from dmlo.simulator.scene import generate_street
    from dmlo.simulator.sensor import HDL64E
    from dmlo.simulator.trajectory import camera_to_lidar_poses, generate_drive, read_kitti_poses

    if args.trajectory:
        poses = camera_to_lidar_poses(
            read_kitti_poses(args.trajectory)[args.start : args.start + args.frames]
        )
    else:
        poses = generate_drive(args.frames, args.seed)
    scene, _ = generate_street(poses, args.seed).static.build()
    elevations = HDL64E.elevations()
    walls, cpus = [], []
    for pose in poses:
        wall, cpu = time.perf_counter(), time.process_time()
        scene.cast_scan(pose, elevations, HDL64E.azimuth_count, HDL64E.max_range)
        walls.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
    print(
        f"static-scene cast only: wall median {1000 * np.median(walls):.1f} ms "
        f"(min {1000 * min(walls):.1f}), "
        f"CPU median {1000 * np.median(cpus):.1f} ms"
    )


if __name__ == "__main__":
    main()
