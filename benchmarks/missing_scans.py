"""The odometry across missing scans: how far off is the motion between the scans before and after a gap.

Every method runs a fresh odometry over `--lead-in` scans (20: KISS-ICP errs decimetres a frame over its
first scans, while its adaptive threshold settles), then `gap − 1` scans go missing and the next one is
registered; the error is that of the motion across the gap (angular `2·asin(‖R−R̄‖_F/(2√2))`, translation
‖t−t̄‖). DMLO is told the scans are missing (`Odometry.predict_skipped`, as `dmlo run` does for unreadable
files); the peers have no such call and are simply given the next scan, as a user of theirs would. A gap
counts as bridged when its motion errs less than 10 cm and 1°; gap 1 (nothing missing) is the baseline.

    python benchmarks/missing_scans.py DRIVE [DRIVE ...] --gaps 1 2 4 8 12 --cases 8
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dmlo.peers.peers import PEERS, FrameOdometry
from dmlo.datasets import open_sequence
from dmlo.metrics import registration_errors

BRIDGED_TRANSLATION_M = 0.1
BRIDGED_ROTATION_DEG = 1.0


@dataclass(frozen=True)
class Method:
    make: Callable[[], FrameOdometry]
    knows_gaps: bool  # has `predict_skipped` for the missing scans


def methods(model: Path | None, peers: list[str]) -> dict[str, Method]:
    from dmlo.odometry import Odometry, OdometryConfig

    def dmlo(rematch: bool, mapping: bool = False) -> Callable[[], FrameOdometry]:
        def make() -> Odometry:
            config = OdometryConfig()
            config.mapping.enabled = mapping
            if not rematch:
                config.motion_model.rematch_gap = None
            return Odometry(model, config) if model else Odometry.from_default(config)

        return make

    found = {
        "DMLO (re-matched from the prediction)": Method(dmlo(rematch=True), knows_gaps=True),
        "DMLO (the paper: the prediction when the pair fails)": Method(dmlo(rematch=False), knows_gaps=True),
        "DMLO + mapping": Method(dmlo(rematch=True, mapping=True), knows_gaps=True),
    }
    by_name = {peer.name: peer for peer in PEERS}
    for name in peers:
        if name not in by_name:
            raise SystemExit(f"unknown peer {name!r}; known: {', '.join(by_name)}")
        if by_name[name].available:
            found[name] = Method(by_name[name].make, knows_gaps=False)
    return found


def run(
    drives: list[Path], gaps: list[int], cases: int, model: Path | None, peers: list[str], lead_in: int = 20
) -> str:
    by_name = methods(model, peers)
    lines = [
        "| gap (frames) | method | bridged | rot. error mean / max (°) | transl. error mean / max (m) | s for the scan after |",
        "|---|---|---|---|---|---|",
    ]
    sequences = [open_sequence(drive) for drive in drives]
    for sequence, drive in zip(sequences, drives):
        if sequence.poses is None:
            raise SystemExit(f"{drive} has no ground truth")
        if len(sequence) <= lead_in - 1 + max(gaps):
            raise SystemExit(f"{drive}: {len(sequence)} scans, too few for a gap of {max(gaps)} after {lead_in}")
    for gap in gaps:
        # (sequence, index of the last scan before the gap)
        before_gap = [
            (sequence, int(last))
            for sequence in sequences
            for last in np.unique(
                np.linspace(lead_in - 1, len(sequence) - gap - 1, max(1, cases // len(sequences))).round()
            )
        ]
        for name, method in by_name.items():
            estimates, truths, seconds = [], [], 0.0
            for sequence, last in before_gap:
                odometry = method.make()
                for index in range(last - lead_in + 1, last + 1):
                    before = odometry.register(sequence[index].points)
                if method.knows_gaps:
                    for _ in range(gap - 1):
                        odometry.predict_skipped()  # type: ignore[attr-defined]
                scan = sequence[last + gap].points
                start = time.perf_counter()
                after = odometry.register(scan)
                seconds += time.perf_counter() - start
                estimates.append(np.linalg.inv(after) @ before)
                poses = sequence.poses
                assert poses is not None  # checked above
                truths.append(np.linalg.inv(poses[last + gap]) @ poses[last])
            errors = registration_errors(np.stack(estimates), np.stack(truths))
            bridged = (errors.translation < BRIDGED_TRANSLATION_M) & (errors.angular < BRIDGED_ROTATION_DEG)
            lines.append(
                f"| {gap} | {name} | {bridged.sum()}/{len(bridged)} "
                f"| {errors.angular.mean():.3f} / {errors.angular.max():.3f} "
                f"| {errors.translation.mean():.3f} / {errors.translation.max():.3f} | {seconds / len(before_gap):.2f} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("drives", type=Path, nargs="+", help="sequences with ground truth (e.g. dmlo simulate output)")
    parser.add_argument("--gaps", type=int, nargs="+", default=[1, 2, 4, 8, 12], help="frames between the scans kept")
    parser.add_argument("--lead-in", type=int, default=20, help="scans registered before each gap")
    parser.add_argument("--cases", type=int, default=8, help="gaps per length over all drives")
    parser.add_argument("--model", type=Path, default=None)
    parser.add_argument("--peers", nargs="*", default=["KISS-ICP", "small_gicp GICP"], help="peers run when installed")
    args = parser.parse_args(argv)
    if min(args.gaps) < 1 or args.lead_in < 2:
        parser.error("every gap is at least 1 frame, and the lead-in at least 2 scans (a measured velocity)")
    print(run(args.drives, args.gaps, args.cases, args.model, args.peers, args.lead_in))


if __name__ == "__main__":
    main()
