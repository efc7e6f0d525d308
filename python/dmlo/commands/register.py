"""``dmlo register A B``: the motion between two scan files, as `Odometry.register_pair` finds it."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from dmlo.cli import UserError
from dmlo.commands.run import add_odometry_arguments, build_odometry

EXAMPLES = """examples:
  dmlo register 000000.bin 000001.bin
  dmlo register 000000.bin 000001.bin --no-mapping   # DMLO's matches alone, as the paper's pair
  dmlo register a.pcd b.pcd --large-motion --out T_b_a.txt
  dmlo register 000720.bin 001500.bin --loop --json
"""

DESCRIPTION = """\
Register scan B against scan A (.bin, .ply or .pcd) and print T_b_a, the 4×4 motion that carries a point
of A into B's frame (p_b = T_b_a · p_a), with the number of matches and RANSAC inliers. By default the
pair is matched like two consecutive scans of a drive, and the motion refined by NDT of B against A as its
map (DMLO + mapping; --no-mapping: the matches' motion alone); --large-motion is for scans several metres apart
(the wide-window graph from several starts along A's heading, then re-matched), --loop also tries every
30° of yaw for scans that face another way (loop closures), at 12× the cost.
"""


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    parser = subparsers.add_parser(
        "register",
        help="the motion between two scan files",
        description=DESCRIPTION,
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("reference", metavar="A", type=Path, help="reference scan (.bin, .ply, .pcd)")
    parser.add_argument("target", metavar="B", type=Path, help="target scan (.bin, .ply, .pcd)")
    parser.add_argument("--large-motion", action="store_true",
                        help="scans far apart: the wide-window graph from several starts, then re-matched")
    parser.add_argument("--loop", action="store_true",
                        help="like --large-motion, and also from every 30° of yaw (a loop closure)")
    add_odometry_arguments(parser, sequence=False)
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    parser.add_argument("--out", type=Path, default=None, metavar="FILE",
                        help="also write T_b_a to FILE as 4 rows of 4 numbers")
    parser.set_defaults(run=run)


def _read(path: Path, role: str):  # type: ignore[no-untyped-def]
    from dmlo.datasets import DatasetError, check_plausible_scan, read_scan

    if not path.is_file():
        raise UserError(f"{role} scan not found: {path}")
    try:
        points = read_scan(path)
        check_plausible_scan(path, points)
    except DatasetError as err:
        raise UserError(str(err)) from None
    return points


def run(args: argparse.Namespace) -> int:
    import numpy as np

    if args.mapping and (args.large_motion or args.loop):
        raise UserError("--mapping refines consecutive scans; --large-motion and --loop match the pair again in rounds instead")
    reference, target = _read(args.reference, "reference"), _read(args.target, "target")
    odometry = build_odometry(args)
    start = time.perf_counter()
    try:
        result = odometry.register_pair(reference, target, large_motion=args.large_motion or args.loop)
    except ValueError as err:  # a scan too sparse to register
        raise UserError(str(err)) from None
    seconds = time.perf_counter() - start
    transform = np.asarray(result.T_tgt_ref, dtype=np.float64)
    if args.out:
        from dmlo.outputs import OutputError, atomic_output, make_folder

        try:
            make_folder(args.out.parent, "folder of --out")
            with atomic_output(args.out) as temporary:
                np.savetxt(temporary, transform, fmt="%.9f")
        except OutputError as err:
            raise UserError(str(err)) from None
    if args.json:
        print(json.dumps({
            "T_b_a": transform.tolist(),
            "matches": result.num_matches,
            "inliers": result.num_inliers,
            "inlier_ratio": result.inlier_ratio,
            "rounds": result.rounds,
            "map_refined": result.map_refined,
            "seconds": seconds,
        }))
        return 0
    rows = "\n".join("  " + " ".join(f"{value:12.6f}" for value in row) for row in transform)
    print(f"T_b_a (p_b = T_b_a · p_a):\n{rows}")
    print(f"{result.num_inliers} of {result.num_matches} matches are RANSAC inliers; "
          f"{result.rounds} matching round(s), {seconds:.2f} s")
    if result.map_refined is not None:
        print("refined against A (mapping: NDT, or point-to-plane ICP for a pair that stands still)" if result.map_refined
              else "warning: the alignment against A did not converge; the matches' motion is kept")
    # Fewer than min_inliers inliers: the crate's notice, a PairWarning on stderr (with --json too).
    return 0
