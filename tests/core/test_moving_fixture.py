"""The fixture of the crate's moving-object network tests (`cargo test --features inference,onnxruntime`) is
what `dmlo.Odometry`'s detector flags today with the bundled `moving.onnx`: when the network is exported again,
the fixture must be too."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
GRAPH = Path(__file__).resolve().parents[2] / "python/dmlo/models/default/moving.onnx"


def test_the_moving_object_fixture_matches_pythons_detector_today(shared_data: Path) -> None:
    spec = importlib.util.spec_from_file_location("make_moving_flags", FIXTURES / "make_moving_flags.py")
    assert spec is not None and spec.loader is not None
    maker = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(maker)
    fixture = json.loads((FIXTURES / "moving_flags.json").read_text())
    today = maker.flags(shared_data, GRAPH)
    assert fixture["threshold"] == today["threshold"] == 0.5
    for recorded, now in zip(fixture["scans"], today["scans"], strict=True):
        assert recorded["scan"] == now["scan"]
        assert len(now["flagged"]) > 1000  # both scans have cars the network finds
        assert recorded["flagged"] == now["flagged"], f"re-run {maker.__file__}"
        np.testing.assert_allclose(recorded["probability"], now["probability"], atol=1e-5)


def test_the_exported_graph_has_no_operator_tract_cannot_run() -> None:
    """tract (the crate's pure-Rust runtime) has no IsInf; the graph's inputs are checked finite instead."""
    import onnx

    operators = {node.op_type for node in onnx.load(str(GRAPH)).graph.node}
    assert not operators & {"IsInf", "IsNaN"}, operators
