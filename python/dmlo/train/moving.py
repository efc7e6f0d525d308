"""Training of the moving-object network (`dmlo.model.moving`) on simulated drives with moving labels.

    python -m dmlo.train.moving --data runs/moving/train/* --val runs/moving/val/* --out runs/moving/net

Each labelled scan is projected once (the cylinder of the bundled model); a cell's target is whether the
point it keeps is on a moving object (SemanticKITTI classes 252–259). Steps draw random column crops,
rotated about the vertical (a column roll), mirrored, raised or lowered as a whole (sensors sit at other
heights) and tipped a little (cars roll and pitch on real roads; `tilted`). The run checkpoints to `OUT/moving.pt` and resumes from it; at the end it writes
`OUT/moving.onnx` for the odometry (`dmlo.odometry.moving`) and `OUT/train.json` with the held-out
point-wise precision and recall.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

import dmlo_rs
from dmlo.datasets import moving_mask, open_sequence
from dmlo.odometry.moving import range_and_height

if TYPE_CHECKING:
    import torch

GRAPH_NAME = "moving"


@dataclass
class LabelledImages:
    """Projected scans: range and height per cell `[N, H, W]` float32, moving target `[N, H, W]` bool."""

    range: NDArray[np.float32]
    height: NDArray[np.float32]
    moving: NDArray[np.bool_]


def project_labelled(points: NDArray[np.float32], labels: NDArray[np.uint32], cylinder: dmlo_rs.CylinderConfig
                     ) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.bool_]]:
    """A labelled scan's range, height and moving target images (the target of a cell: its kept point's)."""
    ranges, height = range_and_height(points, cylinder)
    index = np.asarray(dmlo_rs.project(points, cylinder).index)
    return ranges, height, (index >= 0) & moving_mask(labels)[np.maximum(index, 0)]


def load_drives(folders: list[Path], cylinder: dmlo_rs.CylinderConfig, stride: int = 1) -> LabelledImages:
    ranges, heights, targets = [], [], []
    for folder in folders:
        sequence = open_sequence(folder)
        for index in range(0, len(sequence), stride):
            frame = sequence[index]
            if frame.labels is None:
                raise ValueError(f"{frame.path}: no labels; the moving-object network trains on labelled drives")
            r, h, m = project_labelled(frame.points, frame.labels, cylinder)
            ranges.append(r)
            heights.append(h)
            targets.append(m)
    return LabelledImages(np.stack(ranges), np.stack(heights), np.stack(targets))


def tilted(range_image: NDArray[np.float32], height: NDArray[np.float32], rng: np.random.Generator, lift: float,
           tilt: float) -> NDArray[np.float32]:
    """The heights `[B, H, W]` of scans raised or lowered by up to `lift` metres and tipped by up to `tilt`
    radians about a random horizontal axis: a sensor mounted at another height, a car rolling or pitching on
    a cambered or sloping road (the simulator's roads are level). Only the heights change, not the cells:
    to first order in the angle, a point at horizontal distance ρ and azimuth φ rises by ρ·(a·cos φ + b·sin φ)."""
    batch, _, width = range_image.shape
    rho = np.sqrt(np.maximum(range_image.astype(np.float64) ** 2 - height.astype(np.float64) ** 2, 0.0))
    azimuth = 2 * np.pi * np.arange(width) / width
    a, b = (rng.uniform(-tilt, tilt, size=(batch, 1, 1)) for _ in range(2))
    rise = rng.uniform(-lift, lift, size=(batch, 1, 1)) + rho * (a * np.cos(azimuth) + b * np.sin(azimuth))
    return (height + rise * (range_image > 0)).astype(np.float32)


def default_cylinder() -> dmlo_rs.CylinderConfig:
    from dmlo.odometry.matcher import OnnxMatcher, default_model_path

    return OnnxMatcher(default_model_path()).cylinder


def train(args: argparse.Namespace) -> dict[str, object]:
    import torch
    from torch.nn import functional as F

    from dmlo.model.moving import MovingObjectNet

    torch.manual_seed(args.seed)
    if args.threads:
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cylinder = default_cylinder()
    data = load_drives([Path(p) for p in args.data], cylinder, stride=args.stride)
    share = float(data.moving.sum() / max((data.range > 0).sum(), 1))
    print(f"{len(data.range)} training scans, {share:.2%} of the filled cells moving", flush=True)

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    net = MovingObjectNet().to(device)
    optimiser = torch.optim.AdamW(net.parameters(), lr=args.lr, weight_decay=1e-4)
    checkpoint = out / "moving.pt"
    step = 0
    if checkpoint.exists():
        state = torch.load(checkpoint, map_location=device)
        net.load_state_dict(state["net"])
        optimiser.load_state_dict(state["optimiser"])
        step = int(state["step"])
        print(f"resumed at step {step}", flush=True)
    schedule = torch.optim.lr_scheduler.OneCycleLR(
        optimiser, max_lr=args.lr, total_steps=args.steps, pct_start=0.1, last_epoch=step - 1 if step else -1
    )
    rng = np.random.default_rng(args.seed + step)
    pos_weight = torch.tensor(args.pos_weight, device=device)
    start, width = time.monotonic(), data.range.shape[2]
    net.train()
    while step < args.steps:
        picks = rng.integers(0, len(data.range), args.batch)
        r, h, m = data.range[picks], data.height[picks], data.moving[picks]
        shift = int(rng.integers(0, width))
        r, h, m = (np.roll(a, shift, axis=2)[:, :, : args.crop] for a in (r, h, m))
        if rng.random() < 0.5:
            r, h, m = (a[:, :, ::-1] for a in (r, h, m))
        h = tilted(r, h, rng, args.height_jitter, np.radians(args.tilt_deg))
        rt = torch.from_numpy(np.ascontiguousarray(r)).to(device)
        ht = torch.from_numpy(np.ascontiguousarray(h)).to(device)
        mt = torch.from_numpy(np.ascontiguousarray(m)).float().to(device)
        valid = (rt > 0).float()
        logits = net(rt, ht)
        loss = (F.binary_cross_entropy_with_logits(logits, mt, pos_weight=pos_weight, reduction="none") * valid).sum()
        loss = loss / valid.sum().clamp(min=1)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
        step += 1
        if step % 50 == 0 or step == args.steps:
            print(f"step {step}/{args.steps} loss {loss.item():.4f} {time.monotonic() - start:.0f} s", flush=True)
            torch.save({"net": net.state_dict(), "optimiser": optimiser.state_dict(), "step": step}, checkpoint)

    net.eval()
    report: dict[str, object] = {"steps": step, "train_scans": len(data.range), "moving_share": share}
    if args.val:
        val = load_drives([Path(p) for p in args.val], cylinder)
        with torch.no_grad():
            probability = np.concatenate([
                torch.sigmoid(net(torch.from_numpy(val.range[k:k + 8]).to(device),
                                  torch.from_numpy(val.height[k:k + 8]).to(device))).cpu().numpy()
                for k in range(0, len(val.range), 8)
            ])
        report["val_cells"] = cell_precision_recall(probability > 0.5, val.moving, val.range > 0)
        print(f"held-out cells: {report['val_cells']}", flush=True)
    export_onnx(net.cpu(), cylinder, out / "moving.onnx")
    (out / "train.json").write_text(json.dumps({**report, "args": vars(args)}, indent=2) + "\n")
    return report


def cell_precision_recall(predicted: NDArray[np.bool_], moving: NDArray[np.bool_], valid: NDArray[np.bool_]
                          ) -> dict[str, float]:
    from dmlo.metrics.moving import precision_recall

    return precision_recall(predicted[valid], moving[valid])


def export_onnx(net: "torch.nn.Module", cylinder: dmlo_rs.CylinderConfig, path: Path) -> None:
    """The network as `moving.onnx`: `range`, `height` float32 [1, H, W] → `moving_probability` [1, H, W]."""
    import onnx
    import torch

    from dmlo.export import cylinder_config_dict

    class WithSigmoid(torch.nn.Module):
        def __init__(self, inner: torch.nn.Module) -> None:
            super().__init__()
            self.inner = inner

        def forward(self, range_image: torch.Tensor, height_image: torch.Tensor) -> torch.Tensor:
            return torch.sigmoid(self.inner(range_image, height_image))

    shape = (1, cylinder.height, cylinder.width)
    torch.onnx.export(
        WithSigmoid(net).eval(), (torch.zeros(shape), torch.zeros(shape)), str(path),
        input_names=["range", "height"], output_names=["moving_probability"], opset_version=19, dynamo=False,
    )
    model = onnx.load(str(path))
    for key, value in {
        "dmlo.graph": GRAPH_NAME,
        "dmlo.height": str(cylinder.height),
        "dmlo.width": str(cylinder.width),
        "dmlo.cylinder_config": json.dumps(cylinder_config_dict(cylinder)),
    }.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save(model, str(path))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dmlo.train.moving", description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs="+", required=True, help="labelled KITTI-layout drives to train on")
    parser.add_argument("--val", nargs="*", default=[], help="held-out labelled drives for precision/recall")
    parser.add_argument("--out", required=True, help="run folder (checkpoint, moving.onnx, train.json)")
    parser.add_argument("--steps", type=int, default=5000)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--crop", type=int, default=512, help="columns of a training crop")
    parser.add_argument("--lr", type=float, default=3e-3)
    parser.add_argument("--pos-weight", type=float, default=3.0, help="weight of a moving cell in the loss")
    parser.add_argument("--height-jitter", type=float, default=0.3, help="metres the scan is raised or lowered")
    parser.add_argument("--tilt-deg", type=float, default=0.0, help="degrees the scan is tipped about a horizontal axis")
    parser.add_argument("--stride", type=int, default=1, help="every STRIDE-th scan of each drive")
    parser.add_argument("--threads", type=int, default=0)
    parser.add_argument("--seed", type=int, default=0)
    train(parser.parse_args(argv))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
