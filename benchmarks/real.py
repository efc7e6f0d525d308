"""Real scans: DMLO, DMLO + mapping and the peers, pair by pair against a GICP consensus, in one run.

    python benchmarks/real.py [FOLDER ...] [--data DIR] [--span 3] [--out runs/bench_real]

Without folders it runs every set under ``DIR/kitti_real`` (``../shared/data`` by default). A folder is
anything ``dmlo run`` reads, a plain folder of ``.bin`` scans included, so it runs on anyone's own drive;
ground-truth poses, when the folder has them, only seed the reference. The reference is the consensus of
two independent GICPs (small_gicp and Open3D, `dmlo.peers.consensus`) over every pair of scans up to
``--span`` apart, the poses that fit all those alignments best (``--span 1``: each consecutive pair's
scan-to-scan consensus alone, whose figures the table adds beside the multi-scan ones otherwise); each
method's pose deltas are compared with it: mean and largest translation and rotation error a pair, the mean
signed pitch error (about the sensor's y axis, which points left: positive tips the nose down), the frames
DMLO left to its motion model, speed, and ratios to KISS-ICP measured in the same run.

``OUT/real.json`` is written again as each set ends, so an interrupted run keeps the sets it finished; a set
that cannot be read (a truncated scan, fewer than two) is named on stderr and the others are measured, and the
run then exits with status 1.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import numpy.typing as npt
from tqdm import tqdm

from dmlo.peers.consensus import ConsensusReference, available_gicps, gicp_consensus, missing_gicps
from dmlo.peers.peers import PEERS, FrameOdometry
from dmlo.peers.runner import REFERENCE_PEER
from dmlo.datasets import DatasetError, open_sequence
from dmlo.metrics import rotation_error_axes_deg
from dmlo.odometry import Odometry, OdometryConfig
from dmlo.outputs import atomic_output

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
DEFAULT_PEERS = ("KISS-ICP", "small_gicp GICP")


@dataclass
class PairErrors:
    """One method's errors on one set, against the consensus; lengths in cm, angles in degrees."""

    method: str
    hz: float
    translation_mean_cm: float
    translation_max_cm: float
    rotation_mean_deg: float
    rotation_max_deg: float
    pitch_bias_deg: float  # mean signed error about the sensor's y axis (left): positive tips the nose down
    uncertain_frames: int | None = None  # DMLO: frames whose motion the odometry did not trust (diagnostics)
    # Against the consecutive pairs' scan-to-scan consensus, when the reference is the multi-scan one.
    consecutive_translation_mean_cm: float | None = None
    consecutive_translation_max_cm: float | None = None


