"""Rigid solve, RANSAC, NMS and match decoding through the Python API, against scipy/numpy references."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import dmlo_rs
from dmlo_rs import CylinderConfig


def random_transform(rng: np.random.Generator, angle_scale: float = 1.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * angle_scale).as_matrix()
    T[:3, 3] = rng.normal(size=3) * 3
    return T


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def rotation_error_deg(A: np.ndarray, B: np.ndarray) -> float:
    cos = (np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))))


def motion_scene(rng: np.random.Generator, n: int, outlier_ratio: float, noise: float = 0.02):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [2.5, 0.3, -0.2], degrees=True).as_matrix()
    T[:3, 3] = [0.9, -0.05, 0.02]
    src = rng.uniform([-40, -40, -2], [40, 40, 3], size=(n, 3))
    dst = apply(T, src) + rng.normal(scale=noise, size=(n, 3))
    outliers = rng.random(n) < outlier_ratio
    dst[outliers] = rng.uniform([-40, -40, -2], [40, 40, 3], size=(int(outliers.sum()), 3))
    return src, dst, T, ~outliers


# ---- rigid_transform -----------------------------------------------------------------------------


def test_rigid_transform_equals_scipy_align_vectors_on_noisy_weighted_data() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        T = random_transform(rng)
        src = rng.normal(size=(50, 3)) * 10
        dst = apply(T, src) + rng.normal(scale=0.05, size=(50, 3))
        weights = rng.uniform(0.1, 2.0, size=50)
        estimate = dmlo_rs.rigid_transform(src, dst, weights)
        assert estimate.shape == (4, 4) and estimate.dtype == np.float64
        p_mean = np.average(src, axis=0, weights=weights)
        q_mean = np.average(dst, axis=0, weights=weights)
        reference, _ = Rotation.align_vectors(dst - q_mean, src - p_mean, weights=weights)
        np.testing.assert_allclose(estimate[:3, :3], reference.as_matrix(), atol=1e-9)
        np.testing.assert_allclose(estimate[:3, 3], q_mean - reference.as_matrix() @ p_mean, atol=1e-9)
        np.testing.assert_array_equal(estimate[3], [0, 0, 0, 1])


def test_rigid_transform_is_exact_without_noise_and_accepts_float32_and_strided_input() -> None:
    rng = np.random.default_rng(1)
    T = random_transform(rng)
    src = rng.normal(size=(200, 3)) * 10
    dst = apply(T, src)
    np.testing.assert_allclose(dmlo_rs.rigid_transform(src, dst), T, atol=1e-10)
    np.testing.assert_allclose(dmlo_rs.rigid_transform(src[::2], dst[::2]), T, atol=1e-10)
    np.testing.assert_allclose(
        dmlo_rs.rigid_transform(src.astype(np.float32), dst.astype(np.float32)), T, atol=1e-4
    )


def test_rigid_transform_bad_input() -> None:
    good = np.random.default_rng(2).normal(size=(10, 3))
    with pytest.raises(dmlo_rs.RegistrationError, match="at least 3"):
        dmlo_rs.rigid_transform(good[:2], good[:2])
    line = np.outer(np.arange(10.0), [1.0, 2.0, 3.0])
    with pytest.raises(dmlo_rs.RegistrationError, match="degenerate"):
        dmlo_rs.rigid_transform(line, line)
    with pytest.raises(TypeError, match="src"):
        dmlo_rs.rigid_transform(good.astype(np.int64), good)
    with pytest.raises(ValueError, match="dst"):
        dmlo_rs.rigid_transform(good, good[:, :2])
    with pytest.raises(ValueError, match="dst"):
        dmlo_rs.rigid_transform(good, good[:5])
    bad = good.copy()
    bad[4, 1] = np.inf
    with pytest.raises(ValueError, match="src"):
        dmlo_rs.rigid_transform(bad, good)
    with pytest.raises(ValueError, match="weights"):
        dmlo_rs.rigid_transform(good, good, np.ones(3))
    with pytest.raises(ValueError, match="weights"):
        dmlo_rs.rigid_transform(good, good, -np.ones(10))


def test_rigid_transform_judges_degeneracy_by_shape_not_scale() -> None:
    rng = np.random.default_rng(17)
    T = random_transform(rng)
    src = rng.normal(size=(30, 3)) * 10
    dst = apply(T, src)
    for scale in (1e-100, 1e100):
        estimate = dmlo_rs.rigid_transform(src * scale, dst * scale)
        np.testing.assert_allclose(estimate[:3, :3], T[:3, :3], atol=1e-9)
        np.testing.assert_allclose(estimate[:3, 3] / scale, T[:3, 3], atol=1e-9)
        line = np.outer(np.arange(10.0), [1.0, 2.0, 3.0]) * scale
        with pytest.raises(dmlo_rs.RegistrationError, match="collinear"):
            dmlo_rs.rigid_transform(line, line)


# ---- ransac_rigid --------------------------------------------------------------------------------


@pytest.mark.parametrize("n, outlier_ratio", [(500, 0.5), (2000, 0.8)])
def test_ransac_recovers_a_known_motion(n: int, outlier_ratio: float) -> None:
    rng = np.random.default_rng(3)
    src, dst, T, is_inlier = motion_scene(rng, n, outlier_ratio)
    result = dmlo_rs.ransac_rigid(src, dst, threshold=0.1, confidence=0.999, max_iterations=1000, seed=5)
    assert rotation_error_deg(result.transform, T) < 0.05
    assert np.linalg.norm(result.transform[:3, 3] - T[:3, 3]) < 0.02
    assert result.inliers.dtype == np.bool_ and result.inliers.shape == (n,)
    assert result.num_inliers == int(result.inliers.sum())
    # Noise of 2 cm per axis: a few true inliers fall beyond 0.1 m only rarely.
    assert np.mean(result.inliers == is_inlier) > 0.99
    assert 0 < result.iterations <= 1000
    assert 0 < result.rmse < 0.1
    assert "RansacResult(" in repr(result)


def test_ransac_is_deterministic_whatever_the_thread_count() -> None:
    src, dst, _, _ = motion_scene(np.random.default_rng(4), 1500, 0.7, noise=0.05)
    one = dmlo_rs.ransac_rigid(src, dst, seed=11, num_threads=1)
    two = dmlo_rs.ransac_rigid(src, dst, seed=11, num_threads=2)
    four = dmlo_rs.ransac_rigid(src, dst, seed=11, num_threads=4)
    for other in (two, four):
        np.testing.assert_array_equal(one.transform, other.transform)
        np.testing.assert_array_equal(one.inliers, other.inliers)
        assert one.iterations == other.iterations


def test_ransac_with_no_consistent_motion_or_too_few_matches() -> None:
    rng = np.random.default_rng(5)
    src = rng.uniform(-40, 40, size=(300, 3))
    dst = rng.uniform(-40, 40, size=(300, 3))
    # No motion tried fits even its own sample within the threshold: an error (the odometry takes it as a
    # pair without motion), not a result with an empty consensus.
    with pytest.raises(dmlo_rs.RegistrationError, match="threshold"):
        dmlo_rs.ransac_rigid(src, dst, max_iterations=300)
    # With a few chance inliers the result stands and callers judge it (the odometry falls back).
    result = dmlo_rs.ransac_rigid(src, dst, threshold=2.0, max_iterations=300)
    assert 1 <= result.num_inliers < 10
    assert result.iterations == 300
    with pytest.raises(dmlo_rs.RegistrationError, match="at least 3"):
        dmlo_rs.ransac_rigid(src[:2], dst[:2])
    with pytest.raises(dmlo_rs.RegistrationError, match="at least 3"):
        dmlo_rs.ransac_rigid(np.zeros((0, 3)), np.zeros((0, 3)))
    line = np.outer(np.arange(20.0), [1.0, 0.5, 0.0])
    with pytest.raises(dmlo_rs.RegistrationError, match="collinear"):
        dmlo_rs.ransac_rigid(line, line)
    # A wrong setting is a plain ValueError: the odometry must not mistake it for a pair with no motion.
    with pytest.raises(ValueError, match="threshold") as refused:
        dmlo_rs.ransac_rigid(src, dst, threshold=-0.1)
    assert not isinstance(refused.value, dmlo_rs.RegistrationError)
    with pytest.raises(ValueError, match="confidence"):
        dmlo_rs.ransac_rigid(src, dst, confidence=1.5)
    with pytest.raises(TypeError, match="dst"):
        dmlo_rs.ransac_rigid(src, dst.astype(np.int32))


@pytest.mark.parametrize("offset", [1e6, 5e6, 1e7])
def test_ransac_counts_inliers_exactly_far_from_the_origin(offset: float) -> None:
    # UTM-like coordinates: the scene and its motion shifted millions of metres give the consensus they
    # give near the origin.
    shift = np.array([offset, -0.7 * offset, 35.0])
    rng = np.random.default_rng(18)
    exact_src, exact_dst, T, _ = motion_scene(rng, 200, 0.0, noise=0.0)
    exact = dmlo_rs.ransac_rigid(exact_src + shift, exact_dst + shift)
    assert exact.num_inliers == 200 and exact.iterations < 10
    src, dst, T, is_inlier = motion_scene(rng, 200, 0.3)
    near = dmlo_rs.ransac_rigid(src, dst)
    far = dmlo_rs.ransac_rigid(src + shift, dst + shift)
    np.testing.assert_array_equal(far.inliers, near.inliers)
    assert np.mean(far.inliers == is_inlier) > 0.99
    assert rotation_error_deg(far.transform, T) < 0.05
    # The far motion moves the shifted points as the true motion moves the original ones.
    moved = apply(far.transform, src + shift) - shift
    assert np.abs(moved - apply(T, src)).max() < 0.03
    assert abs(far.rmse - near.rmse) < 1e-6
    threaded = dmlo_rs.ransac_rigid(src + shift, dst + shift, num_threads=2)
    np.testing.assert_array_equal(threaded.transform, far.transform)


def test_ransac_without_any_inlier_raises_instead_of_an_empty_consensus() -> None:
    rng = np.random.default_rng(19)
    src = rng.uniform(-40, 40, size=(100, 3))
    dst = rng.uniform(-40, 40, size=(100, 3))
    with pytest.raises(dmlo_rs.RegistrationError, match="threshold"):
        dmlo_rs.ransac_rigid(src, dst, threshold=1e-9, max_iterations=50)


# ---- nms -----------------------------------------------------------------------------------------


def reference_nms(
    rows: np.ndarray, cols: np.ndarray, scores: np.ndarray, radius: int, top_n: int, period: int | None = None
) -> list[int]:
    """Greedy NMS by pairwise checks; with a period the column distance is the shorter way round."""

    def column_distance(a: int, b: int) -> int:
        if period is None:
            return abs(a - b)
        d = (a - b) % period
        return min(d, period - d)

    order = sorted(range(len(scores)), key=lambda i: (-scores[i], i))
    kept: list[int] = []
    for i in order:
        if len(kept) == top_n:
            break
        if all(abs(rows[k] - rows[i]) > radius or column_distance(cols[k], cols[i]) > radius for k in kept):
            kept.append(i)
    return kept


FULL_RING = CylinderConfig(height=68, width=1801)  # KITTI's uncropped 360° grid: columns wrap every 1800


def test_nms_wraps_across_the_seam_of_a_360_image() -> None:
    rng = np.random.default_rng(16)
    # Entries crowd both edges of the full ring (column 1800 is column 0 again) and the middle.
    rows = rng.integers(0, 68, 1500)
    cols = np.concatenate([rng.integers(0, 4, 500), rng.integers(1796, 1801, 500), rng.integers(0, 1801, 500)])
    scores = rng.integers(0, 25, 1500).astype(np.float32) / 25
    for radius, top_n in [(1, 1500), (2, 300), (0, 1500)]:
        kept = dmlo_rs.nms(rows, cols, scores, radius, top_n, config=FULL_RING)
        assert kept.tolist() == reference_nms(rows, cols, scores, radius, top_n, period=1800)
        # Without the config (or with a cropped one) the seam does not suppress.
        assert dmlo_rs.nms(rows, cols, scores, radius, top_n).tolist() == reference_nms(rows, cols, scores, radius, top_n)
    kitti = CylinderConfig.kitti()
    inside = (cols < kitti.width) & (rows < kitti.height)
    plain = dmlo_rs.nms(rows[inside], cols[inside], scores[inside], 1, 500)
    np.testing.assert_array_equal(dmlo_rs.nms(rows[inside], cols[inside], scores[inside], 1, 500, config=kitti), plain)


def test_nms_with_a_config_rejects_cells_outside_its_image() -> None:
    kitti = CylinderConfig.kitti()
    one = np.zeros(1, np.float32)
    with pytest.raises(ValueError, match="cols"):
        dmlo_rs.nms(np.zeros(1, np.int64), np.array([1792]), one, config=kitti)
    with pytest.raises(ValueError, match="rows"):
        dmlo_rs.nms(np.array([64]), np.zeros(1, np.int64), one, config=kitti)
    with pytest.raises(TypeError):
        dmlo_rs.nms(np.zeros(1, np.int64), np.zeros(1, np.int64), one, config="kitti")  # type: ignore[arg-type]


def test_nms_equals_the_greedy_reference() -> None:
    rng = np.random.default_rng(6)
    for radius in (0, 1, 2):
        rows = rng.integers(0, 16, 800)
        cols = rng.integers(0, 64, 800)
        scores = rng.integers(0, 30, 800).astype(np.float32) / 30  # ties on purpose
        for top_n in (5, 100, 800):
            kept = dmlo_rs.nms(rows, cols, scores, radius, top_n)
            assert kept.dtype == np.int64
            assert kept.tolist() == reference_nms(rows, cols, scores, radius, top_n)


def test_nms_on_a_full_confidence_map_keeps_separated_local_maxima() -> None:
    rng = np.random.default_rng(7)
    confidence = rng.random((64, 1792)).astype(np.float32)
    rows, cols = np.indices(confidence.shape)
    kept = dmlo_rs.nms(rows.ravel(), cols.ravel(), confidence.ravel(), radius=1, top_n=1000)
    assert len(kept) == 1000
    kept_scores = confidence.ravel()[kept]
    assert (np.diff(kept_scores) <= 0).all()
    r, c = rows.ravel()[kept], cols.ravel()[kept]
    close = (np.abs(r[:, None] - r[None]) <= 1) & (np.abs(c[:, None] - c[None]) <= 1)
    assert close.sum() == len(kept)  # only each entry with itself
    # The global maximum is always kept first.
    assert kept[0] == int(np.argmax(confidence))


def test_nms_bad_input() -> None:
    with pytest.raises(ValueError, match="cols"):
        dmlo_rs.nms(np.zeros(3, np.int64), np.zeros(2, np.int64), np.zeros(3, np.float32))
    with pytest.raises(ValueError, match="scores"):
        dmlo_rs.nms(np.zeros(1, np.int64), np.zeros(1, np.int64), np.array([np.nan], np.float32))
    with pytest.raises(TypeError, match="rows"):
        dmlo_rs.nms(np.zeros(1), np.zeros(1, np.int64), np.zeros(1, np.float32))
    with pytest.raises(ValueError, match="rows"):
        dmlo_rs.nms(np.array([-1]), np.zeros(1, np.int64), np.zeros(1, np.float32))
    assert len(dmlo_rs.nms(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))) == 0


# ---- decode_matches ------------------------------------------------------------------------------


def project_moved_static_scan(shared_data: Path, T: np.ndarray, config: CylinderConfig):
    """A real KITTI scan of a standing car and its copy moved by T, both projected with `config`."""
    path = shared_data / "kitti_raw_static" / "0000000000.bin"
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    scan = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    moved = scan.copy()
    moved[:, :3] = apply(T, scan[:, :3].astype(np.float64)).astype(np.float32)
    return dmlo_rs.project(scan, config), dmlo_rs.project(moved, config)


@pytest.fixture(scope="module")
def moved_pair(shared_data: Path):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 2.0, degrees=True).as_matrix()
    T[:3, 3] = [-0.8, 0.1, 0.0]
    config = CylinderConfig.kitti()
    return (*project_moved_static_scan(shared_data, T, config), T, config)


def test_decoding_ground_truth_flow_gives_matches_consistent_with_the_motion(moved_pair) -> None:
    ref, tgt, T, config = moved_pair
    flow, valid = dmlo_rs.ground_truth_flow(ref.range, tgt.range, T, config)
    confidence = valid.astype(np.float32) * np.random.default_rng(8).uniform(0.5, 1.0, valid.shape).astype(np.float32)
    matches = dmlo_rs.decode_matches(ref.range, tgt.range, flow, confidence, config, min_confidence=0.5)
    assert len(matches) == int(valid.sum())
    assert matches.source.shape == (len(matches), 3) and matches.cells.dtype == np.int64
    np.testing.assert_array_equal(matches.confidence, confidence[matches.cells[:, 0], matches.cells[:, 1]])
    # p'_r is the cell centre at the reference range.
    np.testing.assert_allclose(
        np.linalg.norm(matches.source, axis=1), ref.range[matches.cells[:, 0], matches.cells[:, 1]], rtol=1e-6
    )
    # p̂_t sits where T puts p'_r, up to the target's own surface sampling (mostly within 0.1 m).
    error = np.linalg.norm(apply(T, matches.source) - matches.target, axis=1)
    assert np.median(error) < 0.05
    assert np.mean(error < 0.1) > 0.75
    # The full pipeline recovers the motion: NMS then RANSAC.
    keep = dmlo_rs.nms(matches.cells[:, 0], matches.cells[:, 1], matches.confidence, 1, 2000)
    result = dmlo_rs.ransac_rigid(matches.source[keep], matches.target[keep], seed=1)
    assert rotation_error_deg(result.transform, T) < 0.05
    assert np.linalg.norm(result.transform[:3, 3] - T[:3, 3]) < 0.03


def test_fused_nms_equals_decoding_then_nms(moved_pair) -> None:
    ref, tgt, T, config = moved_pair
    flow, valid = dmlo_rs.ground_truth_flow(ref.range, tgt.range, T, config)
    rng = np.random.default_rng(9)
    flow += rng.normal(scale=2.0, size=flow.shape).astype(np.float32)  # some land on holes or outside
    confidence = (rng.integers(0, 10, valid.shape) / 10).astype(np.float32)  # ties on purpose
    everything = dmlo_rs.decode_matches(ref.range, tgt.range, flow, confidence, config, 0.2)
    for radius, top_n in [(1, 1000), (2, 200)]:
        keep = dmlo_rs.nms(everything.cells[:, 0], everything.cells[:, 1], everything.confidence, radius, top_n)
        fused = dmlo_rs.decode_matches(ref.range, tgt.range, flow, confidence, config, 0.2, top_n=top_n, nms_radius=radius)
        np.testing.assert_array_equal(fused.cells, everything.cells[keep])
        np.testing.assert_array_equal(fused.source, everything.source[keep])
        np.testing.assert_array_equal(fused.target, everything.target[keep])


def test_fused_nms_equals_decoding_then_nms_on_a_360_image(shared_data: Path) -> None:
    """On the full ring the fused NMS suppresses across the azimuth seam, like nms(..., config=...)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 1.0, degrees=True).as_matrix()
    config = FULL_RING
    ref, tgt = project_moved_static_scan(shared_data, T, config)
    flow, valid = dmlo_rs.ground_truth_flow(ref.range, tgt.range, T, config)
    rng = np.random.default_rng(19)
    flow += rng.normal(scale=1.0, size=flow.shape).astype(np.float32)
    confidence = (rng.integers(0, 10, valid.shape) / 10).astype(np.float32)
    # The best confidences sit right at the seam, so the wrap decides what survives there.
    confidence[:, :2] = 1.0
    confidence[:, -3:] = 1.0
    everything = dmlo_rs.decode_matches(ref.range, tgt.range, flow, confidence, config, 0.2)
    for radius, top_n in [(1, 1000), (2, 300)]:
        keep = dmlo_rs.nms(everything.cells[:, 0], everything.cells[:, 1], everything.confidence, radius, top_n,
                           config=config)
        fused = dmlo_rs.decode_matches(ref.range, tgt.range, flow, confidence, config, 0.2, top_n=top_n,
                                       nms_radius=radius)
        np.testing.assert_array_equal(fused.cells, everything.cells[keep])
        np.testing.assert_array_equal(fused.source, everything.source[keep])
        np.testing.assert_array_equal(fused.target, everything.target[keep])
        # No two kept cells are neighbours the short way round the ring.
        r, c = fused.cells[:, 0], fused.cells[:, 1]
        d = np.abs(c[:, None] - c[None]) % 1800
        close = (np.abs(r[:, None] - r[None]) <= radius) & (np.minimum(d, 1800 - d) <= radius)
        assert close.sum() == len(fused)
        # ...which the non-wrapping NMS would not guarantee at the seam.
        plain = dmlo_rs.nms(everything.cells[:, 0], everything.cells[:, 1], everything.confidence, radius, top_n)
        assert plain.tolist() != keep.tolist()


