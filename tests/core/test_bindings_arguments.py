"""Integer arguments of `dmlo_rs` out of range are refused by name: a negative count, a seed beyond 64 bits,
a thread count of zero or of a million, any integer beyond 64 or 128 bits — never pyo3's unnamed
`OverflowError`."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

import dmlo_rs

KITTI = dmlo_rs.CylinderConfig.kitti()
RANGE = np.full((KITTI.height, KITTI.width), 10.0, np.float32)
FLOW = np.zeros((2, KITTI.height, KITTI.width), np.float32)
CONFIDENCE = np.ones((KITTI.height, KITTI.width), np.float32)
POINTS = np.random.default_rng(0).normal(size=(50, 3))
SCAN = np.column_stack([np.random.default_rng(1).uniform(-30, 30, (200, 3)), np.zeros(200)]).astype(np.float32)
FEATURES = [np.zeros((1, 32, 4, 8), np.float32), np.zeros((1, 8, 16, 64), np.float32)] * 2
MATCH = dict(coarse_window=5, refine_window=3, coarse_scale=10.0, refine_scale=10.0)


def nms(**kw: Any) -> Any:
    return dmlo_rs.nms(np.zeros(3, np.int64), np.arange(3), np.ones(3, np.float32), **kw)


def ransac(**kw: Any) -> Any:
    return dmlo_rs.ransac_rigid(POINTS, POINTS, **kw)


def decode(**kw: Any) -> Any:
    return dmlo_rs.decode_matches(RANGE, RANGE, FLOW, CONFIDENCE, KITTI, **kw)


def coherence(**kw: Any) -> Any:
    return dmlo_rs.coherent_confidence(FLOW, CONFIDENCE, RANGE, KITTI, **kw)


def align(**kw: Any) -> Any:
    return dmlo_rs.NdtMap().align(POINTS, np.eye(4), **kw)


def match(**kw: Any) -> Any:
    return dmlo_rs.match_features(*FEATURES, **{**MATCH, **kw})


CASES: list[tuple[Callable[..., Any], dict[str, Any], str]] = [
    (nms, {"radius": -1}, "radius: must be >= 0, got -1"),
    (nms, {"top_n": -5}, "top_n: must be >= 0, got -5"),
    (ransac, {"max_iterations": -1}, "max_iterations: must be >= 0"),
    (ransac, {"refine_iterations": -2}, "refine_iterations: must be >= 0"),
    (ransac, {"seed": -1}, "seed: must be in 0 ..= 2^64 - 1, got -1"),
    (ransac, {"seed": 2**64}, "seed: must be in 0 ..= 2^64 - 1"),
    (ransac, {"num_threads": -1}, "num_threads: must be >= 1 (or None for all cores), got -1"),
    (ransac, {"num_threads": 0}, "num_threads: must be >= 1"),
    (ransac, {"num_threads": 10**6}, "num_threads: at most 1024"),
    (decode, {"top_n": -1}, "top_n: must be >= 0"),
    (decode, {"nms_radius": -1}, "nms_radius: must be >= 0"),
    (coherence, {"radius": -3}, "radius: must be >= 0"),
    (lambda **kw: dmlo_rs.CylinderConfig(**kw), {"height": -64}, "height: must be >= 0"),
    (lambda **kw: dmlo_rs.CylinderConfig(**kw), {"width": -1}, "width: must be >= 0"),
    (lambda **kw: dmlo_rs.NdtMap(**kw), {"max_scans": -1}, "max_scans: must be >= 0"),
    (lambda **kw: dmlo_rs.NdtMap(**kw), {"min_points_per_voxel": -1}, "min_points_per_voxel: must be >= 0"),
    (align, {"max_iterations": -1}, "max_iterations: must be >= 0"),
    (align, {"min_correspondences": -1}, "min_correspondences: must be >= 0"),
    (lambda **kw: dmlo_rs.lidar_scan_directions(np.zeros(4), **kw), {"azimuth_count": -1}, "azimuth_count: must be >= 0"),
    (match, {"coarse_window": -3}, "coarse_window: must be >= 0"),
    (match, {"stride": (-4, 8)}, "stride: must be >= 0"),
    (lambda **kw: dmlo_rs.project(SCAN, KITTI, **kw), {"num_threads": -2}, "num_threads: must be >= 1"),
]


def scan_directions(**kw: Any) -> Any:
    return dmlo_rs.lidar_scan_directions(np.zeros(4), **kw)


# Every integer argument of the bindings, with a call that reaches its check.
INTEGER_ARGUMENTS: list[tuple[Callable[..., Any], str]] = [
    (nms, "radius"),
    (nms, "top_n"),
    (ransac, "max_iterations"),
    (ransac, "refine_iterations"),
    (ransac, "num_threads"),
    (lambda **kw: dmlo_rs.ray_noise_refit(POINTS, POINTS, np.eye(4), **kw), "max_iterations"),
    (decode, "top_n"),
    (decode, "nms_radius"),
    (decode, "num_threads"),
    (coherence, "radius"),
    (coherence, "num_threads"),
    (lambda **kw: dmlo_rs.CylinderConfig(**kw), "height"),
    (lambda **kw: dmlo_rs.CylinderConfig(**kw), "width"),
    (lambda **kw: dmlo_rs.NdtMap(**kw), "max_scans"),
    (lambda **kw: dmlo_rs.NdtMap(**kw), "min_points_per_voxel"),
    (lambda **kw: dmlo_rs.NdtMap().insert(POINTS, **kw), "num_threads"),
    (align, "max_iterations"),
    (align, "min_correspondences"),
    (align, "num_threads"),
    (scan_directions, "azimuth_count"),
    (match, "coarse_window"),
    (match, "refine_window"),
    (match, "num_threads"),
    (lambda **kw: dmlo_rs.project(SCAN, KITTI, **kw), "num_threads"),
    (lambda **kw: dmlo_rs.ground_truth_flow(RANGE, RANGE, np.eye(4), KITTI, **kw), "num_threads"),
    (lambda **kw: dmlo_rs.sweep_times(SCAN, **kw), "num_threads"),
    (lambda **kw: dmlo_rs.deskew(SCAN, np.eye(4), **kw), "num_threads"),
    (lambda **kw: dmlo_rs.NdtMap().insert_scan(POINTS, np.eye(4), **kw), "num_threads"),
]
for _call, _name in INTEGER_ARGUMENTS:
    for _huge in (2**64, 2**127, 2**200, -(2**63) - 1, -(2**200)):  # beyond what any count or seed holds
        CASES.append((_call, {_name: _huge}, f"{_name}: "))
CASES += [
    (ransac, {"seed": 2**200}, f"seed: must be in 0 ..= 2^64 - 1, got {2**200}"),
    (ransac, {"seed": -(2**200)}, "seed: must be in 0 ..= 2^64 - 1"),
    (match, {"stride": (2**64, 8)}, "stride: must be at most"),
    (nms, {"radius": 2**70}, f"radius: must be at most {2**64 - 1}, got {2**70}"),
    (nms, {"radius": -(2**70)}, f"radius: must be >= 0, got {-(2**70)}"),
    (ransac, {"num_threads": 2**63}, f"num_threads: at most 1024, got {2**63}"),
    (ransac, {"num_threads": 2**200}, f"num_threads: at most 1024, got {2**200}"),
    (ransac, {"num_threads": -(2**200)}, "num_threads: must be >= 1"),
]


@pytest.mark.parametrize(("call", "arguments", "message"), CASES)
def test_out_of_range_integers_are_refused_by_name(call: Callable[..., Any], arguments: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError) as raised:
        call(**arguments)
    assert message in str(raised.value)
    assert type(raised.value) is ValueError  # not a RegistrationError, nor pyo3's OverflowError


def test_a_float_where_an_int_belongs_names_the_argument() -> None:
    with pytest.raises(TypeError, match="argument 'radius'"):
        nms(radius=1.5)
    with pytest.raises(TypeError, match="argument 'num_threads'"):
        ransac(num_threads=2.0)
    with pytest.raises(TypeError, match="argument 'seed'"):
        ransac(seed="1")


def test_integer_defaults_show_in_the_signatures() -> None:
    import inspect

    assert inspect.signature(dmlo_rs.nms).parameters["radius"].default == 1
    assert inspect.signature(dmlo_rs.ransac_rigid).parameters["seed"].default == 0
    assert inspect.signature(dmlo_rs.CylinderConfig).parameters["width"].default == 1792


def test_valid_integers_still_pass() -> None:
    assert len(nms(radius=0, top_n=2)) == 2
    assert len(nms(radius=np.int64(1), top_n=np.uint8(2))) == 2  # numpy integers are integers too
    assert len(nms(radius=True)) >= 1
    assert len(nms(radius=0, top_n=2**63)) == 3  # a count beyond i64 but within usize is still a count
    assert ransac(seed=2**64 - 1, num_threads=1).num_inliers == len(POINTS)
    flow, _ = match(stride=(4, 8), num_threads=1)
    assert flow.shape == (2, 16, 64)
