"""A small Table V: the paper's ablations trained under one budget, then measured the same way.

    python -m dmlo.train.ablation --data DATA_DIR --out RUNS_DIR [--epochs 1] [--variants fast no_norm ...]

Every variant trains from scratch on the default recipe's simulated drives with the same seed, data order,
optimiser and number of steps, is exported to ONNX, and is measured by `benchmarks/matching.py` on the
held-out drives (EPE and Fl-all over all cells and over the kept matches, pose error after RANSAC, time per
frame). Finished variants are skipped and an interrupted one resumes, so the same command continues a run;
`RUNS_DIR/ablation.json` and `RUNS_DIR/ablation.md` collect the rows.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dmlo.train.default_recipe import simulate_drives

# name → (what it changes, the training options that make it); all on top of BASE_ARGUMENTS
VARIANTS: dict[str, tuple[str, list[str]]] = {
    "fast": ("bundled model's structure: L2 features, sub-pixel loss, 5 plain refine convs", ["--preset", "fast"]),
    "no_norm": ("without feature normalisation", ["--preset", "fast", "--no-feature-norm"]),
    "one_hot": ("one-hot instead of sub-pixel loss", ["--preset", "fast", "--one-hot-loss"]),
    "light": ("1 deformable refine conv (4 plain + 1 deformable)", ["--preset", "light"]),
    "paper": ("paper's refine: 2 plain + 3 deformable, 16 ch", ["--preset", "paper"]),
}

BASE_ARGUMENTS = (
    "--coarse-window 15 --optimizer adam --lr 0.001 --batch-size 4 --crop-width 448 --val-max-pairs 32 "
    "--val-width 896 --checkpoint-every 25 --seed 0 --resume --no-progress"
).split()


def train_variant(name: str, train: list[Path], val: list[Path], run: Path, epochs: int) -> None:
    from dmlo.train.__main__ import main as train_main

    options = VARIANTS[name][1]
    arguments = ["--data", *map(str, train), "--val", *map(str, val), "--out", str(run)]
    train_main([*arguments, *BASE_ARGUMENTS, "--epochs", str(epochs), "--lr-step", str(epochs), *options])


def export_variant(run: Path) -> Path:
    from dmlo.cli import main as dmlo_main

    model = run / "onnx"
    if not (model / "frame.onnx").is_file() and dmlo_main(["export", str(run / "last.pt"), "--out", str(model), "--graphs", "frame"]):
        raise RuntimeError(f"exporting {run} failed")
    return model


def last_log_row(run: Path) -> dict[str, float]:
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if line.strip()]
    return rows[-1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="folder of the default recipe's simulated drives")
    parser.add_argument("--out", type=Path, required=True, help="folder for one run per variant and the results")
    parser.add_argument("--epochs", type=int, default=1, help="training epochs per variant (the same for all)")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--poses", type=Path, default=Path(__file__).resolve().parents[4] / "shared/data/kitti_gt_poses",
                        help="KITTI ground-truth pose files the drives follow (as in the default recipe)")
    parser.add_argument("--pairs", type=int, default=10, help="consecutive held-out pairs per drive for the pose error")
    args = parser.parse_args(argv)
    train, val = simulate_drives(args.data, args.poses if args.poses.is_dir() else None)

    from dmlo.metrics.matching import evaluate

    results_path = args.out / "ablation.json"
    results = json.loads(results_path.read_text()) if results_path.is_file() else {}
    for name in args.variants:
        run = args.out / name
        if name in results and results[name]["epochs"] == args.epochs:
            continue
        train_variant(name, train, val, run, args.epochs)
        log = last_log_row(run)
        measured = evaluate(export_variant(run), val, args.pairs)
        results[name] = {"change": VARIANTS[name][0], "epochs": args.epochs, "steps": log["step"],
                         "val_epe": log["val_epe"], "val_fl_all": log["val_fl_all"], **measured}
        args.out.mkdir(parents=True, exist_ok=True)
        results_path.write_text(json.dumps(results, indent=2) + "\n")
        (args.out / "ablation.md").write_text(markdown_table(results))
        print(markdown_table(results), flush=True)
    return 0


def markdown_table(results: dict[str, dict]) -> str:
    lines = [
        "| variant | change | steps | val EPE px | val Fl-all % | EPE kept px | rot. err ° | transl. err cm | network ms |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        lines.append(
            f"| {name} | {r['change']} | {r['steps']} | {r['val_epe']:.2f} | {r['val_fl_all']:.1f} | "
            f"{r['kept_epe']:.2f} | {r['rotation_deg']:.3f} | {100 * r['translation_m']:.2f} | {r['network_ms']:.0f} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