def test_decoding_honours_confidence_and_the_exclusion_mask(moved_pair) -> None:
    ref, tgt, _, config = moved_pair
    flow = np.zeros((2, 64, 1792), np.float32)
    confidence = np.tile(np.linspace(0, 1, 1792, dtype=np.float32), (64, 1))
    mask = np.zeros((64, 1792), bool)
    mask[:, :896] = True
    matches = dmlo_rs.decode_matches(ref.range, ref.range, flow, confidence, config, 0.75, mask)
    assert (matches.confidence >= 0.75).all()
    assert (matches.cells[:, 1] >= 896).all()
    # Zero flow on the same image: target = source.
    np.testing.assert_allclose(matches.source, matches.target, atol=1e-9)
    expected = (ref.range > 0) & (confidence >= 0.75) & ~mask
    assert len(matches) == int(expected.sum())


def test_decoding_bad_input() -> None:
    config = CylinderConfig.kitti()
    image = np.ones((64, 1792), np.float32)
    flow = np.zeros((2, 64, 1792), np.float32)
    with pytest.raises(ValueError, match="flow"):
        dmlo_rs.decode_matches(image, image, flow[:, :10], image, config)
    with pytest.raises(ValueError, match="confidence"):
        dmlo_rs.decode_matches(image, image, flow, image[:5], config)
    with pytest.raises(TypeError, match="mask"):
        dmlo_rs.decode_matches(image, image, flow, image, config, mask=np.zeros((64, 1792), np.uint8))
    with pytest.raises(ValueError, match="mask"):
        dmlo_rs.decode_matches(image, image, flow, image, config, mask=np.zeros((64, 10), bool))
    with pytest.raises(ValueError, match="tgt_range"):
        dmlo_rs.decode_matches(image, -image, flow, image, config)
    empty = dmlo_rs.decode_matches(np.zeros_like(image), image, flow, image, config)
    assert len(empty) == 0 and empty.source.shape == (0, 3)
