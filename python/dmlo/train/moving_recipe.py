"""The recipe of the bundled moving-object network (`models/default/moving.onnx`): its drives and training.

    python -m dmlo.train.moving_recipe --data DATA_DIR --out RUN_DIR [--poses KITTI_POSES_DIR]

simulates the labelled drives (skipping those already written; deterministic per seed) — streets with
traffic in the lanes and across, residential streets with the kerbs and parked cars close (`--scene
narrow`), traffic jams whose cars keep pace with the ego (`--escorts`), highways with and without them,
skewed sweeps and per-laser gains — and trains `dmlo.train.moving` on them,
resuming from `RUN_DIR/moving.pt`, so the same command continues an interrupted run; small enough for 2 CPU
cores (its time: docs/training.md). Then copy `RUN_DIR/moving.onnx` to `python/dmlo/models/default/`.
"""

from __future__ import annotations

import sys
from pathlib import Path

from dmlo.train.default_recipe import recipe_parser, simulate_listed_drives

# (name, KITTI trajectory or None for a generated route, first pose, seed, frames, simulator options)
DRIVES: tuple[tuple[str, str | None, int, int, int, dict[str, object]], ...] = (
    ("train/s101", None, 0, 101, 60, {}),
    ("train/s102", None, 0, 102, 60, {"traffic": "mixed"}),
    ("train/s103", None, 0, 103, 60, {"traffic": "mixed", "laser_gain_spread": 0.3}),
    ("train/s104", None, 0, 104, 60, {"escorts": True}),
    ("train/s105", None, 0, 105, 60, {"escorts": True, "traffic": "mixed"}),
    ("train/s106", "00", 500, 106, 60, {"traffic": "mixed"}),
    ("train/s107", "05", 1000, 107, 60, {"escorts": True}),
    ("train/s108", "01", 40, 108, 60, {"scene": "highway"}),
    ("train/s109", "01", 300, 109, 60, {"scene": "highway", "escorts": True, "laser_gain_spread": 0.4}),
    ("train/s110", "07", 200, 110, 60, {"motion_distortion": True, "traffic": "mixed"}),
    ("train/s111", "08", 1500, 111, 60, {"escorts": True, "motion_distortion": True}),
    ("train/s112", "02", 100, 112, 60, {"traffic": "mixed", "laser_gain_spread": 0.2}),
    ("train/s113", "06", 300, 113, 60, {}),
    ("train/s114", "01", 700, 114, 60, {"scene": "highway"}),
    # Residential streets: kerbs, hedges and parked cars as close as cars in a lane beside the ego would be.
    ("train/n121", None, 0, 121, 60, {"scene": "narrow"}),
    ("train/n122", None, 0, 122, 60, {"scene": "narrow", "traffic": "mixed"}),
    ("train/n123", None, 0, 123, 60, {"scene": "narrow", "traffic": "mixed", "escorts": True}),
    ("train/n124", "00", 1500, 124, 60, {"scene": "narrow", "traffic": "mixed"}),
    ("train/n125", "07", 600, 125, 60, {"scene": "narrow", "laser_gain_spread": 0.3}),
    ("train/n126", "05", 300, 126, 60, {"scene": "narrow", "escorts": True, "motion_distortion": True}),
    ("val/s201", None, 0, 201, 30, {"traffic": "mixed"}),
    ("val/s202", None, 0, 202, 30, {"escorts": True}),
    ("val/s203", "01", 500, 203, 30, {"scene": "highway", "escorts": True}),
    ("val/s204", "03", 100, 204, 30, {"traffic": "mixed", "motion_distortion": True}),
    ("val/n221", None, 0, 221, 30, {"scene": "narrow", "traffic": "mixed", "escorts": True}),
)
TRAIN_ARGUMENTS = "--steps 5000 --batch 16 --crop 512 --lr 3e-3 --pos-weight 3 --height-jitter 0.3 --tilt-deg 0".split()


def simulate_drives(data: Path, poses: Path) -> tuple[list[Path], list[Path]]:
    """The recipe's drives under `data` (written once), as training and held-out folders. A highway drive
    needs KITTI 01's trajectory; without `poses` the drives that follow a KITTI trajectory are left out."""
    return simulate_listed_drives(data, poses, DRIVES)


def main(argv: list[str] | None = None) -> int:
    parser = recipe_parser(__doc__)
    parser.add_argument("--steps", type=int, default=None, help="override the recipe's training steps")
    args = parser.parse_args(argv)
    train, val = simulate_drives(args.data, args.poses)
    if not train:
        parser.error(f"no training drive: {args.data}")

    from dmlo.train.moving import main as train_moving

    arguments = list(TRAIN_ARGUMENTS)
    if args.steps is not None:
        arguments += ["--steps", str(args.steps)]
    return train_moving(["--data", *map(str, train), "--val", *map(str, val), "--out", str(args.out), *arguments])


if __name__ == "__main__":
    sys.exit(main())
