"""`dmlo demo`: the embedded default — a simulated drive through the bundled model."""

from __future__ import annotations

import argparse
from pathlib import Path

from dmlo.cli import non_negative_int

EXAMPLES = """examples:
  dmlo demo                       # 100 frames, seed 1, results in runs/demo
  dmlo demo --frames 300 --seed 7 --no-mapping   # the paper's frame-to-frame DMLO
  dmlo demo --motion-distortion --deskew   # skewed sweeps, as a real spinning sensor's
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    from dmlo.commands.run import add_odometry_arguments

    parser = subparsers.add_parser(
        "demo",
        help="simulate a short drive and run the bundled model on it",
        description="Simulate an HDL-64E drive through a procedural street, run DMLO + mapping with the bundled "
        "model (--no-mapping: frame-to-frame DMLO), print metrics against the simulator's ground truth, and save "
        "poses and a plot.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--frames", type=int, default=100, help="scans to simulate (default: 100)")
    parser.add_argument("--seed", type=non_negative_int, default=1, help="scene and drive seed (default: 1)")
    parser.add_argument("--out", type=Path, default=Path("runs/demo"),
                        help="output folder, a previous demo's there replaced (default: runs/demo)")
    parser.add_argument("--motion-distortion", action="store_true",
                        help="simulate skewed sweeps (each column cast from the pose of its own moment)")
    add_odometry_arguments(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from dmlo.cli import UserError
    from dmlo.commands.run import build_odometry, format_summary
    from dmlo.datasets import open_sequence
    from dmlo.run import run_sequence
    from dmlo.outputs import OutputError, describe_os_error, make_folder
    from dmlo.simulator import simulate_sequence

    if args.frames < 2:
        raise UserError("--frames must be at least 2")
    drive = args.out / "drive"
    skew = ", skewed sweeps" if args.motion_distortion else ""
    print(f"simulating {args.frames} scans (seed {args.seed}{skew}) into {drive}/")
    try:
        make_folder(drive)
        simulate_sequence(drive, frames=args.frames, seed=args.seed, motion_distortion=args.motion_distortion)
    except (ValueError, OutputError) as err:  # a file in the way, scans there that a simulation did not write
        raise UserError(str(err)) from None
    except OSError as err:
        raise UserError(f"cannot write the drive into {drive}: {describe_os_error(err)}") from None
    odometry = build_odometry(args)
    try:  # the demo's own folder: an earlier demo's results there are replaced
        summary = run_sequence(open_sequence(drive), odometry, args.out / "odometry", overwrite=True)
    except OutputError as err:
        raise UserError(str(err)) from None
    print(format_summary(summary))
    return 0
