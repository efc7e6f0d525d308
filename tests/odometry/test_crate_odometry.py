"""`dmlo.Odometry` is the crate's per-frame loop (`dmlo_rs.Odometry`, `odometry::pipeline` in Rust) run over
Python's matcher (onnxruntime behind the crate's `FrameMatcher` trait, `dmlo.odometry.matcher.FrameMatcherAdapter`):
what Python adds (scan checks, reflectance notices, the moving-object network) changes no pose; the frame graph
runs once a scan where it matches (`matching_stage` "graph", or a model with `frame.onnx` alone); the binding
passes the matcher's own exceptions through and names wrong outputs, bad configs and bad scans. (Before the
Python loop was removed, the crate's loop was held to it at 1e-12 m on every real drive and setting,
`docs/measurements.md`.)"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import dmlo_rs
import numpy as np
import pytest

from dmlo.datasets import open_sequence
from dmlo.odometry import Odometry, OdometryConfig
from dmlo.odometry.matcher import FrameMatcherAdapter, OnnxMatcher, default_model_path
from dmlo.odometry import ReflectanceNotice

GRAPHS = ("encoder.onnx", "frame.onnx", "match.onnx")


@pytest.fixture(scope="module")
def three_graphs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("model")
    for graph in GRAPHS:
        (folder / graph).symlink_to(default_model_path() / graph)
    return folder / "frame.onnx"


def _scans(shared_data: Path, name: str) -> tuple[list[np.ndarray], list[float] | None]:
    folder = shared_data / "kitti_real" / name
    if not folder.is_dir():
        pytest.skip(f"{folder} not found")
    sequence = open_sequence(folder)
    frames = [sequence[i] for i in range(len(sequence))]
    times = [frame.timestamp for frame in frames]
    return [frame.points for frame in frames], None if any(t is None for t in times) else times  # type: ignore[misc]


def _without_timings(diagnostics: list[dmlo_rs.FrameDiagnostics]) -> list[dict[str, Any]]:
    return [{key: value for key, value in d.to_dict().items() if key != "timings_ms"} for d in diagnostics]


@pytest.mark.slow
@pytest.mark.parametrize(("name", "mapping"), [("odometry_03", True), ("raw_drive_22", False)])
def test_dmlo_odometry_adds_nothing_to_the_crates_poses(
    shared_data: Path, three_graphs: Path, name: str, mapping: bool
) -> None:
    scans, times = _scans(shared_data, name)
    config = OdometryConfig()
    config.mapping.enabled = mapping
    python = Odometry(three_graphs, config)
    crate = dmlo_rs.Odometry(python.matcher, json.dumps(config.to_dict()))
    for index, points in enumerate(scans):
        timestamp = None if times is None else times[index]
        expected = python.register(points, timestamp=timestamp)
        got = crate.register(points, timestamp=timestamp)
        np.testing.assert_array_equal(got, expected, err_msg=f"{name} scan {index}")
    assert _without_timings(crate.diagnostics) == _without_timings(python.diagnostics)
    assert crate.reflectance_scale == "unit" and len(crate) == len(scans)


class _CountingFrames:
    """`OnnxMatcher` whose graph calls are counted."""

    def __init__(self, inner: OnnxMatcher) -> None:
        self.inner, self.calls = inner, {"frame": 0, "encode": 0, "match": 0}
        self.path, self.cylinder, self.matching_stage = inner.path, inner.cylinder, inner.matching_stage
        self.uses_reflectance = inner.uses_reflectance

    def frame(self, image: np.ndarray, previous: Any) -> Any:
        self.calls["frame"] += 1
        return self.inner.frame(image, previous)

    def encode(self, image: np.ndarray) -> Any:
        self.calls["encode"] += 1
        return self.inner.encode(image)

    def match(self, reference: Any, target: Any) -> Any:
        self.calls["match"] += 1
        return self.inner.match(reference, target)


@pytest.mark.slow
def test_the_frame_graph_encodes_each_scan_while_matching_it(shared_data: Path, three_graphs: Path, tmp_path: Path) -> None:
    """`matching_stage` "graph": one `frame` call a scan after the first (which is encoded alone), all of it
    counted as the network; its poses those of the crate's matching stage up to float32 near-ties of the flow's argmax. A model
    with `frame.onnx` alone runs it too (without re-matching from the prediction, which needs the other graphs)."""
    scans, times = _scans(shared_data, "odometry_03")
    scans = scans[:5]
    poses = {}
    for stage in ("graph", "crate"):
        config = OdometryConfig()
        config.matching_stage = stage
        odometry = Odometry(three_graphs, config)
        counting = _CountingFrames(odometry.matcher)  # type: ignore[arg-type]
        odometry.matcher = counting
        poses[stage] = np.stack([odometry.register(points) for points in scans])
        # The first pair is also matched from two other starts (motion_model.start_check_m): the reference moved,
        # encoded and matched again, twice.
        if stage == "graph":
            assert counting.calls == {"frame": len(scans) - 1, "encode": 1 + 2, "match": 2}
            assert all("matching" not in d.timings_ms for d in odometry.diagnostics)  # the frame graph's time
        else:
            assert counting.calls == {"frame": 0, "encode": len(scans) + 2, "match": len(scans) - 1 + 2}
    np.testing.assert_allclose(poses["graph"], poses["crate"], atol=5e-3)
    (tmp_path / "frame.onnx").symlink_to(default_model_path() / "frame.onnx")
    with pytest.warns(UserWarning, match="has no encoder.onnx or match.onnx"):
        alone = Odometry(tmp_path, OdometryConfig())
    np.testing.assert_allclose(np.stack([alone.register(points) for points in scans]), poses["graph"], atol=1e-9)
    with pytest.raises(RuntimeError, match="matcher: replaced after the first scan"):
        alone.matcher = counting


@pytest.mark.slow
def test_scans_without_reflectance_switch_the_crate_to_the_range_only_model(
    shared_data: Path, tmp_path: Path
) -> None:
    """From the first scan whose reflectance is gone (zeroed from scan 5 of odometry 03 on), both odometries
    run the range-only model beside the model, the reference scan encoded again by it."""
    for folder, source in ((tmp_path, default_model_path()), (tmp_path / "range_only", default_model_path() / "range_only")):
        folder.mkdir(exist_ok=True)
        for graph in GRAPHS:
            (folder / graph).symlink_to(source / graph)
    scans, times = _scans(shared_data, "odometry_03")
    assert times is not None
    config = OdometryConfig()
    python = Odometry(tmp_path / "frame.onnx", config)
    range_only = python._range_only
    assert range_only is not None and not range_only.uses_reflectance
    crate = dmlo_rs.Odometry(python.matcher, json.dumps(config.to_dict()), range_only=range_only)
    for index, points in enumerate(scans):
        if index >= 5:
            points = points.copy()
            points[:, 3] = 0.0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ReflectanceNotice)
            expected = python.register(points, timestamp=times[index])
        got = crate.register(points, timestamp=times[index])
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12, err_msg=f"scan {index}")
    assert python.matcher is range_only and crate.reflectance_scale == "none"
    assert _without_timings(crate.diagnostics) == _without_timings(python.diagnostics)
    with pytest.raises(ValueError, match="range_only: reads the reflectance"):
        dmlo_rs.Odometry(range_only, range_only=FrameMatcherAdapter(OnnxMatcher(tmp_path / "frame.onnx")))


class _Recorder:
    """A matcher that hands its calls on to `inner`, and can be told to fail."""

    def __init__(self, inner: Any, fail_on: str | None = None) -> None:
        self.inner, self.fail_on = inner, fail_on
        self.cylinder = inner.cylinder
        self.calls: list[str] = []

    def encode(self, image: np.ndarray) -> Any:
        self.calls.append("encode")
        if self.fail_on == "encode":
            raise KeyError("encoder broke")
        return self.inner.encode(image)

    def match(self, reference: Any, target: Any) -> Any:
        self.calls.append("match")
        if self.fail_on == "match":
            raise KeyError("matcher broke")
        if self.fail_on == "shape":
            flow, confidence = self.inner.match(reference, target)
            return flow[:, :-1], confidence
        return self.inner.match(reference, target)


@pytest.fixture(scope="module")
def real_pair(shared_data: Path) -> list[np.ndarray]:
    return _scans(shared_data, "odometry_03")[0][:2]


@pytest.fixture(scope="module")
def onnx_matcher(three_graphs: Path) -> Any:
    return Odometry(three_graphs, OdometryConfig()).matcher


@pytest.mark.parametrize("fail_on", ["encode", "match"])
def test_a_matcher_that_raises_raises_through_the_crate_and_leaves_the_odometry_as_it_was(
    onnx_matcher: Any, real_pair: list[np.ndarray], fail_on: str
) -> None:
    matcher = _Recorder(onnx_matcher)
    crate = dmlo_rs.Odometry(matcher)
    crate.register(real_pair[0])
    matcher.fail_on = fail_on
    with pytest.raises(KeyError, match="broke"):
        crate.register(real_pair[1])
    assert len(crate) == 1
    matcher.fail_on = None
    pose = crate.register(real_pair[1])  # the first scan is still the reference
    assert 0.5 < np.linalg.norm(pose[:3, 3]) < 2.0 and len(crate) == 2


def test_a_matcher_that_returns_the_wrong_shape_is_named(onnx_matcher: Any, real_pair: list[np.ndarray]) -> None:
    crate = dmlo_rs.Odometry(_Recorder(onnx_matcher, fail_on="shape"))
    crate.register(real_pair[0])
    with pytest.raises(ValueError, match=r"match: flow: expected shape \(2, 64, 1792\)"):
        crate.register(real_pair[1])


def test_bad_matchers_configs_and_scans_are_named(onnx_matcher: Any, real_pair: list[np.ndarray]) -> None:
    with pytest.raises(ValueError, match="cylinder"):
        dmlo_rs.Odometry(object())
    without_match = type("NoMatch", (), {"cylinder": onnx_matcher.cylinder, "encode": lambda self, image: image})()
    with pytest.raises(ValueError, match="match"):
        dmlo_rs.Odometry(without_match)
    with pytest.raises(ValueError, match=r"ransac\.treshold"):
        dmlo_rs.Odometry(onnx_matcher, json.dumps({"ransac": {"treshold": 0.2}}))
    crate = dmlo_rs.Odometry(onnx_matcher)
    with pytest.raises(ValueError, match=r"points: expected shape \(N, 4\) or \(N, 3\)"):
        crate.register(np.zeros((10, 5), np.float32))
    # N×3 is a scan without reflectance: the crate alone refuses to run a reflectance model on it.
    with pytest.raises(ValueError, match=r"points: the scans have no reflectance \(N×3 points\).*range-only"):
        crate.register(real_pair[0][:, :3])
    with pytest.raises(TypeError, match="points"):
        crate.register(real_pair[0].astype(np.int32))
    with pytest.raises(ValueError, match="moving"):
        crate.register(real_pair[0], moving=np.zeros(3, dtype=bool))
    assert len(crate) == 0
    dark = real_pair[0].copy()
    dark[:, 3] = 0.0
    with pytest.raises(ValueError, match="every point's reflectance is 0, and the model reads reflectance"):
        crate.register(dark)
    assert len(crate) == 0
    on_zeros = dmlo_rs.Odometry(onnx_matcher, allow_zero_reflectance=True)
    on_zeros.register(dark)
    assert on_zeros.reflectance_scale == "none" and on_zeros.last_diagnostics.fallback is None
    crate.register(real_pair[0], moving=np.zeros(len(real_pair[0]), dtype=bool))
    skipped = crate.predict_skipped()
    assert crate.diagnostics[-1].fallback == "unreadable_scan" and skipped.shape == (4, 4)
