"""Per-frame onnxruntime time of the exported matcher (``frame.onnx``) for several refine variants, of
exported model folders on a real scan pair, or of where a model's matching stage runs.

    python benchmarks/network.py [--height 64 --width 1792 --threads 2 --repeats 10 --profile]
    python benchmarks/network.py --models python/dmlo/models/default other/ --drive DRIVE [--frame 10]
        [--graph frame_wide]
    python benchmarks/network.py --stages --drive DRIVE [--models FOLDER]

With ``--stages`` one model (default: the bundled one) runs its correlation and window decoding both ways on
the same scan pair of ``--drive``, each call timed in turns with the others: in onnxruntime (``frame.onnx``
whole, ``match.onnx`` on cached features, ``frame_wide.onnx``) and in the crate (``encoder.onnx`` followed by
`dmlo_rs.match_features`, or the latter alone); the table gives the ratios and how many cells' flow differ.

Without ``--models`` each refine variant is exported with random weights (time does not depend on them).
With ``--models`` the folders' own ``frame.onnx`` (or ``frame_wide.onnx``) run on two consecutive scans of
``--drive`` projected by the odometry, each fed the previous scan's features from its own ``encoder.onnx``;
the table also gives how far each model's flow and confidence are from the first model's. Either way the sessions run
in turns so that machine load hits all of them alike, and the table gives the median per-frame time.
"""

from __future__ import annotations

import argparse
import collections
import functools
import json
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

VARIANTS: dict[str, dict[str, Any]] = {
    "paper (2 plain + 3 deformable, 16 ch)": dict(refine_channels=16, refine_plain_layers=2, refine_deformable_layers=3),
    "paper, 8 ch": dict(refine_channels=8, refine_plain_layers=2, refine_deformable_layers=3),
    "light (4 plain + 1 deformable, 8 ch)": dict(refine_channels=8, refine_plain_layers=4, refine_deformable_layers=1),
    "fast (5 plain, 8 ch)": dict(refine_channels=8, refine_plain_layers=5, refine_deformable_layers=0),
}


def _session(path: Path, threads: int) -> Any:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    # No spin-waiting: the process CPU time is then the work done, a figure that machine load
    # disturbs far less than wall time.
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def _profile(path: Path, feeds: dict[str, np.ndarray], threads: int, top: int = 10) -> list[tuple[str, float]]:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.enable_profiling = True
    totals: collections.Counter[str] = collections.Counter()
    # The trace goes to a temporary folder, never beside the model (which may be the installed package's).
    with tempfile.TemporaryDirectory() as folder:
        options.profile_file_prefix = str(Path(folder) / "profile")
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        runs = 3
        for _ in range(runs):
            session.run(None, feeds)
        for event in json.loads(Path(session.end_profiling()).read_text()):
            if event.get("cat") == "Node" and event["name"].endswith("_kernel_time"):
                totals[event["args"].get("op_name", "?")] += event["dur"]
    return [(op, micros / runs / 1000) for op, micros in totals.most_common(top)]


def _time_in_turns(sessions: dict[str, Any], feeds: dict[str, Any], repeats: int) -> dict[str, tuple[float, float]]:
    """Median (wall ms, CPU ms) per session, the sessions run one after the other ``repeats`` times."""
    return _time_calls({name: functools.partial(session.run, None, feeds[name]) for name, session in sessions.items()}, repeats)


def _time_calls(calls: dict[str, Callable[[], object]], repeats: int) -> dict[str, tuple[float, float]]:
    """Median (wall ms, CPU ms) per call, the calls made one after the other ``repeats`` times."""
    for call in calls.values():
        call()  # warm-up
    times: dict[str, list[float]] = {name: [] for name in calls}
    cpu_times: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            start, start_cpu = time.perf_counter(), time.process_time()
            call()
            times[name].append(time.perf_counter() - start)
            cpu_times[name].append(time.process_time() - start_cpu)
    return {name: (1000 * float(np.median(times[name])), 1000 * float(np.median(cpu_times[name]))) for name in calls}


