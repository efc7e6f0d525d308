"""The matching network at run time: the exported ONNX graphs in onnxruntime and, on a CPU, its matching
stage in the crate.

The odometry calls the matcher once per scan: it encodes the new scan and matches the previous scan's
cached features against it, so each scan is encoded once. Where the matching stage (correlation and
window decoding, most of the exported `frame` graph's time on a CPU) runs is a choice:

- ``graph``: the `frame` graph does both in one onnxruntime session (ONNX-NOTES item 10) — on a GPU, all
  of it runs there;
- ``crate``: `encoder.onnx` encodes the scan and `dmlo_rs.match_features` matches the cached features on
  the CPU (the same computation, faster there: it computes each window's correlation directly instead of
  through the tensors the graph gathers for it; it needs the graphs' ``dmlo.similarity_scales``);
- ``auto`` (the default): ``crate`` when onnxruntime runs on the CPU and the model allows it, else ``graph``.

The graph's metadata carries the cylinder configuration it was trained for; the projection is built
from it, so a model and its input geometry cannot drift apart. All of the metadata that the run reads is
checked when the model is opened: a missing or malformed key is a `ModelError` naming it, before any scan.
"""

from __future__ import annotations

import json
import math
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

import dmlo_rs

FRAME_GRAPH = "frame.onnx"
WIDE_FRAME_GRAPH = "frame_wide.onnx"  # the same weights with the wide coarse window of §IV-D
MATCH_GRAPH = "match.onnx"  # any pair of cached features, e.g. the new scan back against the previous one
ENCODER_GRAPH = "encoder.onnx"  # a scan's features alone (frame.onnx would also match it against zeros)
RANGE_ONLY_DIR = "range_only"  # the range-only model's folder inside a model's folder
INTERFACE_VERSION = "1"
MATCHING_STAGES = ("auto", "crate", "graph")
REFINE_OFFSETS = ("window", "peak_centroid")  # `dmlo.model.MatcherConfig.refine_offset`
_MATCH_STAGE_KEYS = ("coarse_window", "refine_window", "refine_offset")  # export-time choices, same weights
_CYLINDER_KEYS = (
    "fov_up_deg",
    "fov_down_deg",
    "vertical_resolution_deg",
    "horizontal_resolution_deg",
    "height",
    "width",
)


class ModelError(ValueError):
    """A model file that is missing, not a dmlo export, or does not fit the input."""


@dataclass(frozen=True)
class Features:
    """One scan's cached network features (coarse at stride 4×8, refine at full resolution)."""

    coarse: npt.NDArray[np.float32]
    refine: npt.NDArray[np.float32]


@dataclass(frozen=True)
class FrameOutput:
    features: Features
    flow: npt.NDArray[np.float32] | None  # [2, H, W] (Δrow, Δcol) from the previous scan, None first
    confidence: npt.NDArray[np.float32] | None  # [H, W] Q*
    matching_ms: float | None = None  # of the call, the crate's matching stage (None: all of it in onnxruntime)


class Matcher(Protocol):
    path: Path
    cylinder: dmlo_rs.CylinderConfig

    def frame(self, image: npt.NDArray[np.float32], previous: Features | None) -> FrameOutput: ...

    def match(
        self, reference: Features, target: Features
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]: ...

    def encode(self, image: npt.NDArray[np.float32]) -> Features: ...


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the system tells it)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def session_options(threads: int) -> Any:
    """onnxruntime's options for every graph the odometry runs: `threads` (0: its choice), no spinning."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    # Idle worker threads would spin between frames and steal the cores from projection and RANSAC.
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if threads > 0:
        options.intra_op_num_threads = threads
    return options


def usable_threads(requested: int) -> int:
    """`threads` as onnxruntime and the crate's matching stage get them: 0 (they choose) or at most the
    machine's cores. More threads than cores only wait for one another, and onnxruntime sets every one up
    when a session opens (100000 blocked there, its memory growing), so more are bounded, with a warning."""
    cores = available_cores()
    if requested > cores:
        warnings.warn(
            f"threads: {requested} is more than the {cores} cores of this machine; using {cores}", stacklevel=3
        )
        return cores
    return requested


def default_model_path() -> Path:
    """The bundled default model: a folder with `frame.onnx` inside the installed package."""
    return Path(__file__).resolve().parent.parent / "models" / "default"


def onnxruntime_library() -> Path:
    """The shared library inside the installed `onnxruntime` wheel (`onnxruntime/capi/libonnxruntime.*`): the one
    the crate's `onnxruntime` feature loads (`OrtEncoder`, `examples/odometry.rs --onnxruntime`) to run the
    network as `dmlo run` does. `ModelError` when the wheel holds none."""
    import onnxruntime

    capi = Path(onnxruntime.__file__).parent / "capi"
    found = sorted(path for path in capi.iterdir() if path.name.startswith("libonnxruntime.")
                   or path.name == "onnxruntime.dll") if capi.is_dir() else []
    if not found:
        raise ModelError(f"{capi}: no onnxruntime shared library in the installed onnxruntime wheel")
    return found[0]


def wide_graph_path(frame_graph: Path) -> Path:
    """The large-motion graph stored beside a model's `frame.onnx`."""
    wide = frame_graph.with_name(WIDE_FRAME_GRAPH)
    if not wide.is_file():
        raise ModelError(
            f"{frame_graph.parent} has no {WIDE_FRAME_GRAPH} for large motion; export one from the "
            "checkpoint with `dmlo export CHECKPOINT --out DIR --wide-window 41`"
        )
    return wide


