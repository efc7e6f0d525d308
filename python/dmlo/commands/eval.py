"""``dmlo eval GT EST``: odometry metrics of an estimated trajectory against the ground truth."""

from __future__ import annotations

import argparse
import json
import math
import warnings
from pathlib import Path
from typing import Any

from dmlo.cli import UserError

HELP = "Evaluate an estimated trajectory against ground truth (KITTI t_rel/r_rel, ATE, RPE)."

DESCRIPTION = """\
Evaluate an estimated trajectory against the ground truth. Both files hold one pose a line, KITTI
(12 numbers, the top 3×4 of the matrix) or TUM (timestamp tx ty tz qx qy qz qw); poses are paired by line
order, so both files need the same number of poses.

Prints the KITTI odometry metrics t_rel (%) and r_rel (°/100 m) over segments of 100…800 m (as the
official devkit; null for paths shorter than 100 m), the absolute trajectory error after an SE(3) Umeyama
alignment, and the relative pose error between consecutive frames.
"""


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    parser = subparsers.add_parser(
        "eval", help=HELP, description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n"
        "  dmlo eval runs/sim/ground_truth_kitti.txt runs/sim/poses_kitti.txt --plot trajectory.png\n"
        "  dmlo eval poses/07.txt est_07.txt --calib sequences/07/calib.txt --json\n",
    )
    parser.add_argument("ground_truth", metavar="GT", type=Path, help="ground-truth pose file")
    parser.add_argument("estimate", metavar="EST", type=Path, help="estimated pose file")
    parser.add_argument(
        "--format",
        choices=("kitti", "tum"),
        default=None,
        help="pose file format of both files (default: detected from the number of columns)",
    )
    parser.add_argument(
        "--align",
        choices=("se3", "sim3", "none"),
        default="se3",
        help="alignment of the estimate before the ATE (default: se3)",
    )
    parser.add_argument("--delta", type=int, default=1, help="RPE frame distance (default: 1)")
    parser.add_argument(
        "--calib",
        type=Path,
        default=None,
        help="KITTI calib.txt: the estimate holds LiDAR poses and the ground truth camera poses; "
        "convert the estimate with Tr (P = Tr · T · Tr⁻¹) before comparing",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    parser.add_argument("--plot", type=Path, default=None, metavar="FILE", help="write a top-view PNG")
    parser.set_defaults(run=run)


def _read(path: Path, fmt: str | None, role: str) -> Any:
    from dmlo import poses

    if not path.is_file():
        raise UserError(f"{role} file not found: {path}")
    try:
        return poses.read_poses(path, fmt)[1]  # type: ignore[arg-type]
    except poses.PoseFileError as err:
        raise UserError(str(err)) from None


def _fmt(value: float | None, digits: int = 4) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def format_table(result: dict[str, Any]) -> str:
    lines = [
        f"poses          {result['poses']}  ({result['path_length']:.1f} m ground-truth path)",
        f"t_rel          {_fmt(result['t_rel'])} %      ({result['segments']} segments of 100-800 m)",
        f"r_rel          {_fmt(result['r_rel'])} deg/100 m",
        f"ATE rmse       {_fmt(result['ate_rmse'])} m      "
        f"(mean {_fmt(result['ate_mean'])}, max {_fmt(result['ate_max'])}; {result['ate_alignment']} aligned)",
        f"RPE t mean     {_fmt(result['rpe_t_mean'])} m      (max {_fmt(result['rpe_t_max'])}; "
        f"delta {result['rpe_delta']} frame{'s' if result['rpe_delta'] != 1 else ''})",
        f"RPE r mean     {_fmt(result['rpe_r_mean'])} deg    (max {_fmt(result['rpe_r_max'])})",
    ]
    if result["note"]:
        lines.append(f"note: {result['note']}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from dmlo import poses

    if args.delta < 1:
        raise UserError(f"--delta must be at least 1, got {args.delta}")
    poses_gt = _read(args.ground_truth, args.format, "ground-truth")
    poses_est = _read(args.estimate, args.format, "estimate")
    if len(poses_gt) != len(poses_est):
        raise UserError(
            f"{args.ground_truth} has {len(poses_gt)} poses but {args.estimate} has {len(poses_est)}; "
            "poses are paired by line, so both need the same number"
        )
    if args.calib is not None:
        if not args.calib.is_file():
            raise UserError(f"calibration file not found: {args.calib}")
        try:
            tr = poses.read_kitti_calib(args.calib)["Tr"]
        except poses.PoseFileError as err:
            raise UserError(str(err)) from None
        poses_est = poses.lidar_to_camera(poses_est, tr)

    from dmlo.metrics import evaluate_trajectory

    alignment = None if args.align == "none" else args.align
    try:
        result = evaluate_trajectory(poses_gt, poses_est, alignment, args.delta)
    except ValueError as err:
        raise UserError(str(err)) from None

    plotted = False
    if args.plot is not None:
        from dmlo.plot import PlotUnavailable, plot_trajectories

        try:
            plot_trajectories(
                poses_gt, poses_est, args.plot, title=f"{args.estimate.name} vs {args.ground_truth.name}"
            )
            plotted = True
        except PlotUnavailable as err:  # the metrics are still printed; the plot is optional
            warnings.warn(f"--plot skipped: {err}", stacklevel=2)
        except OSError as err:
            raise UserError(f"cannot write the plot {args.plot}: {err}") from None

    if args.json:
        print(json.dumps(result))
    else:
        print(format_table(result))
        if plotted:
            print(f"plot           {args.plot}")
    return 0
