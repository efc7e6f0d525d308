"""`dmlo bench`: DMLO and the installed peers on the same scans, in one process, one table."""

from __future__ import annotations

import argparse
from pathlib import Path

EXAMPLES = """examples:
  dmlo bench sim_drive/ --max-frames 200
  dmlo bench /data/kitti --sequence 07 --peers KISS-ICP "small_gicp GICP"
  dmlo bench skewed_drive/ --deskew
  dmlo bench sim_drive/ --no-mapping        # the paper's frame-to-frame DMLO row alone
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    from dmlo.commands.run import add_dataset_arguments, add_odometry_arguments

    parser = subparsers.add_parser(
        "bench",
        help="compare DMLO with KISS-ICP, small_gicp and Open3D on the same scans",
        description="Run DMLO and every installed peer (KISS-ICP, small_gicp, Open3D ICP/GICP, "
        "Open3D FPFH+RANSAC) on the same scans and print drift, speed and the ratio to KISS-ICP; DMLO in two "
        "rows, frame-to-frame and + mapping (--no-mapping: the first alone).",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("path", type=Path, help="dataset folder with ground-truth poses")
    add_dataset_arguments(parser)
    parser.add_argument("--peers", nargs="*", default=None,
                        help="peer names to run (default: every installed peer except FPFH+RANSAC and "
                        "KISS-ICP deskewed; with --deskew, KISS-ICP deskewed too)")
    parser.add_argument("--out", type=Path, default=Path("runs/bench"))
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the files of an earlier run in --out (refused otherwise)")
    add_odometry_arguments(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from dmlo.peers.runner import UnknownPeerError, benchmark_sequence, format_table
    from dmlo.cli import UserError
    from dmlo.commands.run import build_odometry
    from dmlo.datasets import DatasetError, open_sequence
    from dmlo.outputs import OutputError

    try:
        sequence = open_sequence(args.path, format=args.format, sequence=args.sequence)
    except DatasetError as err:
        raise UserError(str(err)) from err
    if sequence.poses is None:
        raise UserError(f"{args.path} has no ground-truth poses to compare against")
    settings = [
        label
        for label, on in (("symmetric", args.symmetric), ("no coherence", args.no_coherence), ("deskewed", args.deskew))
        if on
    ]
    if args.matching_stage in ("crate", "graph"):  # only speed differs: say where the matching ran
        settings.append("matching in " + ("the crate" if args.matching_stage == "crate" else "onnxruntime"))
    peers = args.peers
    if peers is None and args.deskew:  # compare with the peer that compensates its sweeps too
        from dmlo.peers.peers import PEERS

        peers = [p.name for p in PEERS if (p.by_default or p.name == "KISS-ICP deskewed") and p.available]
    name = f"DMLO ({', '.join(settings)})" if settings else "DMLO"
    variants = {name: lambda: build_odometry(args, mapping=False)}
    if args.mapping is not False:  # both rows unless --no-mapping
        variants[f"{name} + mapping"] = lambda: build_odometry(args, mapping=True)
    try:
        rows = benchmark_sequence(sequence, variants, args.out, peers=peers, max_frames=args.max_frames,
                                  overwrite=args.overwrite)
    except (UnknownPeerError, OutputError) as err:
        raise UserError(str(err)) from err
    print(format_table(rows))
    return 0
