"""Frame-to-frame DMLO (mapping off) per model, pair by pair: the real sets against `benchmarks/real.py`'s
reference and two simulated street drives against the simulator's truth, in one run.

    python benchmarks/model_pairs.py --model NAME=MODEL_DIR_OR_FRAME_ONNX [...] [--sets DIR ...]
        [--sim SEED:KITTI_SEQUENCE ...] [--frames 150] [--out runs/model_pairs]

The figures of issue 52's table (docs/measurements.md, sessions 39 and 40): translation mean / max (cm),
rotation mean (°) and the mean signed pitch error (°, positive tips the nose down) of each pose delta, from
`real.py`'s `pair_errors`. The real sets' reference is real.py's (the multi-scan GICP consensus, span 3),
computed once per set and cached in `OUT/reference_<set>.npz`, so several models (or later runs) compare
against the same one; the peers are not run. The simulated drives are `benchmarks/odometry.py`'s street
drives (`simulate_sequence(frames, seed, trajectory=KITTI poses)`, lanes traffic, no motion distortion),
written once into `OUT/drive_seed<SEED>`, compared with their ground truth. `NAME=` with no path runs the
bundled model; `NAME=PATH,reflectance=none` runs the odometry with `reflectance: "none"` (the range-only
model beside the model, with the model's moving-object network, as session 39's range-only column).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any, cast

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real import DEFAULT_DATA, pair_errors  # noqa: E402

from dmlo.datasets import open_sequence  # noqa: E402
from dmlo.peers.consensus import ConsensusReference  # noqa: E402
from dmlo.odometry import Odometry, OdometryConfig  # noqa: E402


def make_odometry(model: Path | None, reflectance: str = "auto") -> Odometry:
    config = OdometryConfig()
    config.mapping.enabled = False
    config.reflectance = cast(Any, reflectance)  # checked by the odometry's config
    return Odometry(model, config) if model is not None else Odometry.from_default(config)


def motions_reference(motions: np.ndarray, sources: tuple[str, ...]) -> ConsensusReference:
    """A reference of these pair motions alone (what `pair_errors` reads)."""
    zeros = np.zeros(len(motions))
    return ConsensusReference(motions=motions, disagreement_m=zeros, disagreement_deg=zeros, sources=sources)


def real_reference(folder: Path, scans: list[np.ndarray], ground_truth: np.ndarray | None, cache: Path) -> ConsensusReference:
    if cache.is_file():
        data = np.load(cache)
        return motions_reference(data["motions"], tuple(str(s) for s in data["sources"]))
    from dmlo.peers.consensus import gicp_consensus

    reference = gicp_consensus(scans, ground_truth, span=3)
    np.savez(cache, motions=reference.motions, sources=np.array(reference.sources))
    return motions_reference(reference.motions, reference.sources)


def run_model(model: Path | None, scans: list[np.ndarray], reflectance: str = "auto") -> tuple[np.ndarray, float]:
    odometry = make_odometry(model, reflectance)
    start = time.perf_counter()
    poses = np.stack([odometry.register(points) for points in scans])
    return poses, len(scans) / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", action="append", required=True, metavar="NAME=PATH",
                        help="a model folder or its frame.onnx, NAME= (no path) for the bundled model; a suffix "
                        "',reflectance=none' sets the odometry's reflectance setting (none: the range-only model beside)")
    parser.add_argument("--sets", nargs="*", type=Path, default=None,
                        help="real scan folders (default: every set in ../shared/data/kitti_real)")
    parser.add_argument("--sim", nargs="*", default=["1:07", "3:05"], metavar="SEED:SEQ",
                        help="simulated street drives, seed and the KITTI trajectory they follow (default 1:07 3:05)")
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--poses", type=Path, default=DEFAULT_DATA / "kitti_gt_poses")
    parser.add_argument("--out", type=Path, default=Path("runs/model_pairs"))
    args = parser.parse_args()

    models: list[tuple[str, Path | None, str]] = []
    for item in args.model:
        name, _, spec = item.partition("=")
        path, _, option = spec.partition(",")
        reflectance = option.partition("reflectance=")[2] or "auto"
        model = Path(path) if path else None
        if model is not None and model.is_dir():
            model = model / "frame.onnx"
        models.append((name, model, reflectance))
    sets = args.sets if args.sets is not None else sorted(p for p in (DEFAULT_DATA / "kitti_real").iterdir() if p.is_dir())
    args.out.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict[str, dict[str, float]]] = {}

    def report(label: str, name: str, poses: np.ndarray, reference: ConsensusReference, hz: float) -> None:
        row = pair_errors(name, poses, reference, hz)
        results.setdefault(label, {})[name] = {
            "t_mean_cm": row.translation_mean_cm, "t_max_cm": row.translation_max_cm,
            "r_mean_deg": row.rotation_mean_deg, "pitch_deg": row.pitch_bias_deg, "hz": hz,
        }
        print(f"| {label} | {name} | {row.translation_mean_cm:.2f} / {row.translation_max_cm:.2f}, "
              f"{row.rotation_mean_deg:.3f}, {row.pitch_bias_deg:+.3f} | {hz:.1f} Hz |", flush=True)
        (args.out / "model_pairs.json").write_text(json.dumps(results, indent=1) + "\n")

    print("| set | model | t mean / max cm, r mean °, pitch ° | speed |\n|---|---|---|---|")
    for folder in sets:
        sequence = open_sequence(folder)
        scans = [sequence[i].points for i in range(len(sequence))]
        reference = real_reference(folder, scans, sequence.poses, args.out / f"reference_{folder.name}.npz")
        for name, model, reflectance in models:
            poses, hz = run_model(model, scans, reflectance)
            report(folder.name, name, poses, reference, hz)

    from dmlo.simulator import simulate_sequence

    for item in args.sim:
        seed_text, _, trajectory_name = item.partition(":")
        seed = int(seed_text)
        drive = args.out / f"drive_seed{seed}"
        trajectory = args.poses / f"{trajectory_name}.txt"
        if not (drive / "poses.txt").is_file():
            simulate_sequence(drive, frames=args.frames, seed=seed, trajectory=trajectory if trajectory.is_file() else None,
                              progress=False)
        sequence = open_sequence(drive)
        total = min(args.frames, len(sequence))
        scans = [sequence[i].points for i in range(total)]
        assert sequence.poses is not None, f"{drive}: a simulated drive has its poses"
        truth = sequence.poses[:total]
        reference = motions_reference(np.linalg.inv(truth[:-1]) @ truth[1:], ("truth",))
        for name, model, reflectance in models:
            poses, hz = run_model(model, scans, reflectance)
            report(f"sim seed {seed} along {trajectory_name}", name, poses, reference, hz)


if __name__ == "__main__":
    main()
