"""The crate's per-frame odometry (`dmlo_rs.Odometry`, `odometry::pipeline` in Rust) run on Python's own
matcher (onnxruntime behind the crate's `FrameMatcher` trait) gives `dmlo.Odometry`'s poses and diagnostics
exactly, on every real KITTI drive of `../shared/data/kitti_real`, with mapping and frame to frame — the same
network outputs on both sides, so no RANSAC inlier can flip between them (as it does between tract's and
onnxruntime's features, `docs/measurements.md`). The model folder holds the three graphs the crate's loop runs
(no moving-object network, no wide-window graph)."""

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
from dmlo.odometry.matcher import CrateMatcher, OnnxMatcher, default_model_path
from dmlo.odometry.reflectance import ReflectanceNotice

GRAPHS = ("encoder.onnx", "frame.onnx", "match.onnx")
REAL_SETS = ("odometry_01", "odometry_02", "odometry_03", "raw_drive_22")


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


def _without_timings(diagnostics: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{key: value for key, value in d.items() if key != "timings_ms"} for d in diagnostics]


@pytest.mark.slow
@pytest.mark.parametrize("mapping", [True, False], ids=["mapping", "frame_to_frame"])
@pytest.mark.parametrize("name", REAL_SETS)
def test_the_crate_odometry_on_pythons_matcher_equals_dmlo_odometry(
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
        # Both chain the same motions; only the order of the float64 products differs.
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12, err_msg=f"{name} scan {index}")
    np.testing.assert_allclose(crate.poses, np.stack(python.poses), rtol=0, atol=1e-12)
    assert _without_timings(crate.diagnostics) == _without_timings([d.to_dict() for d in python.diagnostics])
    assert crate.reflectance_scale == "unit" and len(crate) == len(scans)


@pytest.fixture(scope="module")
def with_wide_window(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("model_wide")
    for graph in (*GRAPHS, "frame_wide.onnx"):
        (folder / graph).symlink_to(default_model_path() / graph)
    return folder / "frame.onnx"


@pytest.mark.slow
@pytest.mark.parametrize("mapping", [True, False], ids=["mapping", "frame_to_frame"])
def test_across_missing_scans_the_crate_rematches_with_the_wide_window_as_dmlo_odometry(
    shared_data: Path, with_wide_window: Path, mapping: bool
) -> None:
    """Scans 4–6 of odometry 03 dropped (their timestamps tell the gap): both odometries match the pair across
    the gap again from the prediction, with the model's own window and the wide one, and keep the same."""
    scans, times = _scans(shared_data, "odometry_03")
    assert times is not None
    kept = [0, 1, 2, 3, 7, 8, 9]
    config = OdometryConfig()
    config.mapping.enabled = mapping
    python = Odometry(with_wide_window, config)
    matcher = CrateMatcher(python.matcher)
    wide_calls: list[int] = []
    wide_match = matcher.wide_match
    matcher.wide_match = lambda reference, image: wide_calls.append(1) or wide_match(reference, image)
    crate = dmlo_rs.Odometry(matcher, json.dumps(config.to_dict()))
    for index in kept:
        expected = python.register(scans[index], timestamp=times[index])
        got = crate.register(scans[index], timestamp=times[index])
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12, err_msg=f"scan {index}")
    diagnostics = _without_timings(crate.diagnostics)
    assert diagnostics == _without_timings([d.to_dict() for d in python.diagnostics])
    assert diagnostics[4]["gap"] == 4 and diagnostics[4]["rematch_rounds"] is not None and wide_calls


@pytest.mark.slow
@pytest.mark.parametrize("mapping", [True, False], ids=["mapping", "frame_to_frame"])
def test_deskewed_sweeps_are_the_same_in_the_crate(shared_data: Path, three_graphs: Path, mapping: bool) -> None:
    """The raw drive's sweeps (not motion-compensated) deskewed by the measured velocity, from the third scan
    on (its reference deskewed and encoded again then), sweep times from the azimuths or given."""
    scans, _ = _scans(shared_data, "raw_drive_22")
    scans = scans[:8]
    config = OdometryConfig()
    config.mapping.enabled = mapping
    config.deskew.enabled = True
    python = Odometry(three_graphs, config)
    crate = dmlo_rs.Odometry(python.matcher, json.dumps(config.to_dict()))
    for index, points in enumerate(scans):
        # Given times on the odd scans: the azimuth's, scaled a little so that they differ from the derived.
        times = None
        if index % 2:
            azimuth = np.arctan2(points[:, 1], points[:, 0])
            times = (-azimuth / (2 * np.pi) * 0.9).astype(np.float64)
        expected = python.register(points, point_times=times)
        got = crate.register(points, point_times=times)
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12, err_msg=f"scan {index}")
    diagnostics = _without_timings(crate.diagnostics)
    assert diagnostics == _without_timings([d.to_dict() for d in python.diagnostics])
    assert [d["deskewed"] for d in diagnostics] == [False, False] + [True] * (len(scans) - 2)
    with pytest.raises(ValueError, match="point_times"):
        crate.register(scans[0], point_times=np.zeros(3))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["odometry_01", "raw_drive_22"])
def test_symmetric_matching_is_the_same_in_the_crate(shared_data: Path, three_graphs: Path, name: str) -> None:
    """`matching.symmetric`: every pair matched both ways, the round-trip check leaving cells out, the two
    motions' midpoint."""
    scans, times = _scans(shared_data, name)
    config = OdometryConfig()
    config.mapping.enabled = False
    config.matching.symmetric = True
    python = Odometry(three_graphs, config)
    crate = dmlo_rs.Odometry(python.matcher, json.dumps(config.to_dict()))
    for index, points in enumerate(scans[:10]):
        timestamp = None if times is None else times[index]
        expected = python.register(points, timestamp=timestamp)
        got = crate.register(points, timestamp=timestamp)
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12, err_msg=f"scan {index}")
    diagnostics = _without_timings(crate.diagnostics)
    assert diagnostics == _without_timings([d.to_dict() for d in python.diagnostics])
    assert all(d["backward_inliers"] for d in diagnostics[1:])


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
    assert _without_timings(crate.diagnostics) == _without_timings([d.to_dict() for d in python.diagnostics])
    with pytest.raises(ValueError, match="range_only: reads the reflectance"):
        dmlo_rs.Odometry(range_only, range_only=CrateMatcher(OnnxMatcher(tmp_path / "frame.onnx")))


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
    with pytest.raises(ValueError, match=r"points: expected shape \(N, 4\)"):
        crate.register(real_pair[0][:, :3])
    with pytest.raises(TypeError, match="points"):
        crate.register(real_pair[0].astype(np.int32))
    with pytest.raises(ValueError, match="moving"):
        crate.register(real_pair[0], moving=np.zeros(3, dtype=bool))
    assert len(crate) == 0
    crate.register(real_pair[0], moving=np.zeros(len(real_pair[0]), dtype=bool))
    skipped = crate.predict_skipped()
    assert crate.diagnostics[-1]["fallback"] == "unreadable_scan" and skipped.shape == (4, 4)