def _variant_table(args: argparse.Namespace) -> None:
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
            sessions[name] = _session(paths[name], args.threads)
            with torch.no_grad():
                features = model.encode(torch.from_numpy(scan))
            feeds[name] = {
                "scan": scan,
                "prev_coarse_features": features.coarse.numpy(),
                "prev_refine_features": features.refine.numpy(),
            }
        medians = _time_in_turns(sessions, feeds, args.repeats)
        print(f"frame.onnx at {args.height}×{args.width}, onnxruntime {ort.__version__}, {args.threads} threads, "
              f"median of {args.repeats}\n")
        print("| refine variant | wall ms per frame | Hz | CPU ms per frame | CPU ms / threads |\n|---|---|---|---|---|")
        for name, (ms, cpu_ms) in medians.items():
            print(f"| {name} | {ms:.0f} | {1000 / ms:.1f} | {cpu_ms:.0f} | {cpu_ms / args.threads:.0f} |")
        if args.profile:
            for name in VARIANTS:
                ops = ", ".join(f"{op} {ms:.0f}" for op, ms in _profile(paths[name], feeds[name], args.threads))
                print(f"\n{name}: {ops} (ms)")


def _model_table(args: argparse.Namespace) -> None:
    import onnxruntime as ort

    from dmlo.datasets import open_sequence
    from dmlo.odometry import Odometry

    if args.drive is None:
        raise SystemExit("--models needs --drive: the sequence whose scans are fed to the models")
    sequence = open_sequence(args.drive)
    odometry = Odometry(args.models[0])
    previous, scan = (odometry.project(sequence[args.frame + step].points)[0][None].astype(np.float32) for step in (0, 1))
    names = [str(folder) for folder in args.models]
    if len(set(names)) != len(names):
        raise SystemExit("--models: name each folder once (its row would be timed and compared with itself)")
    sessions = {name: _session(folder / f"{args.graph}.onnx", args.threads) for name, folder in zip(names, args.models)}
    feeds = {}
    for name, folder in zip(names, args.models):
        prev_coarse, prev_refine = _session(folder / "encoder.onnx", args.threads).run(None, {"scan": previous})
        feeds[name] = {"scan": scan, "prev_coarse_features": prev_coarse, "prev_refine_features": prev_refine}
    outputs = {name: sessions[name].run(None, feeds[name]) for name in names}
    medians = _time_in_turns(sessions, feeds, args.repeats)
    print(f"{args.graph}.onnx on {args.drive} frames {args.frame}→{args.frame + 1} ({scan.shape[2]}×{scan.shape[3]}), "
          f"onnxruntime {ort.__version__}, {args.threads} threads, median of {args.repeats}\n")
    print("| model | wall ms per frame | Hz | CPU ms per frame | max \\|Δflow\\| px | cells \\|Δflow\\| > 1e-4 | max \\|ΔQ*\\| |")
    print("|---|---|---|---|---|---|---|")
    first_flow, first_confidence = outputs[names[0]][:2]
    for name, (ms, cpu_ms) in medians.items():
        flow, confidence = outputs[name][:2]
        flow_change = np.abs(flow - first_flow).max(axis=1)
        print(f"| {name} | {ms:.1f} | {1000 / ms:.1f} | {cpu_ms:.1f} | {flow_change.max():.2g} | "
              f"{int((flow_change > 1e-4).sum())} | {np.abs(confidence - first_confidence).max():.2g} |")
    if args.profile:
        for name, folder in zip(names, args.models):
            ops = ", ".join(f"{op} {ms:.1f}" for op, ms in _profile(folder / f"{args.graph}.onnx", feeds[name], args.threads))
            print(f"\n{name}: {ops} (ms)")


