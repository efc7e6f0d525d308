"""``dmlo export``: write the matcher as ONNX graphs for onnxruntime (frame.onnx, encoder.onnx, match.onnx)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "export", help="export a trained matcher to ONNX", description=__doc__,
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("checkpoint", help="a checkpoint (.pt) or a run folder (uses best.pt, else last.pt)")
    parser.add_argument("--out", required=True, metavar="DIR", help="folder for the .onnx files")
    parser.add_argument("--height", type=int, default=None, help="input rows (default: the cylinder config's)")
    parser.add_argument("--width", type=int, default=None, help="input columns (default: the cylinder config's)")
    parser.add_argument("--graphs", nargs="+", default=["frame", "encoder", "match"], choices=["frame", "encoder", "match"])
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


def run(args: argparse.Namespace) -> int:
    from dmlo.cli import UserError

    try:
        from dmlo.export import export_onnx
        from dmlo.train.trainer import load_model

        checkpoint = resolve_checkpoint(Path(args.checkpoint))
        cylinder, height, width = default_cylinder()
        model = load_model(checkpoint)
        paths = export_onnx(model, args.out, args.height or height, args.width or width, cylinder, tuple(args.graphs))
    except (ValueError, FileNotFoundError, KeyError) as err:
        raise UserError(str(err)) from err
    for name, path in paths.items():
        print(f"{name}: {path}")
    return 0
