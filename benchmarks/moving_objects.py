"""The moving-object network against labels: point-wise precision and recall, per labelled drive.

    python benchmarks/moving_objects.py [FOLDER ...] [--data DIR] [--model DIR] [--threshold P]

Without folders it runs the labelled real sets under ``DIR/kitti_real`` (SemanticKITTI labels; moving
classes 252–259). Any labelled KITTI-layout folder works, held-out simulated drives included (`dmlo
simulate` writes labels). Besides precision and recall it reports the share of parked (static) cars'
points flagged: the network sees one scan, so a car at rest in a lane looks like one driving, and the
odometry loses little by leaving parked cars out, but the figure says how often it happens.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from dmlo.datasets import moving_mask, open_sequence
from dmlo.metrics.moving import precision_recall
from dmlo.odometry.matcher import default_model_path
from dmlo.odometry.moving import MovingObjectDetector, moving_objects_graph

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
CAR = 10  # SemanticKITTI's (static) car


def evaluate(folder: Path, detector: MovingObjectDetector) -> dict[str, float]:
    sequence = open_sequence(folder)
    flagged, truth, parked = [], [], []
    for index in range(len(sequence)):
        frame = sequence[index]
        if frame.labels is None:
            raise SystemExit(f"{frame.path}: no labels")
        predicted = detector.mask(frame.points)
        flagged.append(predicted)
        truth.append(moving_mask(frame.labels))
        parked.append(predicted[(frame.labels & 0xFFFF) == CAR])
    result = precision_recall(np.concatenate(flagged), np.concatenate(truth))
    parked_points = np.concatenate(parked)
    result["parked_car_points"] = int(parked_points.size)
    result["parked_flagged"] = float(parked_points.mean()) if parked_points.size else float("nan")
    result["scans"] = len(sequence)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="*", type=Path)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--model", type=Path, default=None, help="model folder or moving.onnx (default: bundled)")
    parser.add_argument("--threshold", type=float, default=0.5)
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = parser.parse_args()
    graph = args.model if args.model and args.model.suffix == ".onnx" else moving_objects_graph(
        (args.model or default_model_path()) / "frame.onnx"
    )
    if graph is None:
        raise SystemExit("the model has no moving.onnx")
    detector = MovingObjectDetector(graph, args.threshold)
    folders = args.folders or sorted(p for p in (args.data / "kitti_real").iterdir() if (p / "labels").is_dir())
    results = {}
    print(f"{'drive':<16} {'scans':>5} {'moving pts':>10} {'flagged':>8} {'precision':>9} {'recall':>7} {'parked flagged':>14}")
    for folder in folders:
        r = evaluate(folder, detector)
        results[folder.name] = r
        print(f"{folder.name:<16} {r['scans']:>5} {r['moving']:>10} {r['predicted']:>8} {r['precision']:>9.3f} "
              f"{r['recall']:>7.3f} {r['parked_flagged']:>14.3f}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