class OnnxMatcher:
    """Runs an exported `frame.onnx` (or a folder holding one) on the CPU, or CUDA when available.

    `match_graph` opens what `match` needs at once (a missing graph is an error here rather than on the
    first `match`); `matching_stage` chooses where the matching stage runs (module docs); `threads` beyond
    the machine's cores are bounded to them (`usable_threads`)."""

    def __init__(self, path: Path, threads: int = 0, match_graph: bool = False, matching_stage: str = "auto") -> None:
        import onnxruntime as ort

        threads = usable_threads(threads)
        if matching_stage not in MATCHING_STAGES:
            raise ValueError(f"matching_stage: expected one of {', '.join(MATCHING_STAGES)}, got {matching_stage!r}")
        graph = path / FRAME_GRAPH if path.is_dir() else path
        if not graph.is_file():
            raise ModelError(f"model not found: {graph}")
        options = session_options(threads)
        providers = [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in ort.get_available_providers()]
        self._session = _open_session(graph, options, providers)
        metadata = self._session.get_modelmeta().custom_metadata_map
        if metadata.get("dmlo.interface_version") != INTERFACE_VERSION or metadata.get("dmlo.graph") != "frame":
            raise ModelError(f"{graph}: not a dmlo frame graph (interface {INTERFACE_VERSION} expected)")
        self.path = graph
        self.model_config = _model_config(metadata, graph)
        self.height, self.width = _size(metadata, graph)
        self.cylinder = _cylinder_from_metadata(_json_object(metadata, "dmlo.cylinder_config", graph), graph)
        if (self.cylinder.height, self.cylinder.width) != (self.height, self.width):
            raise ModelError(
                f"{graph}: network input {self.height}×{self.width} does not match its cylinder image "
                f"{self.cylinder.height}×{self.cylinder.width}"
            )
        shapes = {i.name: i.shape for i in self._session.get_inputs()}
        missing = [name for name in ("scan", "prev_coarse_features", "prev_refine_features") if name not in shapes]
        if missing:
            raise ModelError(f"{graph}: a frame graph without the input(s) {', '.join(missing)}")
        self._zeros = Features(
            coarse=np.zeros(shapes["prev_coarse_features"], np.float32),
            refine=np.zeros(shapes["prev_refine_features"], np.float32),
        )
        self._options, self._providers = options, providers
        self._threads = threads if threads > 0 else None
        self._scales = _similarity_scales(metadata, graph)
        self._match_session: Any = None  # on the first `match` of the graph stage
        self._encoder_session: Any = None  # on the first `encode`
        self.matching_stage = self._choose_stage(matching_stage)
        if self.matching_stage == "crate":
            self._encoder_session = self._open_graph(ENCODER_GRAPH, "encoder", "encode a scan on its own")
        elif match_graph:
            self._match_session = self._open_match_graph()

    @property
    def uses_reflectance(self) -> bool:
        """Whether the model reads the reflectance channel (False: a range-only model)."""
        return self.model_config.get("use_reflectance", True) is not False

    def _choose_stage(self, requested: str) -> str:
        on_cpu = self._session.get_providers()[0] == "CPUExecutionProvider"
        crate_possible = self._scales is not None and self.path.with_name(ENCODER_GRAPH).is_file()
        if requested == "auto":
            return "crate" if on_cpu and crate_possible else "graph"
        if requested == "crate" and not crate_possible:
            missing = "dmlo.similarity_scales metadata" if self._scales is None else ENCODER_GRAPH
            raise ModelError(
                f"{self.path}: matching in the crate needs {missing} (export the model again with `dmlo export`)"
            )
        return requested

    def frame(self, image: npt.NDArray[np.float32], previous: Features | None) -> FrameOutput:
        self._check_image(image)
        if self.matching_stage == "crate":
            features = self.encode(image)
            if previous is None:
                return FrameOutput(features, None, None)
            start = time.perf_counter()
            flow, confidence = self._match_in_crate(previous, features)
            return FrameOutput(features, flow, confidence, (time.perf_counter() - start) * 1e3)
        prev = previous or self._zeros
        flow, confidence, coarse, refine = self._session.run(
            None,
            {
                "scan": image[None].astype(np.float32, copy=False),
                "prev_coarse_features": prev.coarse,
                "prev_refine_features": prev.refine,
            },
        )
        features = Features(coarse=coarse, refine=refine)
        if previous is None:  # matched against zeros: only the features mean anything
            return FrameOutput(features, None, None)
        return FrameOutput(features, flow[0], confidence[0])

    def match(
        self,
        reference: Features,
        target: Features,
        cells: npt.NDArray[np.bool_] | None = None,
        guide: npt.NDArray[np.float32] | None = None,
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """Flow `[2, H, W]` and confidence `[H, W]` from `reference` to `target`, both scans' cached
        features (`match.onnx` beside `frame.onnx`, the same weights, or the crate): no scan is encoded again.
        `cells` (bool `[H, W]`): the reference cells whose flow is wanted; in the crate the others are left
        out (NaN flow, confidence 0), the graph matches every cell. `guide` (float32 `[H, W, 2]`, the crate's
        stage only): each cell's expected flow (NaN: none), where the coarse windows are placed
        (`dmlo_rs.match_features`)."""
        if self.matching_stage == "crate":
            return self._match_in_crate(reference, target, cells, guide)
        if guide is not None:
            raise ModelError(f"{self.path}: placing the coarse windows (guide) needs the crate's matching stage")
        if self._match_session is None:
            self._match_session = self._open_match_graph()
        flow, confidence = self._match_session.run(
            None,
            {
                "ref_coarse_features": reference.coarse,
                "ref_refine_features": reference.refine,
                "tgt_coarse_features": target.coarse,
                "tgt_refine_features": target.refine,
            },
        )
        return flow[0], confidence[0]

    def encode(self, image: npt.NDArray[np.float32]) -> Features:
        """A scan's features alone (`encoder.onnx` beside `frame.onnx`, the same weights), for scans that are
        only ever matched through `match` or as a `frame` call's `previous`."""
        self._check_image(image)
        if self._encoder_session is None:
            self._encoder_session = self._open_graph(ENCODER_GRAPH, "encoder", "encode a scan on its own")
        coarse, refine = self._encoder_session.run(None, {"scan": image[None].astype(np.float32, copy=False)})
        return Features(coarse=coarse, refine=refine)

    def _match_in_crate(
        self,
        reference: Features,
        target: Features,
        cells: npt.NDArray[np.bool_] | None = None,
        guide: npt.NDArray[np.float32] | None = None,
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        assert self._scales is not None  # `_choose_stage` chose the crate only with them
        config = self.model_config
        return dmlo_rs.match_features(
            reference.coarse, reference.refine, target.coarse, target.refine,
            coarse_window=config["coarse_window"], refine_window=config["refine_window"],
            coarse_scale=self._scales["coarse"], refine_scale=self._scales["refine"],
            refine_offset=config["refine_offset"], cells=cells, guide=guide, num_threads=self._threads,
        )

    def _same_weights(self, config: Any, kind: str) -> bool:
        """Whether a graph's model config is this graph's, up to what the graph's kind does not depend on: the
        encoder serves every export of the same weights (e.g. `frame_wide.onnx`, whose windows differ)."""
        if not isinstance(config, dict):
            return False
        ignored = _MATCH_STAGE_KEYS if kind == "encoder" else ()
        return {k: v for k, v in config.items() if k not in ignored} == {
            k: v for k, v in self.model_config.items() if k not in ignored
        }

    def _check_image(self, image: npt.NDArray[np.float32]) -> None:
        if image.shape != (2, self.height, self.width):
            raise ModelError(
                f"scan image {image.shape} does not fit the model's input (2, {self.height}, {self.width})"
            )

    def _open_match_graph(self) -> Any:
        return self._open_graph(MATCH_GRAPH, "match", "match a scan back against the previous one")

    def _open_graph(self, name: str, kind: str, purpose: str) -> Any:
        """A graph exported beside `frame.onnx`, checked to belong to the same model and input size."""
        graph = self.path.with_name(name)
        if not graph.is_file():
            raise ModelError(
                f"{self.path.parent} has no {name} to {purpose}; export one with `dmlo export CHECKPOINT "
                "--out DIR` (it writes all three graphs)"
            )
        session = _open_session(graph, self._options, self._providers)
        metadata = session.get_modelmeta().custom_metadata_map
        if metadata.get("dmlo.graph") != kind or not self._same_weights(_model_config(metadata, graph), kind):
            raise ModelError(f"{graph}: not the {kind} graph of {self.path.name}'s model")
        if _size(metadata, graph) != (self.height, self.width):
            raise ModelError(f"{graph}: input size differs from {self.path.name}'s {self.height}×{self.width}")
        return session


def _open_session(graph: Path, options: Any, providers: list[str]) -> Any:
    import onnxruntime as ort

    try:
        return ort.InferenceSession(str(graph), options, providers=providers)
    except Exception as err:  # onnxruntime raises its own exception types for unreadable files
        raise ModelError(f"{graph}: not a readable ONNX model ({err})") from err


def _json_object(metadata: dict[str, str], key: str, graph: Path) -> dict[str, Any]:
    """A metadata property holding a JSON object, or a `ModelError` naming it."""
    if key not in metadata:
        raise ModelError(f"{graph}: its metadata lacks {key} (export the model again with `dmlo export`)")
    try:
        value = json.loads(metadata[key])
    except ValueError as err:
        raise ModelError(f"{graph}: metadata {key} is not JSON ({err})") from None
    if not isinstance(value, dict):
        raise ModelError(f"{graph}: metadata {key} must be a JSON object, got {metadata[key][:60]!r}")
    return value


def _size(metadata: dict[str, str], graph: Path) -> tuple[int, int]:
    """The network input's `dmlo.height` and `dmlo.width`."""
    size = []
    for key in ("dmlo.height", "dmlo.width"):
        text = metadata.get(key)
        if text is None:
            raise ModelError(f"{graph}: its metadata lacks {key} (export the model again with `dmlo export`)")
        if not text.strip().isdigit() or int(text) < 1:
            raise ModelError(f"{graph}: metadata {key} must be a positive integer, got {text[:60]!r}")
        size.append(int(text))
    return size[0], size[1]


def _model_config(metadata: dict[str, str], graph: Path) -> dict[str, Any]:
    """`dmlo.model_config`, with the settings the run reads checked: the matching stage's windows and
    offset, and whether the model reads reflectance (absent: it does, as models exported before it)."""
    config = _json_object(metadata, "dmlo.model_config", graph)
    for name in ("coarse_window", "refine_window"):
        if name not in config:
            raise ModelError(f"{graph}: metadata dmlo.model_config lacks {name}")
        value = config[name]
        if isinstance(value, bool) or not isinstance(value, int) or value < 3 or value % 2 == 0:
            raise ModelError(f"{graph}: dmlo.model_config.{name} must be an odd integer >= 3, got {value!r}")
    if config.get("refine_offset") not in REFINE_OFFSETS:
        got = f"got {config['refine_offset']!r}" if "refine_offset" in config else "it lacks it"
        raise ModelError(f"{graph}: dmlo.model_config.refine_offset must be one of {', '.join(REFINE_OFFSETS)}; {got}")
    if not isinstance(config.get("use_reflectance", True), bool):
        raise ModelError(f"{graph}: dmlo.model_config.use_reflectance must be true or false, got {config['use_reflectance']!r}")
    return config


def _similarity_scales(metadata: dict[str, str], graph: Path) -> dict[str, float] | None:
    """`dmlo.similarity_scales` (the learned softmax temperatures the crate's matching stage needs), None for
    models exported before it: they match in the graph."""
    if "dmlo.similarity_scales" not in metadata:
        return None
    scales = _json_object(metadata, "dmlo.similarity_scales", graph)
    for name in ("coarse", "refine"):
        value = scales.get(name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            got = f"got {value!r}" if name in scales else "it lacks it"
            raise ModelError(f"{graph}: dmlo.similarity_scales.{name} must be a finite number > 0; {got}")
    return {"coarse": float(scales["coarse"]), "refine": float(scales["refine"])}


def _cylinder_from_metadata(values: dict[str, object], graph: Path) -> dmlo_rs.CylinderConfig:
    missing = [k for k in _CYLINDER_KEYS if k not in values]
    if missing:
        raise ModelError(f"{graph}: cylinder configuration lacks {', '.join(missing)}")
    try:
        return dmlo_rs.CylinderConfig(**{k: values[k] for k in _CYLINDER_KEYS})  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError) as err:
        raise ModelError(f"{graph}: invalid cylinder configuration: {err}") from err


class FrameMatcherAdapter:
    """`matcher` adapted to the crate's `FrameMatcher` protocol, as its odometry loop (`dmlo_rs.Odometry`)
    calls it: `encode`, `match`, `cylinder`, `uses_reflectance`, `match_cells` and `match_guided` when the
    crate matches (only the cells that hold a point: the loop reads no other; the coarse windows placed where
    the prediction takes each cell, for pairs beyond the window), and `wide_match` when the wide-window graph
    lies beside the model (opened on the first pair far apart, with `threads` and `matching_stage` as the
    model's; an `OnnxMatcher`'s only).

    A matcher that matches in the crate (`OnnxMatcher` on a CPU) encodes each scan with `encoder.onnx`. Any
    other — the `frame` graph, which encodes a scan while matching the previous one against it (all of it on
    the GPU), or a matcher with only `frame` — defers the encoding: `encode` keeps the image, and the scan's
    first `match` as the target runs `frame`; a scan needed before that is encoded alone (`encoder.onnx`, or
    `frame` against nothing for a model without one)."""

    def __init__(self, matcher: Matcher, threads: int = 0, matching_stage: str = "auto") -> None:
        self.matcher = matcher
        self.cylinder = matcher.cylinder
        self.uses_reflectance = getattr(matcher, "uses_reflectance", True)
        self._encodes_alone = getattr(matcher, "matching_stage", None) == "crate"
        self._wide: OnnxMatcher | None = None
        self._threads, self._matching_stage = threads, matching_stage
        # The wide-window graph reads its model's features: a matcher of another kind has its own.
        if isinstance(matcher, OnnxMatcher) and matcher.path.with_name(WIDE_FRAME_GRAPH).is_file():
            self.wide_match = self._wide_match
        if self._encodes_alone and isinstance(matcher, OnnxMatcher):
            self.match_cells = self._match_cells
            self.match_guided = self._match_guided

    def encode(self, image: npt.NDArray[np.float32]) -> Features | _Deferred:
        return self.matcher.encode(image) if self._encodes_alone else _Deferred(image)

    @property
    def defers_encoding(self) -> bool:
        """Whether scans are encoded inside `match` (the frame graph) rather than by `encode`."""
        return not self._encodes_alone

    def match(
        self, reference: Features | _Deferred, target: Features | _Deferred
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        previous = self._features(reference)
        if isinstance(target, _Deferred) and target.features is None:
            output = self.matcher.frame(target.image, previous)
            target.features = output.features
            assert output.flow is not None and output.confidence is not None
            return output.flow, output.confidence
        return self.matcher.match(previous, self._features(target))

    def _match_cells(
        self, reference: Features, target: Features, cells: npt.NDArray[np.bool_]
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        assert isinstance(self.matcher, OnnxMatcher)
        return self.matcher.match(reference, target, cells)

    def _match_guided(
        self, reference: Features, target: Features, cells: npt.NDArray[np.bool_], guide: npt.NDArray[np.float32]
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        assert isinstance(self.matcher, OnnxMatcher)
        return self.matcher.match(reference, target, cells, guide)

    def _features(self, features: Features | _Deferred) -> Features:
        if not isinstance(features, _Deferred):
            return features
        if features.features is None:
            try:
                features.features = self.matcher.encode(features.image)
            except (ModelError, AttributeError):  # no encoder.onnx (or a matcher with `frame` alone)
                features.features = self.matcher.frame(features.image, None).features
        return features.features

    def _wide_match(
        self, reference: Features | _Deferred, target: Features | _Deferred, target_image: npt.NDArray[np.float32]
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """The wide window's flow of `reference` into `target` (features of the model's encoder; the scan's
        image `target_image` for a wide graph that matches in the graph, which encodes it itself)."""
        if self._wide is None:
            self._wide = OnnxMatcher(
                wide_graph_path(self.matcher.path), threads=self._threads, matching_stage=self._matching_stage
            )
        if self._wide.matching_stage == "crate":
            return self._wide.match(self._features(reference), self._features(target))
        output = self._wide.frame(target_image, self._features(reference))
        assert output.flow is not None and output.confidence is not None
        return output.flow, output.confidence


@dataclass
class _Deferred:
    """A scan's image whose features are computed when first needed (`FrameMatcherAdapter`)."""

    image: npt.NDArray[np.float32]
    features: Features | None = None
