"""Odometry side by side: DMLO (with and without NDT mapping) and the peers on the same scans.

Simulated drives along real KITTI ground-truth trajectories (several seeds), plus the real static KITTI
scans when `../shared/data` is present. Every method reads the same files; the table gives drift, speed
and the ratios to KISS-ICP measured in this run.

    python benchmarks/odometry.py --frames 300 --seeds 1 2 3 --trajectories 07 07 05 --out runs/bench_odometry

With `--highway SEED` a named drive is added: the simulator's highway (`--scene highway`, guard rails and
sparse poles) along KITTI 01's trajectory (~1 m a frame), its lasers' reflectance gains spread by ±0.6, the
feature-poor scene where the road's rings lock from scan to scan. With `--jam SEED` a named traffic jam is
added: a generated route with crossing traffic, six cars keeping pace with the ego (a lead car and a
follower in its lane, two in each lane beside it; `--escorts`), the scene where the cars around the ego
outnumber the static scene's matches. With `--stop-and-go SEED` a named stop-and-go drive is added
(`--scene stop-and-go`): the ego crawls at 0.5–3 m/s and stands for seconds at a time in a queue that
stops and goes with it, while the oncoming lane and the cross streets' traffic pass.

With `--motion-distortion` the drives are simulated with skewed sweeps (every column cast from the pose of
the moment it fires, as a real spinning sensor's) and DMLO runs with and without deskewing
(`deskew.enabled`); name "KISS-ICP deskewed" among the peers for KISS-ICP's own motion compensation.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from dmlo.peers.runner import benchmark_sequence, format_table
from dmlo.datasets import open_sequence
from dmlo.odometry import Odometry, OdometryConfig
from dmlo.simulator import simulate_sequence

TRAJECTORIES = ("07", "05", "00")  # KITTI sequences whose ground truth the drives follow, by seed
HIGHWAY_TRAJECTORY = "01"  # KITTI's highway
HIGHWAY_LASER_GAIN_SPREAD = 0.6


def _dmlo(model: Path | None, mapping: bool, symmetric: bool = False, deskew: bool = False,
          keep_moving: bool = False) -> Odometry:
    config = OdometryConfig()
    config.mapping.enabled = mapping
    config.moving_objects.detect = not keep_moving
    config.matching.symmetric = symmetric
    config.deskew.enabled = deskew
    return Odometry(model, config) if model else Odometry.from_default(config)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--seeds", type=int, nargs="*", default=[1, 2, 3])
    parser.add_argument("--poses", type=Path, default=Path(__file__).resolve().parents[2] / "shared/data/kitti_gt_poses",
                        help="folder of KITTI ground-truth pose files to drive along (default: ../shared/data)")
    parser.add_argument("--trajectories", nargs="+", default=list(TRAJECTORIES), metavar="XX",
                        help="KITTI sequence each seed's drive follows, in order (cycled; default: 07 05 00)")
    parser.add_argument("--model", type=Path, default=None)
    parser.add_argument("--peers", nargs="*", default=["KISS-ICP", "small_gicp GICP", "Open3D GICP"])
    parser.add_argument("--symmetric", action="store_true", help="add a row for DMLO with symmetric matching")
    parser.add_argument("--motion-distortion", action="store_true",
                        help="simulate skewed sweeps and add deskewed DMLO rows")
    parser.add_argument("--highway", type=int, default=None, metavar="SEED",
                        help="add the named highway drive of this scene seed (along KITTI 01)")
    parser.add_argument("--jam", type=int, default=None, metavar="SEED",
                        help="add the named traffic-jam drive of this scene seed (a generated route)")
    parser.add_argument("--stop-and-go", type=int, default=None, metavar="SEED",
                        help="add the named stop-and-go drive of this scene seed (a generated crawl with standstills)")
    parser.add_argument("--keep-moving", action="store_true",
                        help="add rows for DMLO without the moving-object network (moving_objects.detect = false)")
    parser.add_argument("--out", type=Path, default=Path("runs/bench_odometry"))
    args = parser.parse_args()

    drives = [(seed, args.trajectories[index % len(args.trajectories)], "street") for index, seed in enumerate(args.seeds)]
    if args.highway is not None:
        drives.append((args.highway, HIGHWAY_TRAJECTORY, "highway"))
    if args.jam is not None:
        drives.append((args.jam, None, "jam"))
    if args.stop_and_go is not None:
        drives.append((args.stop_and_go, None, "stop-and-go"))
    for seed, trajectory_name, scene in drives:
        trajectory = args.poses / f"{trajectory_name or 'generated'}.txt"
        drive = args.out / (f"drive_seed{seed}" if scene == "street" else f"{scene}_seed{seed}")
        if not (drive / "poses.txt").is_file():
            simulate_sequence(drive, frames=args.frames, seed=seed,
                              trajectory=trajectory if trajectory_name and trajectory.is_file() else None,
                              motion_distortion=args.motion_distortion, scene="street" if scene == "jam" else scene,
                              laser_gain_spread=HIGHWAY_LASER_GAIN_SPREAD if scene == "highway" else 0.0,
                              traffic="mixed" if scene in ("jam", "stop-and-go") else "lanes", escorts=scene == "jam")
        elif _skewed(drive) != args.motion_distortion:
            parser.error(f"{drive} holds drives {'with' if _skewed(drive) else 'without'} motion distortion; "
                         "choose another --out")
        sequence = open_sequence(drive)
        variants = {"DMLO": lambda: _dmlo(args.model, False), "DMLO + mapping": lambda: _dmlo(args.model, True)}
        if args.keep_moving:
            variants["DMLO, moving kept"] = lambda: _dmlo(args.model, False, keep_moving=True)
            variants["DMLO + mapping, moving kept"] = lambda: _dmlo(args.model, True, keep_moving=True)
        if args.symmetric:
            variants["DMLO (symmetric)"] = lambda: _dmlo(args.model, False, symmetric=True)
        if args.motion_distortion:
            variants["DMLO deskewed"] = lambda: _dmlo(args.model, False, deskew=True)
            variants["DMLO + mapping, deskewed"] = lambda: _dmlo(args.model, True, deskew=True)
        # The drive is kept and reused by the next run; its results are replaced.
        rows = benchmark_sequence(sequence, variants, args.out / drive.name, peers=args.peers, max_frames=args.frames,
                                  overwrite=True)
        source = f"KITTI {trajectory.stem}" if trajectory_name and trajectory.is_file() else "generated"
        print(f"\n### {drive.name} ({source} trajectory, {len(sequence)} frames)\n")
        print(format_table(rows))


def _skewed(drive: Path) -> bool:
    """Whether the simulated drive in `drive` was cast with motion distortion (its simulation.json)."""
    info = drive / "simulation.json"
    return bool(json.loads(info.read_text()).get("motion_distortion", False)) if info.is_file() else False


if __name__ == "__main__":
    main()
