"""The recipe of the bundled default model: its simulated drives and its training command, in one place.

    python -m dmlo.train.default_recipe --data DATA_DIR --out RUN_DIR [--poses KITTI_POSES_DIR]
        [--finetune | --range-only | --range-only-pose | --sensor-variety | --sensor-variety-pose | --scenes
         | --scenes-pose | --reflectance-robust | --reflectance-robust-pose | --kitti-reflectance
         | --kitti-reflectance-pose] [--device auto|cpu|cuda]

simulates the drives (skipping those already written; deterministic per seed) and then trains, resuming
from `RUN_DIR/last.pt` when it exists, so the same command continues an interrupted run. `--finetune` runs
the second stage instead: from `RUN_DIR/best.pt`, full-width pairs with the pose loss (beyond the paper),
into `RUN_DIR/finetune`. Afterwards `dmlo export RUN_DIR/finetune --out python/dmlo/models/default
--wide-window 41 --refine-window 7` refreshes the bundled model (its refine window, 5 in training, widened
to 7 at inference).

`--range-only` makes the range-only model that the odometry runs on scans without a usable reflectance:
the bundled model's final weights (`models/default/training/finetune/best.pt`, or `--init CKPT`) fine-tuned
with the reflectance channel zeroed in every sample (`--no-reflectance`), into `RUN_DIR/range_only`,
resumable like the other stages; two epochs on 448-column crops, sized to finish within 10 minutes on one
GPU (about an hour on 2 CPU cores; `best.pt` from the first epoch's validation on). Then `dmlo export
RUN_DIR/range_only --out python/dmlo/models/default/range_only --wide-window 41 --refine-window 7`.

`--range-only-pose` gives the range-only model the bundled model's last stage (whole images, the pose loss),
with the reflectance zeroed as in its crop stage, from the range-only weights
(`models/default/training/range_only/best.pt`, or `--init CKPT`), into `RUN_DIR/range_only_pose`: the crop
stage alone loses what the whole-image pose-loss stage taught. One epoch; on 2 CPU cores it spans sessions
(`--resume` continues it), on one GPU it is a single run.

`--sensor-variety` fine-tunes the same final weights (or `--init CKPT`) on pairs with a real sensor's row
artefacts — per-laser reflectance gains and partly empty rows (`Augmentation`) — into
`RUN_DIR/sensor_variety`: the simulator's even, equally bright lasers taught the matcher to follow the
stripes of a real sensor's rings, which stay in their rows and pull the vertical flow towards zero. Sized
like the range-only stage; export it as the bundled model with the same `dmlo export` options.

`--sensor-variety-pose` is the bundled model's last stage again (whole images, the pose loss) with the same
row artefacts, from the final weights (or `--init CKPT`), into `RUN_DIR/sensor_variety_pose`: the crop stage
above loses what the whole-image pose-loss stage taught. One epoch; on 2 CPU cores it spans sessions
(`--resume` continues it), on one GPU it is a single run.

`--scenes` fine-tunes the final weights (or `--init CKPT`) on the recipe's drives and the scenes where real
drives failed (`SCENE_DRIVES`: feature-poor highways with per-laser gains, traffic keeping pace around the
ego, stop-and-go queues, mixed traffic), into `RUN_DIR/scenes`: two epochs on 448-column crops, held out
on the recipe's validation drives and a highway and a jam of its own. Sized like the range-only stage.

`--scenes-pose` is the bundled model's last stage (whole images, the pose loss) on the same drives as
`--scenes`, from that stage's weights (`RUN_DIR/scenes/best.pt`, or `--init CKPT`), into
`RUN_DIR/scenes_pose`: the crop stage loses what the whole-image stage taught. One epoch; on 2 CPU cores it
spans sessions (`--resume` continues it), on one GPU it is a single run.

`--reflectance-robust` fine-tunes the final weights (or `--init CKPT`) on pairs whose reflectance looks
like a real sensor's in the ways the simulator's does not: per-laser gains, a random monotone calibration
curve rounded to KITTI's 0.01 steps, a fade with range, cells of zero reflectance, and a quarter of the
pairs without it (`REFLECTANCE_ROBUST_AUGMENTATION`), into `RUN_DIR/reflectance_robust`: frame-to-frame
DMLO's pitch bias on real drives comes through what the matcher learned from the simulator's reflectance,
and the range-only model, which never reads it, has none on most real sets. Flow loss on 448-column crops
at the range-only stage's learning rate, two epochs: sized like the range-only stage (one GPU run of a few
minutes; on 2 CPU cores it spans sessions, the same command resuming it).

`--reflectance-robust-pose` is the bundled model's last stage (whole images, the pose loss) with the same
reflectance augmentations, from that stage's weights (`RUN_DIR/reflectance_robust/best.pt`, or `--init
CKPT`), into `RUN_DIR/reflectance_robust_pose`: the crop stage loses what the whole-image stage taught. One
epoch; on 2 CPU cores it spans sessions, on one GPU it is a single run.

`--kitti-reflectance` fine-tunes the final weights (or `--init CKPT`) on the recipe's drives simulated again
with a real KITTI HDL-64E's reflectance (`simulate_sequence(reflectance="kitti")`: per-laser gains and
offsets, a fade with range to zero beyond ~50 m, zeros at grazing incidence, 0.01 steps; calibrated on the
shared real scans' per-row reflectance histograms, `dmlo.simulator.reflectance`), the same seeds, places and
points as `DRIVES`, under `DATA/kitti_reflectance/`, into `RUN_DIR/kitti_reflectance`: the simulator's
reflectance, not the matcher, is what differed from a real scan's. Flow loss on 448-column crops at the
range-only stage's learning rate, per-laser gains of ±0.2 on top (another sensor's lasers), two epochs: one
GPU run of a few minutes (`--device cuda`); on 2 CPU cores it spans sessions, the same command resuming it.

`--kitti-reflectance-pose` is the bundled model's last stage (whole images, the pose loss) on the same
drives, from that stage's weights (`RUN_DIR/kitti_reflectance/best.pt`, or `--init CKPT`), into
`RUN_DIR/kitti_reflectance_pose`. One epoch.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

# (name, KITTI ground-truth trajectory the drive follows, seed, first pose of that trajectory, frames)
DRIVES = (
    ("train_00", "00", 11, 0, 150),
    ("train_02", "02", 12, 500, 150),
    ("train_05", "05", 13, 200, 150),
    ("train_08", "08", 14, 1000, 150),
    ("train_01", "01", 15, 100, 150),
    ("train_06", "06", 16, 0, 150),
    ("train_gen", None, 17, 0, 150),
    ("val_07", "07", 21, 0, 60),
    ("val_04", "04", 22, 0, 60),
)

# The scenes the real-drive issue added to the simulator, for the `--scenes` stage: (name, KITTI trajectory
# or None for a generated route, first pose, seed, frames, simulator options), as `moving_recipe.DRIVES`. The highways follow KITTI 01
# from pose 400 on, away from the odometry benchmark's highway (its first 300 poses); no seed is one of
# the benchmark's drives.
SCENE_DRIVES: tuple[tuple[str, str | None, int, int, int, dict[str, object]], ...] = (
    ("scenes_highway", "01", 400, 51, 100, {"scene": "highway", "laser_gain_spread": 0.6}),
    ("scenes_highway_escorts", "01", 600, 52, 100, {"scene": "highway", "escorts": True, "laser_gain_spread": 0.4}),
    ("scenes_jam", None, 0, 53, 100, {"escorts": True, "traffic": "mixed"}),
    ("scenes_stop_and_go", None, 0, 54, 100, {"scene": "stop-and-go", "traffic": "mixed"}),
    ("scenes_street_gains", "08", 2500, 55, 100, {"traffic": "mixed", "laser_gain_spread": 0.4}),
    ("val_scenes_highway", "01", 900, 61, 40, {"scene": "highway", "laser_gain_spread": 0.6}),
    ("val_scenes_jam", None, 0, 62, 40, {"escorts": True, "traffic": "mixed"}),
)

TRAIN_ARGUMENTS = (
    "--preset fast --coarse-window 15 --optimizer adam --lr 0.001 --lr-step 8 --epochs 24 --batch-size 4 "
    "--crop-width 448 --val-max-pairs 32 --val-width 896 --checkpoint-every 25 --resume --mirror"
).split()

# The second stage: the whole 64×1792 image, as the odometry sees it, and a small pose-loss weight (a larger
# one, 1.0, lowered the confidence ranking: fewer RANSAC inliers and a few wrong consensuses).
FINETUNE_ARGUMENTS = (
    "--pose-loss-weight 0.2 --optimizer adam --lr 1e-4 --lr-step 1 --epochs 2 --batch-size 2 --crop-width 0 "
    "--val-max-pairs 32 --val-width 0 --checkpoint-every 50 --resume --mirror"
).split()


# The range-only stage: the flow loss on 448-column crops, as the first stage, from the final weights.
RANGE_ONLY_ARGUMENTS = (
    "--no-reflectance --optimizer adam --lr 5e-4 --lr-step 1 --epochs 2 --batch-size 4 --crop-width 448 "
    "--val-max-pairs 32 --val-width 896 --checkpoint-every 25 --resume --mirror"
).split()
# The range-only pose stage: the second stage's whole images and pose loss, with the reflectance zeroed.
RANGE_ONLY_POSE_ARGUMENTS = (
    "--no-reflectance --pose-loss-weight 0.2 --optimizer adam --lr 1e-4 --lr-step 1 --epochs 1 --batch-size 2 "
    "--crop-width 0 --val-max-pairs 32 --val-width 0 --checkpoint-every 25 --resume --mirror"
).split()
# The sensor-variety stage: the flow loss on 448-column crops with per-row gains and row dropout.
SENSOR_VARIETY_ARGUMENTS = (
    "--laser-gain-spread 0.6 --row-dropout 0.4 --optimizer adam --lr 1e-4 --lr-step 1 --epochs 2 --batch-size 4 "
    "--crop-width 448 --val-max-pairs 32 --val-width 896 --checkpoint-every 25 --resume --mirror"
).split()
# The sensor-variety pose stage: the second stage's whole images and pose loss, with the row artefacts.
SENSOR_VARIETY_POSE_ARGUMENTS = (
    "--laser-gain-spread 0.6 --row-dropout 0.4 --pose-loss-weight 0.2 --optimizer adam --lr 1e-4 --lr-step 1 "
    "--epochs 1 --batch-size 2 --crop-width 0 --val-max-pairs 32 --val-width 0 --checkpoint-every 25 --resume --mirror"
).split()
# The scenes stage: the flow loss on 448-column crops of the recipe's drives and the scene drives.
SCENES_ARGUMENTS = (
    "--optimizer adam --lr 1e-4 --lr-step 1 --epochs 2 --batch-size 4 --crop-width 448 --val-max-pairs 48 "
    "--val-width 896 --checkpoint-every 25 --resume --mirror"
).split()
# The scenes pose stage: the second stage's whole images and pose loss on the scenes stage's drives.
SCENES_POSE_ARGUMENTS = (
    "--pose-loss-weight 0.2 --optimizer adam --lr 1e-4 --lr-step 1 --epochs 1 --batch-size 2 --crop-width 0 "
    "--val-max-pairs 48 --val-width 0 --checkpoint-every 25 --resume --mirror"
).split()
# The reflectance-robust stage: the range-only stage's crops and learning rate, with the reflectance kept but
# made untrustworthy in the ways a real sensor's differs from the simulator's.
REFLECTANCE_ROBUST_ARGUMENTS = (
    "--laser-gain-spread 0.6 --reflectance-dropout 0.25 --optimizer adam --lr 5e-4 --lr-step 1 --epochs 2 "
    "--batch-size 4 --crop-width 448 --val-max-pairs 32 --val-width 896 --checkpoint-every 25 --resume --mirror"
).split()
# The reflectance-robust pose stage: the second stage's whole images and pose loss, with the same reflectance.
REFLECTANCE_ROBUST_POSE_ARGUMENTS = (
    "--laser-gain-spread 0.6 --reflectance-dropout 0.25 --pose-loss-weight 0.2 --optimizer adam --lr 1e-4 "
    "--lr-step 1 --epochs 1 --batch-size 2 --crop-width 0 --val-max-pairs 32 --val-width 0 --checkpoint-every 25 "
    "--resume --mirror"
).split()
# Their augmentations beyond `dmlo train`'s options (`TrainConfig` fields): most pairs remapped, half faded with
# range, up to a sixth of the cells dark, as the shared real scans' reflectance is.
REFLECTANCE_ROBUST_AUGMENTATION = {"reflectance_remap": 0.75, "reflectance_falloff": 0.5, "reflectance_zeros": 0.15}
# The stages on drives with the calibrated reflectance: the range-only stage's crops and learning rate, then the
# second stage's whole images and pose loss; per-laser gains of ±0.2 on top of the calibrated ones.
KITTI_REFLECTANCE_ARGUMENTS = (
    "--laser-gain-spread 0.2 --optimizer adam --lr 5e-4 --lr-step 1 --epochs 2 --batch-size 4 --crop-width 448 "
    "--val-max-pairs 32 --val-width 896 --checkpoint-every 25 --resume --mirror"
).split()
KITTI_REFLECTANCE_POSE_ARGUMENTS = (
    "--laser-gain-spread 0.2 --pose-loss-weight 0.2 --optimizer adam --lr 1e-4 --lr-step 1 --epochs 1 --batch-size 2 "
    "--crop-width 0 --val-max-pairs 32 --val-width 0 --checkpoint-every 25 --resume --mirror"
).split()
KITTI_REFLECTANCE_DATA = "kitti_reflectance"  # the drives with the calibrated reflectance, under --data
BUNDLED_FINAL = Path(__file__).resolve().parents[1] / "models" / "default" / "training" / "finetune" / "best.pt"
BUNDLED_RANGE_ONLY = BUNDLED_FINAL.parents[1] / "range_only" / "best.pt"


def simulate_drives(data: Path, poses: Path | None, reflectance: str = "simple") -> tuple[list[Path], list[Path]]:
    """`DRIVES` under `data` (written once), as training and held-out folders; with `reflectance="kitti"` the
    same drives with the calibrated reflectance (`simulate_sequence(reflectance=...)`)."""
    from dmlo.simulator import simulate_sequence

    train: list[Path] = []
    val: list[Path] = []
    for name, sequence, seed, start, frames in DRIVES:
        out = data / name
        trajectory = poses / f"{sequence}.txt" if poses is not None and sequence is not None else None
        if trajectory is not None and not trajectory.is_file():
            trajectory = None  # without KITTI's poses the simulator drives a generated route instead
        if not (out / "poses.txt").is_file():
            options = {} if reflectance == "simple" else {"reflectance": reflectance}
            simulate_sequence(out, frames=frames, seed=seed, trajectory=trajectory, start=start if trajectory else 0,
                              **options)  # type: ignore[arg-type]
        (val if name.startswith("val") else train).append(out)
    return train, val


def simulate_kitti_reflectance_drives(data: Path, poses: Path | None) -> tuple[list[Path], list[Path]]:
    """`DRIVES` with the calibrated reflectance under `data/kitti_reflectance` (written once)."""
    return simulate_drives(data / KITTI_REFLECTANCE_DATA, poses, reflectance="kitti")


def simulate_scene_drives(data: Path, poses: Path | None) -> tuple[list[Path], list[Path]]:
    """`SCENE_DRIVES` under `data` (written once), as training and held-out folders."""
    return simulate_listed_drives(data, poses, SCENE_DRIVES)


def simulate_listed_drives(
    data: Path, poses: Path | None, drives: tuple[tuple[str, str | None, int, int, int, dict[str, object]], ...]
) -> tuple[list[Path], list[Path]]:
    """`drives` (name, KITTI trajectory or None, first pose, seed, frames, simulator options) under `data`,
    each written once, as training and held-out (`val…`) folders. Without KITTI's poses the drives that
    follow a KITTI trajectory are left out (a generated route is no highway)."""
    from dmlo.simulator import simulate_sequence

    train: list[Path] = []
    val: list[Path] = []
    for name, sequence, start, seed, frames, options in drives:
        trajectory = poses / f"{sequence}.txt" if poses is not None and sequence is not None else None
        if sequence is not None and (trajectory is None or not trajectory.is_file()):
            continue
        out = data / name
        if not (out / "poses.txt").is_file():
            simulate_sequence(out, frames=frames, seed=seed, trajectory=trajectory, start=start, progress=False,
                              **options)  # type: ignore[arg-type]
        (val if name.startswith("val") else train).append(out)
    return train, val


def recipe_parser(description: str) -> argparse.ArgumentParser:
    """The arguments every recipe takes: where its drives go, where the run goes, which KITTI poses to follow."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="folder for the simulated drives")
    parser.add_argument("--out", type=Path, required=True, help="training run folder")
    parser.add_argument("--poses", type=Path, default=Path(__file__).resolve().parents[4] / "shared/data/kitti_gt_poses",
                        help="KITTI ground-truth pose files to drive along (default: ../shared/data/kitti_gt_poses)")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = recipe_parser(__doc__)
    parser.add_argument("--finetune", action="store_true",
                        help="the second stage: fine-tune OUT/best.pt with the pose loss into OUT/finetune")
    parser.add_argument("--range-only", action="store_true",
                        help="fine-tune the range-only model (reflectance zeroed) from --init into OUT/range_only")
    parser.add_argument("--range-only-pose", action="store_true",
                        help="fine-tune the range-only weights on whole images with the pose loss, reflectance zeroed, "
                        "into OUT/range_only_pose")
    parser.add_argument("--sensor-variety", action="store_true",
                        help="fine-tune --init on pairs with per-laser gains and partly empty rows into OUT/sensor_variety")
    parser.add_argument("--sensor-variety-pose", action="store_true",
                        help="fine-tune --init on whole images with the pose loss and the same row artefacts into "
                        "OUT/sensor_variety_pose")
    parser.add_argument("--scenes", action="store_true",
                        help="fine-tune --init on the recipe's drives and the highway, traffic and stop-and-go scenes "
                        "(SCENE_DRIVES) into OUT/scenes")
    parser.add_argument("--scenes-pose", action="store_true",
                        help="the whole-image pose-loss stage on the --scenes drives, from OUT/scenes/best.pt (or --init), "
                        "into OUT/scenes_pose")
    parser.add_argument("--reflectance-robust", action="store_true",
                        help="fine-tune --init on pairs with a real sensor's reflectance (gains, a monotone calibration "
                        "curve, a fade with range, dark cells, some pairs without it) into OUT/reflectance_robust")
    parser.add_argument("--reflectance-robust-pose", action="store_true",
                        help="the whole-image pose-loss stage with the same reflectance augmentations, from "
                        "OUT/reflectance_robust/best.pt (or --init), into OUT/reflectance_robust_pose")
    parser.add_argument("--kitti-reflectance", action="store_true",
                        help="fine-tune --init on the recipe's drives simulated with a real KITTI HDL-64E's calibrated "
                        "reflectance (DATA/kitti_reflectance) into OUT/kitti_reflectance")
    parser.add_argument("--kitti-reflectance-pose", action="store_true",
                        help="the whole-image pose-loss stage on the same drives, from OUT/kitti_reflectance/best.pt "
                        "(or --init), into OUT/kitti_reflectance_pose")
    parser.add_argument("--device", default=None,
                        help="the training device for the chosen stage (auto: CUDA when available; cpu, cuda, cuda:N)")
    parser.add_argument("--init", type=Path, default=None,
                        help="with --range-only(-pose), --sensor-variety(-pose), --scenes(-pose), "
                        "--reflectance-robust(-pose) or --kitti-reflectance(-pose): the weights to start "
                        "from (default: the bundled model's final ones; with --range-only-pose the bundled range-only "
                        "ones, with --scenes-pose OUT/scenes/best.pt, with --reflectance-robust-pose "
                        "OUT/reflectance_robust/best.pt, with --kitti-reflectance-pose OUT/kitti_reflectance/best.pt)")
    args = parser.parse_args(argv)
    chosen = (args.finetune, args.range_only, args.range_only_pose, args.sensor_variety, args.sensor_variety_pose,
              args.scenes, args.scenes_pose, args.reflectance_robust, args.reflectance_robust_pose,
              args.kitti_reflectance, args.kitti_reflectance_pose)
    if sum(chosen) > 1:
        parser.error("--finetune, --range-only, --range-only-pose, --sensor-variety, --sensor-variety-pose, --scenes, "
                     "--scenes-pose, --reflectance-robust, --reflectance-robust-pose, --kitti-reflectance and "
                     "--kitti-reflectance-pose are separate stages: choose one")
    poses = args.poses if args.poses.is_dir() else None
    if args.kitti_reflectance or args.kitti_reflectance_pose:
        train, val = simulate_kitti_reflectance_drives(args.data, poses)
    else:
        train, val = simulate_drives(args.data, poses)
    if args.scenes or args.scenes_pose:
        scene_train, scene_val = simulate_scene_drives(args.data, poses)
        train, val = train + scene_train, val + scene_val

    from dmlo.train.__main__ import main as train_main

    data = ["--data", *map(str, train), "--val", *map(str, val)]
    stages = {"range_only": RANGE_ONLY_ARGUMENTS, "range_only_pose": RANGE_ONLY_POSE_ARGUMENTS,
              "sensor_variety": SENSOR_VARIETY_ARGUMENTS,
              "sensor_variety_pose": SENSOR_VARIETY_POSE_ARGUMENTS, "scenes": SCENES_ARGUMENTS,
              "scenes_pose": SCENES_POSE_ARGUMENTS, "reflectance_robust": REFLECTANCE_ROBUST_ARGUMENTS,
              "reflectance_robust_pose": REFLECTANCE_ROBUST_POSE_ARGUMENTS,
              "kitti_reflectance": KITTI_REFLECTANCE_ARGUMENTS, "kitti_reflectance_pose": KITTI_REFLECTANCE_POSE_ARGUMENTS}
    device = ["--device", args.device] if args.device else []
    stage = next((name for name in stages if getattr(args, name)), None)
    if stage is not None:
        arguments = stages[stage]
        default_init = {"range_only_pose": BUNDLED_RANGE_ONLY, "scenes_pose": args.out / "scenes" / "best.pt",
                        "reflectance_robust_pose": args.out / "reflectance_robust" / "best.pt",
                        "kitti_reflectance_pose": args.out / "kitti_reflectance" / "best.pt"}
        init = args.init or default_init.get(stage, BUNDLED_FINAL)
        if not init.is_file():
            parser.error(f"--{stage.replace('_', '-')} starts from {init}, which does not exist")
        argv = [*data, "--out", str(args.out / stage), "--init", str(init), *arguments, *device]
        if stage in ("reflectance_robust", "reflectance_robust_pose"):
            return train_main(argv, REFLECTANCE_ROBUST_AUGMENTATION)
        return train_main(argv)
    if args.finetune:
        start = args.out / "best.pt"
        if not start.is_file():
            parser.error(f"--finetune starts from {start}, which does not exist: run the first stage first")
        return train_main([*data, "--out", str(args.out / "finetune"), "--init", str(start), *FINETUNE_ARGUMENTS,
                           *device])
    return train_main([*data, "--out", str(args.out), *TRAIN_ARGUMENTS, *device])


if __name__ == "__main__":
    sys.exit(main())
