"""Accuracy and speed of exported models on held-out drives, through the odometry's own code path.

For pairs of consecutive scans: EPE and Fl-all of the network's flow over every cell with ground truth
(Eq. 5–8) and over the NMS-kept matches the pose is solved from, the pair's pose error after RANSAC, and
the per-frame time of the network and of the whole pair — one row per model, measured in one run.

    python benchmarks/matching.py DRIVE [DRIVE ...] --models python/dmlo/models/default other/
"""

from __future__ import annotations

import argparse
from pathlib import Path

from dmlo.metrics.matching import evaluate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("drives", type=Path, nargs="+", help="held-out sequences with ground truth")
    parser.add_argument("--models", type=Path, nargs="+", required=True, help="model folders (frame.onnx inside)")
    parser.add_argument("--pairs", type=int, default=10, help="consecutive pairs per drive")
    parser.add_argument("--without-coherence", action="store_true",
                        help="also a row per model with the network's confidence as it is (matching.coherence_px off)")
    args = parser.parse_args()
    print("| model | EPE px | Fl-all % | EPE kept px | Fl kept % | rot. err ° | transl. err m | network ms | network + decode + NMS + RANSAC ms |")
    print("|---|---|---|---|---|---|---|---|---|")
    variants = [(model, True) for model in args.models]
    if args.without_coherence:
        variants += [(model, False) for model in args.models]
    for model, coherence in variants:
        r = evaluate(model, args.drives, args.pairs, coherence)
        name = model if coherence else f"{model}, no coherence"
        print(
            f"| {name} | {r['epe']:.2f} | {r['fl_all']:.1f} | {r['kept_epe']:.2f} | {r['kept_fl_all']:.1f} | "
            f"{r['rotation_deg']:.3f} | {r['translation_m']:.3f} | {r['network_ms']:.0f} | {r['pair_ms']:.0f} |"
        )


if __name__ == "__main__":
    main()
