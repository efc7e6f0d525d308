"""How close the real-scan benchmark's reference comes to the truth, on simulated drives that have one.

    python benchmarks/reference.py [--seeds 5 6 ... 12] [--frames 8] [--spans 1 2 3]

`benchmarks/real.py` judges every method against the consensus of two GICPs, since KITTI's own ground truth
is too coarse for centimetre pairs. This measures that judge: it simulates short street drives, builds the
consensus of each for every span (1: each consecutive pair's scan-to-scan consensus alone; more: every pair
up to that many scans apart, solved jointly) and compares its pair motions with the simulator's truth.
Translation error a pair in cm, mean over each drive's pairs; the GICPs that are installed are used.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from dmlo.datasets import open_sequence
from dmlo.peers.consensus import available_gicps, gicp_consensus
from dmlo.simulator import simulate_sequence


def reference_errors_cm(folder: Path, spans: list[int]) -> dict[int, float]:
    """Per span: the mean translation error a pair (cm) of the drive's consensus against its truth."""
    sequence = open_sequence(folder)
    scans = [sequence[i].points for i in range(len(sequence))]
    truth = sequence.poses
    assert truth is not None
    true_motions = np.linalg.inv(truth[:-1]) @ truth[1:]
    errors = {}
    for span in spans:
        motions = gicp_consensus(scans, truth, span=span).motions
        errors[span] = float(np.linalg.norm((np.linalg.inv(true_motions) @ motions)[:, :3, 3], axis=1).mean() * 100)
    return errors


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(5, 13)))
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--spans", type=int, nargs="+", default=[1, 2, 3])
    args = parser.parse_args(argv)
    if args.frames < 2:
        parser.error("--frames: a pair needs at least 2 frames")
    if min(args.spans) < 1:
        parser.error("--spans: each at least 1 (consecutive pairs)")
    print(f"reference: {' + '.join(available_gicps())}; {len(args.seeds)} simulated drives of {args.frames} scans")
    per_drive: dict[int, list[float]] = {span: [] for span in args.spans}
    with tempfile.TemporaryDirectory() as scratch:
        for seed in args.seeds:
            folder = Path(scratch) / f"seed{seed}"
            simulate_sequence(folder, frames=args.frames, seed=seed, progress=False)
            for span, error in reference_errors_cm(folder, args.spans).items():
                per_drive[span].append(error)
    print("\n| span | t mean cm | worst drive cm | per drive |\n|---|---|---|---|")
    for span, errors in per_drive.items():
        print(f"| {span} | {np.mean(errors):.2f} | {np.max(errors):.2f} | {' '.join(f'{e:.2f}' for e in errors)} |")


if __name__ == "__main__":
    main()
