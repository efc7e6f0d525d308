"""`dmlo simulate`: write a simulated drive as a KITTI odometry sequence or an Argoverse 1 log."""

from __future__ import annotations

import argparse
from typing import Any

from dmlo.cli import non_negative_int, positive_int


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "simulate",
        help="simulate a LiDAR drive through a procedural street (KITTI or Argoverse 1 layout)",
        description=(
            "Simulates a LiDAR driving through a procedural street (buildings, poles, trees, parked and "
            "moving cars). --sensor hdl64e (KITTI's HDL-64E) writes KITTI layout: OUT/velodyne/*.bin, "
            "OUT/labels/*.label (SemanticKITTI, moving cars 252), poses.txt (camera frame), calib.txt, "
            "times.txt. --sensor argoverse (Argoverse 1's two stacked VLP-32C, sweeps in the ego frame) "
            "writes an Argoverse 1 log: OUT/lidar/PC_<ns>.ply (x y z intensity laser_number), "
            "OUT/poses/city_SE3_egovehicle_<ns>.json, vehicle_calibration_info.json and "
            "labels/PC_<ns>.label. "
            "Both also write simulation.json. The same arguments always give identical files."
        ),
        epilog="examples:\n"
        "  dmlo simulate --frames 50 --seed 1 --out runs/sim01\n"
        "  dmlo simulate --frames 200 --seed 2 --out runs/sim00 "
        "--trajectory ../shared/data/kitti_gt_poses/00.txt --start 300\n"
        "  dmlo simulate --frames 100 --seed 3 --sensor argoverse --traffic mixed --out runs/av_sim03\n",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--frames", type=positive_int, default=50, help="number of scans (default 50)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="scene and noise seed (default 0)")
    parser.add_argument("--out", required=True, help="output sequence folder")
    parser.add_argument(
        "--trajectory",
        help="KITTI camera-frame pose file to drive along (12 floats a line); default: a generated drive",
    )
    parser.add_argument("--start", type=non_negative_int, default=0, help="first pose of --trajectory to use (default 0)")
    parser.add_argument(
        "--calib", help="KITTI calib.txt whose Tr converts --trajectory (default: KITTI 00-02 Tr)"
    )
    parser.add_argument(
        "--sensor",
        choices=("hdl64e", "argoverse"),
        default="hdl64e",
        help="hdl64e: KITTI's Velodyne HDL-64E; argoverse: Argoverse 1's two VLP-32C (default hdl64e)",
    )
    parser.add_argument(
        "--layout",
        choices=("kitti", "argoverse"),
        help="output layout (default: the sensor's own, kitti for hdl64e, argoverse for argoverse)",
    )
    parser.add_argument(
        "--traffic",
        choices=("lanes", "mixed"),
        default="lanes",
        help="lanes: moving cars only in the lanes along the ego's street (as earlier versions); mixed: "
        "also cross streets with cars crossing and turning on their own paths (default lanes)",
    )
    parser.add_argument(
        "--scene",
        choices=("street", "highway", "narrow", "stop-and-go"),
        default="street",
        help="street: buildings, furniture, parked cars (default); narrow: a residential street, kerbs 3.5-5.5 m "
        "away and cars parked along them, no lanes beside the ego's; highway: wide asphalt, guard rails, sparse "
        "sign poles, fast lanes (drive it along a highway trajectory, e.g. KITTI 01's); stop-and-go: a street in a "
        "traffic jam, the queue in the ego's lane and the one to its right stopping and going with it, the oncoming "
        "lane flowing (without --trajectory the ego crawls and stands)",
    )
    parser.add_argument(
        "--laser-gain-spread",
        type=float,
        default=0.0,
        metavar="S",
        help="each laser's reflectance scaled by its own gain, uniform in 1 ± S (0 ≤ S < 1; default 0): real "
        "sensors' lasers differ in intensity calibration, so the road's rings differ in brightness",
    )
    parser.add_argument(
        "--escorts",
        action="store_true",
        help="six cars keep pace with the ego (lead car, follower, two beside on each side): a traffic jam",
    )
    parser.add_argument(
        "--motion-distortion",
        action="store_true",
        help="the sensor moves while it spins (raw-KITTI-like skew); default: instantaneous sweeps",
    )
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace scans in OUT even if the simulator did not write them",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from dmlo.cli import UserError
    from dmlo.simulator import simulate_sequence

    try:
        result = simulate_sequence(
            args.out,
            frames=args.frames,
            seed=args.seed,
            trajectory=args.trajectory,
            start=args.start,
            calib=args.calib,
            progress=not args.quiet,
            sensor=args.sensor,
            layout=args.layout,
            traffic=args.traffic,
            scene=args.scene,
            laser_gain_spread=args.laser_gain_spread,
            escorts=args.escorts,
            motion_distortion=args.motion_distortion,
            overwrite=args.overwrite,
        )
    except (ValueError, FileNotFoundError) as err:
        raise UserError(str(err)) from None
    except OSError as err:  # a file in the way of --out, a full disk
        from dmlo.outputs import describe_os_error

        where = f" {err.filename}" if err.filename else ""
        raise UserError(f"cannot write{where}: {describe_os_error(err)}") from None
    if not args.quiet:
        frames = len(result.points_per_frame)
        mean_points = sum(result.points_per_frame) / frames
        cast_ms = 1000 * sum(result.cast_seconds) / frames
        frame_ms = 1000 * sum(result.frame_seconds) / frames
        print(
            f"wrote {frames} scans to {result.out_dir} ({mean_points:.0f} points a scan; ray casting "
            f"{cast_ms:.0f} ms, whole frame {frame_ms:.0f} ms; "
            f"scene of {result.static_primitives} primitives "
            f"built in {result.scene_seconds:.2f} s)"
        )
    return 0
