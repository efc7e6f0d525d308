"""Flow coherence (`dmlo_rs.coherent_confidence`, `matching.coherence_px`): against a numpy loop over every
cell's neighbourhood, its bad input, and what it does to the odometry's choice of matches."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import dmlo_rs
from dmlo.datasets import open_sequence
from dmlo.odometry import Odometry, OdometryConfig
from dmlo.simulator import simulate_sequence
from support import frame_to_frame


def reference(flow, confidence, ref_range, radius, scale_px, wraps):
    """The module's definition written out: per component, the median down each window column over the
    usable cells (a range, a finite flow), then the median of those column medians across the window."""
    height, width = confidence.shape
    usable = (ref_range > 0) & np.isfinite(flow).all(axis=0)
    column_median = np.full((2, height, width), np.nan)
    for row in range(height):
        rows = slice(max(row - radius, 0), min(row + radius, height - 1) + 1)
        for col in range(width):
            keep = usable[rows, col]
            if keep.any():
                column_median[:, row, col] = [np.median(flow[k, rows, col][keep]) for k in (0, 1)]
    out = np.zeros_like(confidence)
    for row in range(height):
        for col in range(width):
            if not usable[row, col]:
                continue
            cols = np.arange(col - radius, col + radius + 1)
            cols = cols % width if wraps else cols[(cols >= 0) & (cols < width)]
            medians = column_median[:, row, cols]
            medians = medians[:, ~np.isnan(medians[0])]
            centre = np.median(medians, axis=1)
            distance = np.hypot(*(flow[:, row, col] - centre))
            out[row, col] = confidence[row, col] * np.exp(-distance / scale_px)
    return out


def random_image(height: int, width: int, seed: int):
    rng = np.random.default_rng(seed)
    flow = (np.array([0.3, -2.0])[:, None, None] + rng.normal(0, 0.4, (2, height, width))).astype(np.float32)
    flow[:, rng.uniform(size=(height, width)) < 0.1] += rng.normal(0, 6, 2)[:, None]  # jumps
    flow[1, 2, 5] = np.nan  # a non-finite flow: 0 itself, ignored by its neighbours
    confidence = rng.uniform(0.05, 1, (height, width)).astype(np.float32)
    ref_range = np.where(rng.uniform(size=(height, width)) < 0.2, 0, rng.uniform(2, 60, (height, width))).astype(np.float32)
    return flow, confidence, ref_range


@pytest.mark.parametrize("radius,scale_px", [(1, 1.0), (2, 0.5), (3, 0.25)])
def test_cropped_image_matches_the_numpy_reference(radius: int, scale_px: float) -> None:
    config = dmlo_rs.CylinderConfig(height=12, width=40)  # a crop of the 360° grid: edges are edges
    flow, confidence, ref_range = random_image(12, 40, seed=radius)
    got = dmlo_rs.coherent_confidence(flow, confidence, ref_range, config, radius=radius, scale_px=scale_px)
    assert got.dtype == np.float32 and got.shape == (12, 40)
    expected = reference(flow, confidence, ref_range, radius, scale_px, wraps=False)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)
    assert got[2, 5] == 0 and (got[ref_range == 0] == 0).all()
    assert (got <= confidence + 1e-7).all()


def test_a_full_circle_wraps_its_columns() -> None:
    width = 36
    config = dmlo_rs.CylinderConfig(horizontal_resolution_deg=360 / width, height=10, width=width)
    flow, confidence, ref_range = random_image(10, width, seed=7)
    flow[0, :, -2:] += 3.0  # the seam's two last columns flow unlike the first ones
    got = dmlo_rs.coherent_confidence(flow, confidence, ref_range, config, radius=2, scale_px=0.5)
    np.testing.assert_allclose(got, reference(flow, confidence, ref_range, 2, 0.5, wraps=True), rtol=1e-5, atol=1e-6)
    cropped = reference(flow, confidence, ref_range, 2, 0.5, wraps=False)
    assert not np.allclose(got[:, :2], cropped[:, :2])  # the seam's neighbours took part


def test_bad_input_names_the_argument() -> None:
    config = dmlo_rs.CylinderConfig(height=4, width=8)
    flow, confidence, ref_range = np.zeros((2, 4, 8), np.float32), np.ones((4, 8), np.float32), np.ones((4, 8), np.float32)
    with pytest.raises(ValueError, match="flow"):
        dmlo_rs.coherent_confidence(flow[:, :3], confidence, ref_range, config)
    with pytest.raises(ValueError, match="confidence"):
        dmlo_rs.coherent_confidence(flow, confidence[:, :7], ref_range, config)
    with pytest.raises(ValueError, match="ref_range"):
        dmlo_rs.coherent_confidence(flow, confidence, ref_range.T, config)
    with pytest.raises(TypeError, match="flow"):
        dmlo_rs.coherent_confidence(flow.astype(np.int32), confidence, ref_range, config)
    with pytest.raises(ValueError, match="scale_px"):
        dmlo_rs.coherent_confidence(flow, confidence, ref_range, config, scale_px=0.0)
    largest = dmlo_rs.MAX_COHERENCE_RADIUS
    assert largest == 15
    dmlo_rs.coherent_confidence(flow, confidence, ref_range, config, radius=largest)
    with pytest.raises(ValueError, match="radius"):
        dmlo_rs.coherent_confidence(flow, confidence, ref_range, config, radius=largest + 1)


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> dict[str, np.ndarray]:
    """Two simulated scans, their true motion and its ground-truth flow."""
    out = tmp_path_factory.mktemp("drive")
    simulate_sequence(out, frames=2, seed=31, progress=False)
    sequence = open_sequence(Path(out))
    ref, tgt = sequence[0], sequence[1]
    assert ref.pose is not None and tgt.pose is not None
    odometry = Odometry.from_default(frame_to_frame())
    _, ref_range = odometry.project(ref.points)
    _, tgt_range = odometry.project(tgt.points)
    motion = np.linalg.inv(tgt.pose) @ ref.pose
    flow, valid = dmlo_rs.ground_truth_flow(ref_range, tgt_range, motion, odometry.cylinder)
    return {"ref_range": ref_range, "tgt_range": tgt_range, "flow": flow, "valid": valid}


def test_the_odometry_keeps_coherent_matches_over_confident_jumps(pair: dict[str, np.ndarray]) -> None:
    # The true flow with 4000 scattered cells thrown 5 px off and given the highest confidence: the
    # network's confidently wrong matches. Without coherence NMS keeps them first.
    rng = np.random.default_rng(0)
    flow, valid = pair["flow"].copy(), pair["valid"]
    cells = np.flatnonzero(valid)
    wrong = rng.choice(cells, 4000, replace=False)
    rows, cols = np.unravel_index(wrong, valid.shape)
    flow[0, rows, cols] += 5.0
    confidence = np.where(valid, 0.5, 0.0).astype(np.float32)
    confidence[rows, cols] = 1.0
    is_wrong = np.zeros(valid.shape, bool)
    is_wrong[rows, cols] = True

    def wrong_share(coherence_px: float | None) -> float:
        config = frame_to_frame()
        config.matching.coherence_px = coherence_px
        odometry = Odometry.from_default(config)
        weighted = confidence if coherence_px is None else dmlo_rs.coherent_confidence(
            flow, confidence, pair["ref_range"], odometry.cylinder, scale_px=coherence_px)
        matches = dmlo_rs.decode_matches(
            pair["ref_range"], pair["tgt_range"], flow, weighted, odometry.cylinder, top_n=config.matching.max_matches
        )
        # The odometry's back end chose exactly these matches.
        result = odometry.pose_from_flow(pair["ref_range"], pair["tgt_range"], flow, confidence)
        np.testing.assert_array_equal(result.source_points, matches.source)
        return float(is_wrong[matches.cells[:, 0], matches.cells[:, 1]].mean())

    assert wrong_share(None) > 0.9
    assert wrong_share(0.5) < 0.05


def test_settings_are_checked() -> None:
    for name, value in (("coherence_px", 0.0), ("coherence_px", -1.0), ("coherence_radius", -1), ("coherence_radius", 16), ("coherence_radius", 1.5)):
        config = frame_to_frame()
        setattr(config.matching, name, value)
        with pytest.raises(ValueError, match=f"matching.{name}"):
            Odometry.from_default(config)
    assert OdometryConfig().matching.coherence_px is not None  # on by default