def _stage_table(args: argparse.Namespace) -> None:
    import onnxruntime as ort

    from dmlo.datasets import open_sequence
    from dmlo.odometry import Odometry
    from dmlo.odometry.matcher import OnnxMatcher, default_model_path

    if args.drive is None:
        raise SystemExit("--stages needs --drive: the sequence whose scans are matched")
    if args.models and len(args.models) > 1:
        raise SystemExit("--stages times one model: name a single folder with --models")
    folder = args.models[0] if args.models else default_model_path()
    sequence = open_sequence(args.drive)
    previous, scan = (Odometry(folder).project(sequence[args.frame + step].points)[0] for step in (0, 1))
    ways = {
        (stage, graph): OnnxMatcher(folder / graph, threads=args.threads, matching_stage=stage)
        for stage in ("graph", "crate")
        for graph in ("frame.onnx", "frame_wide.onnx")
    }
    cached = ways["crate", "frame.onnx"].encode(previous), ways["crate", "frame.onnx"].encode(scan)
    # In pairs: onnxruntime's way, then the crate's.
    rows: dict[str, Callable[[], Any]] = {
        "frame.onnx (encode + match)": lambda: ways["graph", "frame.onnx"].frame(scan, cached[0]),
        "encoder.onnx + crate": lambda: ways["crate", "frame.onnx"].frame(scan, cached[0]),
        "match.onnx (cached features)": lambda: ways["graph", "frame.onnx"].match(*cached),
        "crate alone (cached features)": lambda: ways["crate", "frame.onnx"].match(*cached),
        "frame_wide.onnx (encode + match)": lambda: ways["graph", "frame_wide.onnx"].frame(scan, cached[0]),
        "encoder.onnx + crate, wide window": lambda: ways["crate", "frame_wide.onnx"].frame(scan, cached[0]),
    }
    medians = _time_calls(rows, args.repeats)
    window = ways["graph", "frame_wide.onnx"].metadata.coarse_window
    print(f"{folder} on {args.drive} frames {args.frame}→{args.frame + 1} ({scan.shape[1]}×{scan.shape[2]}), "
          f"onnxruntime {ort.__version__}, {args.threads} threads, median of {args.repeats}; wide: D = {window}\n")
    print("| matching stage | wall ms | CPU ms | graph / crate (wall) | cells \\|Δflow\\| > 1e-3 |\n|---|---|---|---|---|")
    names = list(rows)
    for graph_row, crate_row in zip(names[::2], names[1::2]):
        graph_flow = _flow(rows[graph_row]())
        crate_flow = _flow(rows[crate_row]())
        differing = int((np.abs(graph_flow - crate_flow).max(axis=0) > 1e-3).sum())
        ratio = medians[graph_row][0] / medians[crate_row][0]
        print(f"| {graph_row} | {medians[graph_row][0]:.1f} | {medians[graph_row][1]:.1f} | | |")
        print(f"| {crate_row} | {medians[crate_row][0]:.1f} | {medians[crate_row][1]:.1f} | {ratio:.2f} | "
              f"{differing} of {crate_flow[0].size} |")


def _flow(output: Any) -> np.ndarray:
    """The flow of a `frame` (FrameOutput) or `match` ((flow, confidence)) call."""
    return np.asarray(output[0] if isinstance(output, tuple) else output.flow)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--height", type=int, default=64)
    parser.add_argument("--width", type=int, default=1792)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--profile", action="store_true", help="also print the costliest operator types")
    parser.add_argument("--models", type=Path, nargs="+", help="exported model folders to time instead of the variants")
    parser.add_argument("--drive", type=Path, help="with --models: a sequence to take the scan pair from")
    parser.add_argument("--frame", type=int, default=0, help="with --models: the first scan of the pair")
    parser.add_argument("--graph", default="frame", choices=("frame", "frame_wide"),
                        help="with --models: the per-frame graph to time (same inputs and outputs)")
    parser.add_argument("--stages", action="store_true",
                        help="time one model's matching stage in onnxruntime against the crate (needs --drive)")
    args = parser.parse_args(argv)
    if args.stages:
        _stage_table(args)
    elif args.models:
        _model_table(args)
    else:
        _variant_table(args)


if __name__ == "__main__":
    main()
