"""``dmlo export``: write the matcher as ONNX graphs for onnxruntime (frame.onnx, encoder.onnx, match.onnx)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from dmlo.cli import DefaultsAndExamplesFormatter


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "export", help="Export a trained matcher to ONNX for onnxruntime.", description=__doc__,
        formatter_class=DefaultsAndExamplesFormatter,
        epilog="examples:\n"
        "  dmlo export runs/paper --out my_model/ --wide-window 41 --refine-window 7\n"
        "  dmlo run kitti/sequences/07 --model my_model/\n",
    )
    parser.add_argument("checkpoint", help="a checkpoint (.pt) or a run folder (uses best.pt, else last.pt)")
    parser.add_argument("--out", required=True, metavar="DIR", help="folder for the .onnx files")
    parser.add_argument("--height", type=int, default=None, help="input rows (default: the cylinder config's)")
    parser.add_argument("--width", type=int, default=None, help="input columns (default: the cylinder config's)")
    parser.add_argument("--graphs", nargs="+", default=["frame", "encoder", "match"], choices=["frame", "encoder", "match"])
    parser.add_argument(
        "--wide-window", type=int, default=0, metavar="D",
        help="also write frame_wide.onnx: the same weights with an odd coarse window D for large motion "
        "(the paper uses D = 40 at inference; 41 here); 0 = none",
    )
    parser.add_argument(
        "--refine-window", type=int, default=0, metavar="D",
        help="an odd refine window D for every graph, wider than the one trained (beyond the paper: the "
        "bundled model's 5 widened to 7 at inference); 0 = the checkpoint's",
    )
    parser.add_argument(
        "--refine-offset", choices=("window", "peak_centroid"), default=None,
        help="sub-pixel decoding of the refine window: window = the paper's best 2×2 window (Eq. 11), "
        "peak_centroid = the 3×3 cells around the most likely one (default: the checkpoint's)",
    )
    parser.set_defaults(run=run)


def default_cylinder() -> tuple[Any, int, int]:
    """KITTI's cylinder config from `dmlo_rs` when built with it, and its network input size."""
    try:
        import dmlo_rs

        config = dmlo_rs.CylinderConfig.kitti()
    except (ImportError, AttributeError):
        return {"preset": "kitti", "height": 64, "width": 1792}, 64, 1792
    height = int(getattr(config, "height", 64))
    width = int(getattr(config, "width", 1792))
    return config, height, width


def resolve_checkpoint(path: Path) -> Path:
    if path.is_dir():
        for name in ("best.pt", "last.pt"):
            if (path / name).is_file():
                return path / name
        raise FileNotFoundError(f"no best.pt or last.pt in {path}")
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    return path


def with_changes(model: Any, **changes: Any) -> Any:
    """The same trained weights in a matcher whose config differs by `changes` (no fine-tuning)."""
    import dataclasses

    from dmlo.model import Matcher

    changed = Matcher(dataclasses.replace(model.config, **changes))
    changed.load_state_dict(model.state_dict())
    return changed


def export_wide_frame(model: Any, out: Path, window: int, size: tuple[int, int], cylinder: Any) -> Path:
    """`frame_wide.onnx`: the trained weights with a wider coarse window (§IV-D, no fine-tuning)."""
    import tempfile

    from dmlo.export import export_onnx

    wide = with_changes(model, coarse_window=window)
    with tempfile.TemporaryDirectory(dir=out) as scratch:
        exported = export_onnx(wide, scratch, *size, cylinder, ("frame",))["frame"]
        return exported.replace(out / "frame_wide.onnx")


def run(args: argparse.Namespace) -> int:
    from dmlo.cli import UserError

    try:
        from dmlo.export import export_onnx
        from dmlo.train.trainer import load_model

        checkpoint = resolve_checkpoint(Path(args.checkpoint))
        cylinder, height, width = default_cylinder()
        model = load_model(checkpoint)
        changes = {"refine_offset": args.refine_offset, "refine_window": args.refine_window or None}
        changes = {name: value for name, value in changes.items() if value is not None}
        if changes:
            model = with_changes(model, **changes)
        size = (args.height or height, args.width or width)
        paths = export_onnx(model, args.out, *size, cylinder, tuple(args.graphs))
        if args.wide_window:
            paths["frame_wide"] = export_wide_frame(model, Path(args.out), args.wide_window, size, cylinder)
    except (ValueError, FileNotFoundError, KeyError) as err:
        raise UserError(str(err)) from err
    for name, path in paths.items():
        print(f"{name}: {path}")
    for stale in remove_stale_graphs(Path(args.out), set(paths.values())):
        print(f"removed {stale} (an earlier export's: the odometry would have run it beside these)")
    return 0


MODEL_GRAPHS = ("frame.onnx", "frame_wide.onnx", "encoder.onnx", "match.onnx")


def remove_stale_graphs(out: Path, written: set[Path]) -> list[Path]:
    """The graphs of an earlier export in `out` that this one did not write, removed: the odometry opens every
    graph it finds beside `frame.onnx`, so a stale one would silently run another checkpoint's weights.
    Other files and folders (a range-only model, training state) stay."""
    removed = []
    for name in MODEL_GRAPHS:
        path = out / name
        if path.is_file() and path not in written:
            path.unlink()
            removed.append(path)
    return removed
