"""ONNX export of the matcher for onnxruntime, and reading back what an exported model declares.

Three graphs with static shapes (batch 1, H×W of the cylinder image), opset 19, deformable layers as the
ONNX ``DeformConv`` operator (ONNX-NOTES items 1–2):

``frame.onnx`` — one call per odometry frame (ONNX-NOTES item 10): the previous scan's cached features
and the new scan in, the flow from the previous scan into the new one and the new scan's features out.

    inputs   scan                  float32 [1, 2, H, W]      range (m, 0 = empty), reflectance
             prev_coarse_features  float32 [1, C, H/4, W/8]  from the previous call (or encoder.onnx)
             prev_refine_features  float32 [1, Cr, H, W]
    outputs  flow                  float32 [1, 2, H, W]      (Δrow, Δcol) in pixels: previous-scan cell
                                                             (i, j) matches new-scan location (i+Δrow, j+Δcol)
             confidence            float32 [1, H, W]         Q* in (0, 1]
             coarse_features       float32 [1, C, H/4, W/8]  of the new scan: the next call's prev_*
             refine_features       float32 [1, Cr, H, W]

``encoder.onnx`` — ``scan`` → ``coarse_features``, ``refine_features`` (the first frame).
``match.onnx`` — ``ref_coarse_features``, ``ref_refine_features``, ``tgt_coarse_features``,
``tgt_refine_features`` → ``flow``, ``confidence`` (any pair of encoded scans, reference → target).

Every graph carries metadata properties: ``dmlo.graph`` (frame / encoder / match), ``dmlo.interface_version``,
``dmlo.height``, ``dmlo.width``, ``dmlo.model_config`` (MatcherConfig JSON), ``dmlo.cylinder_config``
(the cylinder projection's settings as JSON) and ``dmlo.similarity_scales`` (JSON ``{"coarse", "refine"}``:
the learned softmax temperatures, so that `dmlo_rs.match_features` can run the matching stage on cached
features outside the graph).
"""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path
from typing import Any

INTERFACE_VERSION = "1"
OPSET = 19
GRAPHS = ("frame", "encoder", "match")
FEATURE_NAMES = ("coarse_features", "refine_features")


def cylinder_config_dict(config: Any) -> dict[str, Any]:
    """A JSON-able dict of a cylinder configuration (a dict, a dataclass or an object with public fields)."""
    if config is None:
        return {}
    if isinstance(config, dict):
        return dict(config)
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        return dataclasses.asdict(config)
    for method in ("to_dict", "as_dict"):
        if callable(getattr(config, method, None)):
            return dict(getattr(config, method)())
    values = {}
    for name in dir(config):
        if name.startswith("_"):
            continue
        value = getattr(config, name)
        if isinstance(value, (int, float, str, bool)) or (
            isinstance(value, (tuple, list)) and all(isinstance(v, (int, float)) for v in value)
        ):
            values[name] = value
    return values


def similarity_scales(model: Any) -> dict[str, float]:
    """The matcher's learned softmax temperatures as the graph uses them (float32 ``exp`` of the log scales)."""
    return {
        "coarse": float(model.coarse_log_scale.detach().float().exp()),
        "refine": float(model.refine_log_scale.detach().float().exp()),
    }


def _wrappers():  # type: ignore[no-untyped-def]
    """The three graph modules; defined lazily so importing this module does not import torch."""
    from torch import Tensor, nn

    from dmlo.model import Features, Matcher

    class FrameGraph(nn.Module):
        def __init__(self, model: Matcher) -> None:
            super().__init__()
            self.model = model

        def forward(self, scan: Tensor, prev_coarse: Tensor, prev_refine: Tensor):  # type: ignore[no-untyped-def]
            new = self.model.encode(scan)
            out = self.model.match(Features(prev_coarse, prev_refine), new)
            return out.flow, out.confidence, new.coarse, new.refine

    class EncoderGraph(nn.Module):
        def __init__(self, model: Matcher) -> None:
            super().__init__()
            self.model = model

        def forward(self, scan: Tensor):  # type: ignore[no-untyped-def]
            features = self.model.encode(scan)
            return features.coarse, features.refine

    class MatchGraph(nn.Module):
        def __init__(self, model: Matcher) -> None:
            super().__init__()
            self.model = model

        def forward(self, ref_coarse: Tensor, ref_refine: Tensor, tgt_coarse: Tensor, tgt_refine: Tensor):  # type: ignore[no-untyped-def]
            out = self.model.match(Features(ref_coarse, ref_refine), Features(tgt_coarse, tgt_refine))
            return out.flow, out.confidence

    return FrameGraph, EncoderGraph, MatchGraph


