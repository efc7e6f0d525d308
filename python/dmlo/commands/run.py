"""`dmlo run`: DMLO odometry over a dataset folder."""

from __future__ import annotations

import argparse
from pathlib import Path

from dmlo.cli import UserError, positive_int

EXAMPLES = """examples:
  dmlo run /data/kitti --sequence 07 --out runs/kitti07
  dmlo run sim_drive/ --no-mapping --out runs/sim_frame_to_frame
  dmlo run raw_drive/ --format folder --deskew --out runs/raw
  dmlo run my_scans/ --format folder --model my_model.onnx
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "run",
        help="run DMLO odometry over a sequence of scans",
        description="Run DMLO odometry over a sequence; write poses (KITTI and TUM), per-frame "
        "diagnostics, the config used, and metrics + a plot when ground truth exists. Unreadable scan files, "
        "and scans missing from the timestamps (times.txt, KITTI raw timestamps.txt, Argoverse), are bridged: "
        "the next scan is matched again from the motion model's prediction.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("path", type=Path, help="dataset folder (KITTI, Argoverse 1/2, or plain scans)")
    add_odometry_arguments(parser)
    add_dataset_arguments(parser)
    parser.add_argument("--out", type=Path, default=Path("runs/dmlo"), help="output folder (default: runs/dmlo)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the files of an earlier run in --out (refused otherwise)")
    parser.set_defaults(run=run)


# The keys of `dmlo.datasets.FORMATS` (a test keeps them equal), spelled out so that building the parser
# does not import the readers and numpy.
DATASET_FORMATS = ("kitti", "argoverse", "argoverse2", "folder")


def add_dataset_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--format", choices=DATASET_FORMATS, default=None,
                        help="dataset layout (default: detected from the folder)")
    parser.add_argument("--sequence", default=None, help="sequence or log name inside the dataset, e.g. 07")
    parser.add_argument("--max-frames", type=positive_int, default=None, help="stop after this many scans")


def add_odometry_arguments(parser: argparse.ArgumentParser, sequence: bool = True) -> None:
    """The odometry's flags; `sequence=False` (a pair of scans: no motion model) leaves out those that
    need one."""
    parser.add_argument("--model", type=Path, default=None, help="ONNX model (default: the bundled model)")
    parser.add_argument("--config", type=Path, default=None, help="odometry config JSON (see config.json of a run)")
    parser.add_argument("--mapping", action=argparse.BooleanOptionalAction, default=None,
                        help="refine every pose by NDT against a local map of recent scans (register: against "
                        "scan A): DMLO + mapping, the "
                        "paper's full system (default; config mapping.enabled); --no-mapping: the paper's "
                        "frame-to-frame DMLO (bench: its row alone)")
    parser.add_argument("--symmetric", action="store_true",
                        help="also match every scan back against the previous one and take the midpoint "
                        "motion: less drift, one more matching pass per frame")
    if sequence:
        parser.add_argument("--deskew", action="store_true",
                            help="motion-compensate every sweep by the constant-velocity prediction before "
                            "matching (for skewed sweeps: raw KITTI, live spinning sensors; times from the azimuth, "
                            "a clockwise sensor with poses at the forward-looking moment; config deskew.* for others); skewed "
                            "sweeps not deskewed drift most with the default ray-noise refit")
    parser.add_argument("--matching-stage", choices=("auto", "crate", "graph"), default=None,
                        help="where the network's correlation and window decoding run: in the Rust crate "
                        "(fast on a CPU), in the ONNX graph (e.g. on a GPU), or auto (default; config matching_stage)")
    parser.add_argument("--reflectance", choices=("auto", "unit", "0-255", "0-65535", "none"), default=None,
                        help="the scans' reflectance scale: auto (default; config reflectance) reads it from the first "
                        "scan; none (or no usable reflectance) runs the range-only model beside the model")
    parser.add_argument("--keep-moving", action="store_true",
                        help="keep the points on moving objects; by default they are left out of matching and "
                        "of the map: labelled ones where the dataset has labels, else those the moving-object "
                        "network beside the model finds (config moving_objects.detect)")
    parser.add_argument("--no-coherence", action="store_true",
                        help="rank the matches by the network's confidence alone, as the paper does, instead of "
                        "also by how well each agrees with its neighbours' flow")


def build_odometry(args: argparse.Namespace, mapping: bool | None = None):  # type: ignore[no-untyped-def]
    """The odometry the arguments ask for; `mapping` overrides `--mapping` / `--no-mapping`, which override
    the config's `mapping.enabled`."""
    from dmlo.odometry import Odometry, OdometryConfig
    from dmlo.odometry.matcher import default_model_path

    try:
        config = OdometryConfig.load(args.config) if args.config else OdometryConfig()
    except (OSError, ValueError) as err:
        raise UserError(f"cannot read config {args.config}: {err}") from err
    mapping = args.mapping if mapping is None else mapping
    if mapping is not None:
        config.mapping.enabled = mapping
    if args.symmetric:
        config.matching.symmetric = True
    if args.no_coherence:
        config.matching.coherence_px = None
    if args.matching_stage:
        config.matching_stage = args.matching_stage
    if getattr(args, "reflectance", None):
        config.reflectance = args.reflectance
    if getattr(args, "deskew", False):
        config.deskew.enabled = True
    if args.keep_moving:
        config.moving_objects.detect = False
    if getattr(args, "loop", False):  # `dmlo register --loop`: yaw starts all round
        config.large_motion.search_yaw_deg = tuple(float(yaw) for yaw in range(0, 360, 30))
    model = args.model or default_model_path()
    try:
        return Odometry(model, config)
    except ValueError as err:  # a ModelError, or a setting of the config file out of its range
        raise UserError(str(err)) from err


