"""``dmlo train``: train the matcher on sequences with ground-truth poses (also ``torchrun -m dmlo.train``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import argparse
from pathlib import Path
from typing import Any

from dmlo.cli import DefaultsAndExamplesFormatter

PRESETS = ("paper", "fast", "light")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    data = parser.add_argument_group("data")
    data.add_argument("--data", nargs="+", required=True, metavar="DIR", help="training sequences (KITTI layout, simulator output, ...)")
    data.add_argument("--val", nargs="+", default=[], metavar="DIR", help="held-out sequences for validation after each epoch")
    data.add_argument("--out", required=True, metavar="RUNDIR", help="run folder: checkpoints, model.json, train.json, log.jsonl")
    data.add_argument("--overwrite", action="store_true",
                      help="start afresh in a RUNDIR that holds an earlier run, deleting its files (refused otherwise; "
                      "--resume continues it)")
    data.add_argument("--crop-width", type=int, default=448, help="random azimuth crop in columns, multiple of 8; 0 = full width (default 448)")
    data.add_argument("--crop-height", type=int, default=0, help="random row crop, multiple of 4; 0 = full height")
    data.add_argument("--no-yaw-roll", action="store_true", help="do not roll both scans by a random yaw")
    data.add_argument("--mirror", action="store_true",
                      help="flip half of the pairs left-right (the mirror world): no learned turning preference")
    data.add_argument("--laser-gain-spread", type=float, default=0.0, metavar="S",
                      help="scale each row's reflectance by its own gain in 1 ± s (s drawn up to S), the same in both "
                      "scans, as a real sensor's lasers differ (default 0: off)")
    data.add_argument("--row-dropout", type=float, default=0.0, metavar="P",
                      help="in half of the pairs each row loses up to this share of its cells, as a real sensor's rows "
                      "are partly empty (default 0: off)")
    data.add_argument("--reflectance-dropout", type=float, default=0.0, metavar="P",
                      help="this share of the pairs has its reflectance zeroed in both scans, so that the matcher learns "
                      "to match by range where brightness misleads (default 0: off)")
    data.add_argument("--reflectance-remap", type=float, default=0.0, metavar="P",
                      help="this share of the pairs has its reflectance passed through one random monotone curve in "
                      "both scans, in KITTI's 0.01 steps, as another sensor's calibration (default 0: off)")
    data.add_argument("--reflectance-falloff", type=float, default=0.0, metavar="P",
                      help="this share of the pairs has its reflectance fade with each cell's range (default 0: off)")
    data.add_argument("--reflectance-zeros", type=float, default=0.0, metavar="P",
                      help="up to this share of each scan's cells has its reflectance zeroed, apart in the two scans "
                      "(default 0: off)")
    data.add_argument("--max-gap", type=int, default=2, help="pairs 1..N frames apart (default 2: the paper's triplets)")
    data.add_argument("--val-max-pairs", type=int, default=64, help="held-out pairs validated after each epoch, evenly spaced")
    data.add_argument("--val-width", type=int, default=0, help="centred validation crop; 0 = full width")
    data.add_argument("--workers", type=int, default=0, help="data loader processes")

    model = parser.add_argument_group("model (ignored when resuming: the checkpoint's config wins)")
    model.add_argument("--preset", choices=PRESETS, default="paper", help="paper: 2 plain + 3 deformable 16 ch; fast: 5 plain 8 ch; light: 4 plain + 1 deformable 8 ch")
    model.add_argument("--model-config", metavar="JSON", help="a MatcherConfig JSON file (overrides --preset)")
    model.add_argument("--coarse-window", type=int, help="odd D of the coarse correlation (paper ≈ 10; default 11)")
    model.add_argument("--refine-channels", type=int)
    model.add_argument("--refine-plain", type=int, help="number of plain refine layers")
    model.add_argument("--refine-deformable", type=int, help="number of deformable refine layers")
    model.add_argument("--no-feature-norm", action="store_true", help="ablation: no L2 feature normalisation")
    model.add_argument("--one-hot-loss", action="store_true", help="ablation: one-hot instead of sub-pixel loss")
    model.add_argument("--no-reflectance", action="store_true",
                       help="a range-only model: the reflectance channel zeroed in every sample (for sensors without a "
                       "usable one); applies over --init's config too and is recorded in the exported metadata")

    optim = parser.add_argument_group("optimisation (defaults: the paper's)")
    optim.add_argument("--epochs", type=int, default=60)
    optim.add_argument("--batch-size", type=int, default=4, help="per process")
    optim.add_argument("--optimizer", choices=("sgd", "adam"), default="sgd", help="sgd: the paper's; adam: faster progress in short runs")
    optim.add_argument("--lr", type=float, default=5e-4)
    optim.add_argument("--momentum", type=float, default=0.9)
    optim.add_argument("--weight-decay", type=float, default=1e-5)
    optim.add_argument("--lr-step", type=int, default=20, help="epochs between learning-rate drops")
    optim.add_argument("--lr-gamma", type=float, default=0.1)
    optim.add_argument("--seed", type=int, default=0)
    optim.add_argument("--device", default="auto", help="auto (CUDA when available), cpu, cuda, cuda:N")
    optim.add_argument("--checkpoint-every", type=int, default=50, help="steps between mid-epoch checkpoints")
    optim.add_argument("--max-steps", type=int, default=None, help="stop after this many steps (smoke runs)")
    optim.add_argument("--resume", action="store_true", help="continue from RUNDIR/last.pt when it exists")
    optim.add_argument("--init", metavar="CKPT", help="start a new run from these weights and their model config (fine-tuning)")
    optim.add_argument("--pose-loss-weight", type=float, default=0.0,
                       help="add the pose loss (the motion error the predicted matches imply) with this weight; 0 = off")
    optim.add_argument("--confidence-loss-weight", type=float, default=0.0,
                       help="add the confidence loss (Q* trained as the chance that the match is within 1 px) with this weight; 0 = off")
    optim.add_argument("--no-progress", action="store_true", help="no progress bar")


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "train", help="Train the matching network (DDP: torchrun -m dmlo.train).", description=__doc__,
        formatter_class=DefaultsAndExamplesFormatter,
        epilog="examples:\n"
        "  dmlo train --data sim/00 sim/01 --val sim/09 --out runs/paper --resume\n"
        "  dmlo train --data kitti/sequences/0[0-6] --val kitti/sequences/07 --out runs/kitti --device cuda\n"
        "  torchrun --nproc_per_node 2 -m dmlo.train --data sim/00 sim/01 --out runs/ddp\n",
    )
    add_arguments(parser)
    parser.set_defaults(run=run)


def model_config_from_args(args: argparse.Namespace) -> Any:
    import dataclasses

    from dmlo.model import MatcherConfig

    config = MatcherConfig.load(args.model_config) if args.model_config else MatcherConfig.preset(args.preset)
    changes: dict[str, Any] = {}
    if args.coarse_window is not None:
        changes["coarse_window"] = args.coarse_window
    if args.refine_channels is not None:
        changes["refine_channels"] = args.refine_channels
    if args.refine_plain is not None:
        changes["refine_plain_layers"] = args.refine_plain
    if args.refine_deformable is not None:
        changes["refine_deformable_layers"] = args.refine_deformable
    if args.no_feature_norm:
        changes["normalize_features"] = False
    if args.one_hot_loss:
        changes["subpixel_loss"] = False
    if args.no_reflectance:
        changes["use_reflectance"] = False
    return dataclasses.replace(config, **changes)


def run(args: argparse.Namespace, options: Mapping[str, Any] | None = None) -> int:
    """Trains as `args` say; `options`: `TrainConfig` fields the command line does not take (a recipe's
    augmentations), recorded in `train.json` with the rest."""
    import dataclasses

    from dmlo.cli import UserError

    _check_run_folder(args, prepare=False)
    for path in [*args.data, *args.val]:
        if not Path(path).is_dir():
            raise UserError(f"sequence folder not found: {path}")
    try:
        model_config = model_config_from_args(args)
        from dmlo.train import Augmentation, PairDataset, TrainConfig, Trainer
        from dmlo.train.distributed import init_distributed, resolve_device

        config = TrainConfig(
            data=[str(p) for p in args.data], val=[str(p) for p in args.val], out=str(args.out),
            epochs=args.epochs, batch_size=args.batch_size, optimizer=args.optimizer, lr=args.lr, momentum=args.momentum,
            weight_decay=args.weight_decay, lr_step_epochs=args.lr_step, lr_gamma=args.lr_gamma,
            crop_height=args.crop_height or None, crop_width=args.crop_width or None, yaw_roll=not args.no_yaw_roll,
            mirror=args.mirror, laser_gain_spread=args.laser_gain_spread, row_dropout=args.row_dropout,
            reflectance_dropout=args.reflectance_dropout, reflectance_remap=args.reflectance_remap,
            reflectance_falloff=args.reflectance_falloff, reflectance_zeros=args.reflectance_zeros,
            max_gap=args.max_gap, val_max_pairs=args.val_max_pairs, val_width=args.val_width or None,
            seed=args.seed, workers=args.workers, device=args.device, checkpoint_every=args.checkpoint_every,
            max_steps=args.max_steps, pose_loss_weight=args.pose_loss_weight,
            confidence_loss_weight=args.confidence_loss_weight,
            init=str(args.init) if args.init else None, no_reflectance=args.no_reflectance,
        )
        config = dataclasses.replace(config, **(options or {}))
        if config.init is not None and not Path(config.init).is_file():
            raise UserError(f"--init checkpoint not found: {config.init}")
        pose_jacobian = config.pose_loss_weight > 0
        train_set = PairDataset.from_paths(
            config.data, augmentation=config.augmentation(), max_gap=config.max_gap, seed=config.seed, pose_jacobian=pose_jacobian
        )
        val_set = None
        if config.val:
            val_set = PairDataset.from_paths(
                config.val, augmentation=Augmentation(None, config.val_width, yaw_roll=False, random=False), max_gap=1,
                pose_jacobian=pose_jacobian,
            )
    except (ValueError, FileNotFoundError) as err:
        raise UserError(str(err)) from err
    _check_run_folder(args, prepare=True)
    context = init_distributed(resolve_device(config.device))
    trainer = Trainer(model_config, config, train_set, val_set, context, resume=args.resume, progress=not args.no_progress)
    trainer.run()
    if context.enabled:
        import torch.distributed as dist

        dist.destroy_process_group()
    return 0


# What a training run writes into RUNDIR (and the temporary files of its checkpoints).
TRAIN_FILES = ("last.pt", "best.pt", "log.jsonl", "train.json", "model.json", ".last.pt.tmp-*", ".best.pt.tmp-*")


def _check_run_folder(args: argparse.Namespace, prepare: bool) -> None:
    """A fresh run (no --resume) refuses a RUNDIR with an earlier run's files unless --overwrite: a new
    log.jsonl appended to the old one, or the old best.pt left beside the new last.pt, would mix two runs.
    Only the main process (RANK 0 under torchrun) looks, and with `prepare` clears them."""
    import os

    from dmlo.cli import UserError
    from dmlo.outputs import OutputError, check_output_folder, prepare_output_folder

    if args.resume or os.environ.get("RANK", "0") != "0":
        return
    try:
        earlier = check_output_folder(args.out, TRAIN_FILES, overwrite=args.overwrite)
        if args.init and Path(args.init).resolve() in {path.resolve() for path in earlier}:
            raise UserError(f"--init {args.init} is a file of the earlier run that --overwrite would delete")
        if prepare:
            prepare_output_folder(args.out, TRAIN_FILES, overwrite=args.overwrite)
    except OutputError as err:
        raise UserError(str(err)) from None
