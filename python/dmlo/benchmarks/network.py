"""Per-frame onnxruntime time of the exported matcher (``frame.onnx``) for several refine variants.

    python -m dmlo.benchmarks.network [--height 64 --width 1792 --threads 2 --repeats 10 --profile]

Each variant is exported with random weights (time does not depend on them), then the sessions run in
turns so that machine load hits all of them alike; the table gives the median per-frame time.
"""

from __future__ import annotations

import argparse
import collections
import json
import tempfile
import time
from typing import Any
from pathlib import Path

import numpy as np

VARIANTS: dict[str, dict[str, Any]] = {
    "paper (2 plain + 3 deformable, 16 ch)": dict(refine_channels=16, refine_plain_layers=2, refine_deformable_layers=3),
    "paper, 8 ch": dict(refine_channels=8, refine_plain_layers=2, refine_deformable_layers=3),
    "light (4 plain + 1 deformable, 8 ch)": dict(refine_channels=8, refine_plain_layers=4, refine_deformable_layers=1),
    "fast (5 plain, 8 ch)": dict(refine_channels=8, refine_plain_layers=5, refine_deformable_layers=0),
}


def _profile(path: Path, feeds: dict[str, np.ndarray], threads: int, top: int = 10) -> list[tuple[str, float]]:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.enable_profiling = True
    options.profile_file_prefix = str(path.with_suffix(""))
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    runs = 3
    for _ in range(runs):
        session.run(None, feeds)
    totals: collections.Counter[str] = collections.Counter()
    for event in json.loads(Path(session.end_profiling()).read_text()):
        if event.get("cat") == "Node" and event["name"].endswith("_kernel_time"):
            totals[event["args"].get("op_name", "?")] += event["dur"]
    return [(op, micros / runs / 1000) for op, micros in totals.most_common(top)]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--height", type=int, default=64)
    parser.add_argument("--width", type=int, default=1792)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--profile", action="store_true", help="also print the costliest operator types")
    args = parser.parse_args(argv)

    import onnxruntime as ort
    import torch

    from dmlo.export import export_onnx
    from dmlo.model import Matcher, MatcherConfig

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    scan = np.stack(
        (rng.uniform(2, 60, (args.height, args.width)), rng.uniform(0, 1, (args.height, args.width)))
    )[None].astype(np.float32)
    sessions: dict[str, Any] = {}
    feeds: dict[str, Any] = {}
    paths: dict[str, Path] = {}
    with tempfile.TemporaryDirectory() as folder:
        for name, changes in VARIANTS.items():
            model = Matcher(MatcherConfig(**changes)).eval()
            out = Path(folder) / str(len(paths))
            paths[name] = export_onnx(model, out, args.height, args.width, graphs=("frame",))["frame"]
            options = ort.SessionOptions()
            options.intra_op_num_threads = args.threads
            # No spin-waiting: the process CPU time is then the work done, a figure that machine load
            # disturbs far less than wall time.
            options.add_session_config_entry("session.intra_op.allow_spinning", "0")
            sessions[name] = ort.InferenceSession(str(paths[name]), options, providers=["CPUExecutionProvider"])
            with torch.no_grad():
                features = model.encode(torch.from_numpy(scan))
            feeds[name] = {
                "scan": scan,
                "prev_coarse_features": features.coarse.numpy(),
                "prev_refine_features": features.refine.numpy(),
            }
            sessions[name].run(None, feeds[name])  # warm-up
        times: dict[str, list[float]] = {name: [] for name in VARIANTS}
        cpu_times: dict[str, list[float]] = {name: [] for name in VARIANTS}
        for _ in range(args.repeats):
            for name, session in sessions.items():
                start, start_cpu = time.perf_counter(), time.process_time()
                session.run(None, feeds[name])
                times[name].append(time.perf_counter() - start)
                cpu_times[name].append(time.process_time() - start_cpu)
        print(f"frame.onnx at {args.height}×{args.width}, onnxruntime {ort.__version__}, {args.threads} threads, "
              f"median of {args.repeats}\n")
        print("| refine variant | wall ms per frame | Hz | CPU ms per frame | CPU ms / threads |\n|---|---|---|---|---|")
        for name, values in times.items():
            ms = 1000 * float(np.median(values))
            cpu_ms = 1000 * float(np.median(cpu_times[name]))
            print(f"| {name} | {ms:.0f} | {1000 / ms:.1f} | {cpu_ms:.0f} | {cpu_ms / args.threads:.0f} |")
        if args.profile:
            for name in VARIANTS:
                ops = ", ".join(f"{op} {ms:.0f}" for op, ms in _profile(paths[name], feeds[name], args.threads))
                print(f"\n{name}: {ops} (ms)")


if __name__ == "__main__":
    main()