def run(args: argparse.Namespace) -> int:
    from dmlo.datasets import DatasetError, open_sequence
    from dmlo.run import run_sequence
    from dmlo.outputs import BENCH_FILES, RUN_FILES, OutputError, check_output_folder

    if not args.path.exists():
        raise UserError(f"no such dataset folder: {args.path}")
    try:
        sequence = open_sequence(args.path, format=args.format, sequence=args.sequence)
    except DatasetError as err:
        raise UserError(str(err)) from err
    try:
        check_output_folder(args.out, RUN_FILES, overwrite=args.overwrite, also_refuse=BENCH_FILES)
    except OutputError as err:  # before the model loads: a refusal is instant
        raise UserError(str(err)) from None
    odometry = build_odometry(args)
    try:
        summary = run_sequence(sequence, odometry, args.out, remove_moving=not args.keep_moving,
                               max_frames=args.max_frames, overwrite=args.overwrite)
    except OutputError as err:
        raise UserError(str(err)) from None
    print(format_summary(summary))
    return 0


def format_summary(summary) -> str:  # type: ignore[no-untyped-def]
    fallbacks = ", ".join(f"{count} {reason.replace('_', ' ')}" for reason, count in summary.fallbacks.items())
    lines = [
        f"{summary.frames} scans in {summary.seconds:.1f} s ({summary.hz:.1f} Hz); "
        f"motion model used for: {fallbacks or 'none'}",
        f"results in {summary.out_dir}/",
    ]
    if summary.ambiguous_starts:
        taken = ("the start driving forward was taken over the pair's reversing motion "
                 "(motion_model.start_max_reverse_m); " if summary.fallbacks.get("forward_start") else "")
        lines.insert(1, "warning: the first motion is ambiguous (another start explained the scans as well: a drive "
                        f"that began at speed past a repeating scene?); {taken}the trajectory may be off from its "
                        "start on (diagnostics.jsonl: ambiguous_start)")
    if summary.moving_share is not None:
        lines.insert(1, f"moving objects: the network left out {100 * summary.moving_share:.1f} % of a scan's points "
                        "on average (--keep-moving keeps them)")
    if summary.metrics:
        m = summary.metrics
        parts = []
        for key, label, unit in (("t_rel", "t_rel", "%"), ("r_rel", "r_rel", "°/100m"),
                                 ("ate_rmse", "ATE", "m"), ("rpe_t_mean", "RPE t", "m"),
                                 ("rpe_r_mean", "RPE r", "°")):
            if m.get(key) is not None:
                parts.append(f"{label} {m[key]:.4g} {unit}")
        lines.append("vs ground truth: " + ", ".join(parts))
    return "\n".join(lines)
