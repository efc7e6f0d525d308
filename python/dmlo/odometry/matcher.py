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
from it, so a model and its input geometry cannot drift apart. The metadata is checked by the crate's
rules (`dmlo_rs.ModelMetadata`, the ones its own runtimes apply) when the model is opened: a missing or
malformed key is a `ModelError` naming it, before any scan. The folder's file names are the crate's
(`dmlo_rs.ModelFolder`).
"""

from __future__ import annotations

import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

import dmlo_rs

MATCHING_STAGES = ("auto", "crate", "graph")
ModelError = dmlo_rs.ModelError  # a model file missing, not a dmlo export, or not fitting the input


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
    wide = frame_graph.with_name(dmlo_rs.ModelFolder.WIDE_WINDOW)
    if not wide.is_file():
        raise ModelError(
            f"{frame_graph.parent} has no {wide.name} for large motion; export one from the "
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
        graph = path / dmlo_rs.ModelFolder.FRAME if path.is_dir() else path
        if not graph.is_file():
            raise ModelError(f"model not found: {graph}")
        options = session_options(threads)
        providers = [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in ort.get_available_providers()]
        self._session, self.metadata = _open_graph_checked(graph, options, providers)
        if self.metadata.graph != "frame":
            raise ModelError(f"{graph}: a dmlo {self.metadata.graph!r} graph, not a frame graph")
        self.path = graph
        self.height, self.width = self.metadata.height, self.metadata.width
        self.cylinder = self.metadata.cylinder
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
        self._match_session: Any = None  # on the first `match` of the graph stage
        self._encoder_session: Any = None  # on the first `encode`
        self.matching_stage = self._choose_stage(matching_stage)
        if self.matching_stage == "crate":
            self._encoder_session = self._open_encoder()
        elif match_graph:
            self._match_session = self._open_match_graph()

    @property
    def uses_reflectance(self) -> bool:
        """Whether the model reads the reflectance channel (False: a range-only model)."""
        return self.metadata.use_reflectance

    def _choose_stage(self, requested: str) -> str:
        on_cpu = self._session.get_providers()[0] == "CPUExecutionProvider"
        scales = self.metadata.similarity_scales
        encoder = self.path.with_name(dmlo_rs.ModelFolder.ENCODER)
        crate_possible = scales is not None and encoder.is_file()
        if requested == "auto":
            return "crate" if on_cpu and crate_possible else "graph"
        if requested == "crate" and not crate_possible:
            missing = "dmlo.similarity_scales metadata" if scales is None else encoder.name
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
            self._encoder_session = self._open_encoder()
        coarse, refine = self._encoder_session.run(None, {"scan": image[None].astype(np.float32, copy=False)})
        return Features(coarse=coarse, refine=refine)

    def _match_in_crate(
        self,
        reference: Features,
        target: Features,
        cells: npt.NDArray[np.bool_] | None = None,
        guide: npt.NDArray[np.float32] | None = None,
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        metadata = self.metadata
        assert metadata.similarity_scales is not None  # `_choose_stage` chose the crate only with them
        coarse_scale, refine_scale = metadata.similarity_scales
        return dmlo_rs.match_features(
            reference.coarse, reference.refine, target.coarse, target.refine,
            coarse_window=metadata.coarse_window, refine_window=metadata.refine_window,
            coarse_scale=coarse_scale, refine_scale=refine_scale,
            refine_offset=metadata.refine_offset, cells=cells, guide=guide, num_threads=self._threads,
        )

    def _check_image(self, image: npt.NDArray[np.float32]) -> None:
        if image.shape != (2, self.height, self.width):
            raise ModelError(
                f"scan image {image.shape} does not fit the model's input (2, {self.height}, {self.width})"
            )

    def _open_match_graph(self) -> Any:
        return self._open_graph(dmlo_rs.ModelFolder.MATCH, "match", "match a scan back against the previous one")

    def _open_encoder(self) -> Any:
        return self._open_graph(dmlo_rs.ModelFolder.ENCODER, "encoder", "encode a scan on its own")

    def _open_graph(self, name: str, kind: str, purpose: str) -> Any:
        """A graph exported beside `frame.onnx`, checked by the crate to belong to the same model (the encoder
        serves every window of its weights)."""
        graph = self.path.with_name(name)
        if not graph.is_file():
            raise ModelError(
                f"{self.path.parent} has no {name} to {purpose}; export one with `dmlo export CHECKPOINT "
                "--out DIR` (it writes all three graphs)"
            )
        session, metadata = _open_graph_checked(graph, self._options, self._providers)
        metadata.check_export_of(kind, self.metadata, str(graph), self.path.name, ignore_matching_stage=kind == "encoder")
        return session


def _open_session(graph: Path, options: Any, providers: list[str]) -> Any:
    import onnxruntime as ort

    try:
        return ort.InferenceSession(str(graph), options, providers=providers)
    except Exception as err:  # onnxruntime raises its own exception types for unreadable files
        raise ModelError(f"{graph}: not a readable ONNX model ({err})") from err


def _open_graph_checked(graph: Path, options: Any, providers: list[str]) -> tuple[Any, dmlo_rs.ModelMetadata]:
    """An onnxruntime session of a dmlo graph and its metadata, checked by the crate's rules."""
    session = _open_session(graph, options, providers)
    return session, dmlo_rs.ModelMetadata(session.get_modelmeta().custom_metadata_map, str(graph))


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
        if isinstance(matcher, OnnxMatcher) and matcher.path.with_name(dmlo_rs.ModelFolder.WIDE_WINDOW).is_file():
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