def export_onnx(
    model: Any,
    out_dir: str | Path,
    height: int,
    width: int,
    cylinder_config: Any = None,
    graphs: tuple[str, ...] = GRAPHS,
) -> dict[str, Path]:
    """Writes ``<graph>.onnx`` for each of ``graphs`` into ``out_dir``; returns their paths.

    ``model`` is a `dmlo.model.Matcher`; it is exported in eval mode (BatchNorm running statistics).
    """
    import onnx
    import torch

    from dmlo.model.matcher import check_scan

    unknown = sorted(set(graphs) - set(GRAPHS))
    if unknown:
        raise ValueError(f"unknown graphs {unknown}; choose from {list(GRAPHS)}")
    check_scan(torch.zeros(1, 2, height, width))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    config = model.config
    was_training = model.training
    model.eval()
    frame_graph, encoder_graph, match_graph = _wrappers()
    scan = torch.zeros(1, 2, height, width)
    coarse = torch.zeros(1, config.coarse_channels, height // 4, width // 8)
    refine = torch.zeros(1, config.refine_channels, height, width)
    specs = {
        "frame": (
            frame_graph(model),
            (scan, coarse, refine),
            ["scan", "prev_coarse_features", "prev_refine_features"],
            ["flow", "confidence", *FEATURE_NAMES],
        ),
        "encoder": (encoder_graph(model), (scan,), ["scan"], list(FEATURE_NAMES)),
        "match": (
            match_graph(model),
            (coarse, refine, coarse, refine),
            ["ref_coarse_features", "ref_refine_features", "tgt_coarse_features", "tgt_refine_features"],
            ["flow", "confidence"],
        ),
    }
    metadata = {
        "dmlo.interface_version": INTERFACE_VERSION,
        "dmlo.height": str(height),
        "dmlo.width": str(width),
        "dmlo.model_config": config.to_json(),
        "dmlo.cylinder_config": json.dumps(cylinder_config_dict(cylinder_config), sort_keys=True),
        "dmlo.similarity_scales": json.dumps(similarity_scales(model)),
    }
    paths = {}
    try:
        for name in graphs:
            wrapper, args, input_names, output_names = specs[name]
            # A fresh wrapper is in training mode and the exporter would keep it so (ONNX-NOTES item 9).
            wrapper.eval()
            path = out_dir / f"{name}.onnx"
            with torch.no_grad(), warnings.catch_warnings():
                # The tracer's notes on constants are expected: shapes are static by design.
                warnings.simplefilter("ignore")
                torch.onnx.export(
                    wrapper,
                    args,
                    str(path),
                    dynamo=False,
                    opset_version=OPSET,
                    input_names=input_names,
                    output_names=output_names,
                    do_constant_folding=True,
                )
            proto = onnx.load(str(path))
            for key, value in {**metadata, "dmlo.graph": name}.items():
                entry = proto.metadata_props.add()
                entry.key, entry.value = key, value
            onnx.checker.check_model(proto)
            onnx.save(proto, str(path))
            paths[name] = path
    finally:
        model.train(was_training)
    return paths


def read_metadata(path: str | Path) -> dict[str, Any]:
    """The ``dmlo.*`` metadata of an exported graph, JSON fields decoded, via onnxruntime (no torch)."""
    import onnxruntime as ort

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    raw = session.get_modelmeta().custom_metadata_map
    if "dmlo.interface_version" not in raw:
        raise ValueError(f"{path} is not a dmlo model export (no dmlo.interface_version metadata)")
    values: dict[str, Any] = dict(raw)
    for key in ("dmlo.model_config", "dmlo.cylinder_config"):
        values[key] = json.loads(raw[key])
    if "dmlo.similarity_scales" in raw:  # newer than interface 1's first exports
        values["dmlo.similarity_scales"] = json.loads(raw["dmlo.similarity_scales"])
    for key in ("dmlo.height", "dmlo.width"):
        values[key] = int(raw[key])
    return values