def pair_errors(
    method: str, poses: npt.NDArray[np.float64], reference: ConsensusReference, hz: float
) -> PairErrors:
    """The errors of the pose deltas `inv(P_i) P_{i+1}` of `poses` against the reference motions."""
    deltas = np.linalg.inv(poses[:-1]) @ poses[1:]

    def translation_cm(motions: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        return np.linalg.norm((np.linalg.inv(motions) @ deltas)[:, :3, 3], axis=1) * 100

    translation = translation_cm(reference.motions)
    consecutive = None if reference.consecutive_motions is None else translation_cm(reference.consecutive_motions)
    axes = rotation_error_axes_deg(deltas[:, :3, :3], reference.motions[:, :3, :3])
    rotation = np.linalg.norm(axes, axis=1)
    return PairErrors(
        method=method,
        hz=hz,
        translation_mean_cm=float(translation.mean()),
        translation_max_cm=float(translation.max()),
        rotation_mean_deg=float(rotation.mean()),
        rotation_max_deg=float(rotation.max()),
        pitch_bias_deg=float(axes[:, 1].mean()),
        consecutive_translation_mean_cm=None if consecutive is None else float(consecutive.mean()),
        consecutive_translation_max_cm=None if consecutive is None else float(consecutive.max()),
    )


def _dmlo(model: Path | None, mapping: bool) -> Callable[[], Odometry]:
    def make() -> Odometry:
        config = OdometryConfig()
        config.mapping.enabled = mapping
        return Odometry(model, config) if model else Odometry.from_default(config)

    return make


def run_set(
    folder: Path, model: Path | None, peers: list[str], max_frames: int | None, span: int = 3
) -> tuple[ConsensusReference, list[PairErrors]]:
    sequence = open_sequence(folder)
    total = len(sequence) if max_frames is None else min(max_frames, len(sequence))
    if total < 2:
        raise DatasetError(f"{len(sequence)} scan(s); a pair needs at least 2")
    frames = [sequence[i] for i in range(total)]
    scans = [frame.points for frame in frames]
    ground_truth = sequence.poses[:total] if sequence.poses is not None else None
    reference = gicp_consensus(scans, ground_truth, span=span)

    methods: list[tuple[str, Callable[[], FrameOdometry]]] = [
        ("DMLO", _dmlo(model, mapping=False)),
        ("DMLO + mapping", _dmlo(model, mapping=True)),
    ]
    methods += [(peer.name, peer.make) for peer in PEERS if peer.name in peers and peer.available]
    rows = []
    for name, make in methods:
        odometry = make()
        start = time.perf_counter()
        poses = np.stack([odometry.register(points) for points in tqdm(scans, desc=f"{folder.name}: {name}", leave=False)])
        row = pair_errors(name, poses, reference, total / (time.perf_counter() - start))
        if isinstance(odometry, Odometry):
            row.uncertain_frames = sum(d.fallback is not None or d.ambiguous_start is True for d in odometry.diagnostics)
        rows.append(row)
    return reference, rows


def format_table(rows: list[PairErrors]) -> str:
    kiss = next((row for row in rows if row.method == REFERENCE_PEER), None)
    lines = [
        "| method | t mean cm | t max cm | r mean ° | r max ° | pitch bias ° | t mean / max cm, consecutive pairs' "
        "reference | uncertain frames | Hz | t ×KISS | speed ×KISS |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        ratio = speed = "—"
        if kiss is not None:
            ratio = f"{row.translation_mean_cm / kiss.translation_mean_cm:.2f}"
            speed = f"{row.hz / kiss.hz:.2f}"
        fallback = "—" if row.uncertain_frames is None else str(row.uncertain_frames)
        consecutive = "—"
        if row.consecutive_translation_mean_cm is not None and row.consecutive_translation_max_cm is not None:
            consecutive = f"{row.consecutive_translation_mean_cm:.2f} / {row.consecutive_translation_max_cm:.2f}"
        lines.append(
            f"| {row.method} | {row.translation_mean_cm:.2f} | {row.translation_max_cm:.2f} | {row.rotation_mean_deg:.3f} "
            f"| {row.rotation_max_deg:.3f} | {row.pitch_bias_deg:+.3f} | {consecutive} | {fallback} | {row.hz:.1f} "
            f"| {ratio} | {speed} |"
        )
    return "\n".join(lines)


def describe(reference: ConsensusReference) -> str:
    """What the reference is and how far it can be trusted, in a line."""
    pairs = (
        f"the consecutive pairs' GICPs disagree by {100 * reference.disagreement_m.mean():.2f} cm / "
        f"{reference.disagreement_deg.mean():.3f}° on average, {100 * reference.disagreement_m.max():.2f} cm at most"
    )
    if reference.span == 1:
        return f"{' + '.join(reference.sources)} on consecutive pairs; {pairs}"
    return (
        f"{' + '.join(reference.sources)} on every pair up to {reference.span} scans apart, solved jointly; its "
        f"{len(reference.residual_m)} alignments lie {100 * reference.residual_m.mean():.2f} cm from its poses on "
        f"average; {pairs}"
    )


def write_report(path: Path, stamp: str, results: Mapping[str, object]) -> None:
    with atomic_output(path) as temporary:
        temporary.write_text(json.dumps({"date": stamp, "sets": results}, indent=1) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="*", type=Path, help="scan folders (default: every set in DATA/kitti_real)")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder (default: ../shared/data)")
    parser.add_argument("--model", type=Path, default=None, help="a model's frame.onnx (default: the bundled model)")
    parser.add_argument("--peers", nargs="*", default=list(DEFAULT_PEERS))
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument(
        "--span", type=int, default=3,
        help="the reference aligns every pair of scans up to this many apart (default 3; 1: consecutive pairs only)",
    )
    parser.add_argument("--out", type=Path, default=Path("runs/bench_real"))
    args = parser.parse_args()
    if args.max_frames is not None and args.max_frames < 2:
        parser.error("--max-frames: a pair needs at least 2 frames")
    if args.span < 1:
        parser.error(f"--span: at least 1 (consecutive pairs), got {args.span}")
    unknown = set(args.peers) - {peer.name for peer in PEERS}
    if unknown:
        parser.error(f"unknown peer(s): {', '.join(sorted(unknown))}; known: {', '.join(p.name for p in PEERS)}")
    folders = args.folders or sorted(p for p in (args.data / "kitti_real").iterdir() if p.is_dir())
    if not folders:
        parser.error(f"no scan folders given and none in {args.data / 'kitti_real'}")

    for peer in PEERS:  # a peer asked for but not installed would otherwise be missing from the tables unsaid
        if peer.name in args.peers and not peer.available:
            print(f"warning: {peer.name} left out: {peer.unavailable_reason}", file=sys.stderr)
    gicps = available_gicps()
    if len(gicps) == 1:
        why = "; ".join(missing_gicps().values())
        print(
            f"warning: the reference is {gicps[0]} alone, not the consensus of two independent GICPs ({why}): "
            "its own row compares it with itself",
            file=sys.stderr,
        )

    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d")
    print(f"{stamp}, {platform.processor() or platform.machine()}, {len(folders)} set(s)")
    results = {}
    args.out.mkdir(parents=True, exist_ok=True)
    failed = []
    for folder in folders:
        try:
            reference, rows = run_set(folder, args.model, args.peers, args.max_frames, args.span)
        except DatasetError as err:  # one unreadable set: say which and why, and measure the others
            print(f"error: {folder}: {err}", file=sys.stderr)
            failed.append(folder)
            continue
        print(f"\n### {folder.name} ({len(reference.motions) + 1} scans; reference: {describe(reference)})\n")
        print(format_table(rows))
        results[str(folder)] = {
            "reference": {"sources": reference.sources, "disagreement_m": reference.disagreement_m.tolist(),
                          "motions": reference.motions.tolist(), "span": reference.span,
                          "residual_m": reference.residual_m.tolist()},
            "rows": [asdict(row) for row in rows],
        }
        write_report(args.out / "real.json", stamp, results)  # after every set: an interrupted run keeps those done
    if failed:
        sys.exit(f"error: {len(failed)} of {len(folders)} set(s) not measured: {', '.join(map(str, failed))}")


if __name__ == "__main__":
    main()
