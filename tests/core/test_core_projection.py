"""Cylinder projection, its inverse and the training ground truth, against numpy references written here."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

import dmlo_rs
from dmlo_rs import CylinderConfig


def load_scan(path: Path) -> np.ndarray:
    return np.fromfile(path, dtype=np.float32).reshape(-1, 4)


@pytest.fixture(scope="module")
def static_scans(shared_data: Path) -> list[np.ndarray]:
    folder = shared_data / "kitti_raw_static"
    if not folder.is_dir():
        pytest.skip(f"{folder} is absent")
    return [load_scan(folder / f"{i:010d}.bin") for i in (0, 5)]


# ---- numpy references ----------------------------------------------------------------------------


def reference_locate(xyz: np.ndarray, config: CylinderConfig) -> tuple[np.ndarray, np.ndarray]:
    """Continuous (row, col) of points, as the Rust docs define it."""
    x, y, z = (xyz[:, k].astype(np.float64) for k in range(3))
    horizontal = np.sqrt(x * x + y * y)
    rows_per_radian = 1.0 / (config.vertical_resolution_deg * (np.pi / 180.0))
    cols_per_radian = 1.0 / (config.horizontal_resolution_deg * (np.pi / 180.0))
    row = config.row_of_zero_elevation - np.arctan2(z, horizontal) * rows_per_radian
    col = config.col_of_zero_azimuth - np.arctan2(y, x) * cols_per_radian
    return row, col


def reference_project(points: np.ndarray, config: CylinderConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest point per cell (ties: lower index); returns range, reflectance, index images."""
    h, w = config.height, config.width
    finite = np.isfinite(points).all(axis=1)
    ids = np.flatnonzero(finite)
    p = points[finite]
    x, y, z = (p[:, k].astype(np.float64) for k in range(3))
    rng = np.sqrt(x * x + y * y + z * z)
    row, col = reference_locate(p, config)
    row = np.floor(row + 0.5)
    col = np.floor(col + 0.5)
    inside = (rng > 0) & (row >= 0) & (row < h) & (col >= 0) & (col < w)
    cell = (row[inside] * w + col[inside]).astype(np.int64)
    range32 = rng[inside].astype(np.float32)
    ids = ids[inside]
    order = np.lexsort((ids, range32, cell))
    cell, range32, ids = cell[order], range32[order], ids[order]
    first = np.ones(len(cell), dtype=bool)
    first[1:] = cell[1:] != cell[:-1]
    range_image = np.zeros(h * w, np.float32)
    reflectance = np.zeros(h * w, np.float32)
    index = np.full(h * w, -1, np.int64)
    range_image[cell[first]] = range32[first]
    reflectance[cell[first]] = points[ids[first], 3]
    index[cell[first]] = ids[first]
    return range_image.reshape(h, w), reflectance.reshape(h, w), index.reshape(h, w)


def reference_unproject(rows: np.ndarray, cols: np.ndarray, ranges: np.ndarray, config: CylinderConfig) -> np.ndarray:
    elevation = np.radians((config.row_of_zero_elevation - rows) * config.vertical_resolution_deg)
    azimuth = np.radians((config.col_of_zero_azimuth - cols) * config.horizontal_resolution_deg)
    return np.stack(
        [
            ranges * np.cos(elevation) * np.cos(azimuth),
            ranges * np.cos(elevation) * np.sin(azimuth),
            ranges * np.sin(elevation),
        ],
        axis=1,
    )


def reference_ground_truth(
    ref_range: np.ndarray, tgt_range: np.ndarray, T: np.ndarray, config: CylinderConfig, max_error: float
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 5-8 for a cropped (non-wrapping) image."""
    h, w = ref_range.shape
    rows, cols = np.nonzero(ref_range > 0)
    p_ref = reference_unproject(rows.astype(float), cols.astype(float), ref_range[rows, cols].astype(float), config)
    p_t = p_ref @ T[:3, :3].T + T[:3, 3]
    row_t, col_t = reference_locate(p_t, config)
    # Columns move the short way round; a path through the cropped-away back is invalid.
    period = 360.0 / config.horizontal_resolution_deg
    col_t = cols + np.mod(col_t - cols + period / 2, period) - period / 2
    cell_r, cell_c = np.floor(row_t + 0.5), np.floor(col_t + 0.5)
    inside = (cell_r >= 0) & (cell_r < h) & (cell_c >= 0) & (cell_c < w)
    target = np.zeros(len(rows), np.float64)
    target[inside] = tgt_range[cell_r[inside].astype(int), cell_c[inside].astype(int)]
    ok = inside & (target > 0) & (np.abs(target - np.linalg.norm(p_t, axis=1)) < max_error)
    flow = np.zeros((2, h, w), np.float64)
    valid = np.zeros((h, w), bool)
    flow[0, rows[ok], cols[ok]] = row_t[ok] - rows[ok]
    flow[1, rows[ok], cols[ok]] = col_t[ok] - cols[ok]
    valid[rows[ok], cols[ok]] = True
    return flow, valid


def yaw_pitch_roll(yaw: float, pitch: float, roll: float, t: tuple[float, float, float]) -> np.ndarray:
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    R = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    R = R @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


# ---- config --------------------------------------------------------------------------------------


def test_presets_and_attributes() -> None:
    kitti = CylinderConfig.kitti()
    assert (kitti.height, kitti.width, kitti.full_height, kitti.full_width) == (64, 1792, 68, 1801)
    assert (kitti.vertical_resolution_deg, kitti.horizontal_resolution_deg) == (0.4, 0.2)
    assert (kitti.crop_top, kitti.crop_left) == (2, 4)
    assert kitti == CylinderConfig()  # the defaults are KITTI's
    assert not kitti.wraps_azimuth
    argoverse = CylinderConfig.argoverse()
    assert argoverse.vertical_resolution_deg == 0.3
    assert argoverse.fov_up_deg - argoverse.fov_down_deg == 20.0
    assert "CylinderConfig(" in repr(kitti) and "height=64" in repr(kitti)
    assert pickle.loads(pickle.dumps(argoverse)) == argoverse
    full = CylinderConfig(width=1801, height=68)
    assert full.wraps_azimuth and full.crop_left == 0


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"vertical_resolution_deg": 0.0}, "vertical_resolution_deg"),
        ({"horizontal_resolution_deg": -1.0}, "horizontal_resolution_deg"),
        ({"fov_up_deg": -30.0}, "fov_up_deg"),
        ({"width": 5000}, "width"),
        ({"height": 0}, "height"),
    ],
)
def test_bad_configs_name_the_field(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        CylinderConfig(**kwargs)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        # 64 × 3·10⁷ cells: the projection's buffers would fail to allocate and abort the interpreter.
        ({"horizontal_resolution_deg": 1e-5, "width": 30_000_000}, r"height \* width"),
        ({"horizontal_resolution_deg": 1e-9}, "horizontal_resolution_deg"),
        ({"vertical_resolution_deg": 1e-300}, "vertical_resolution_deg"),
    ],
)
def test_images_too_large_to_allocate_are_refused_by_the_config(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        CylinderConfig(**kwargs)
    # Large images below the cap stay allowed.
    assert CylinderConfig(horizontal_resolution_deg=0.01, width=36_001).width == 36_001


# ---- projection on real scans --------------------------------------------------------------------


def test_project_equals_the_numpy_reference_on_real_scans(static_scans: list[np.ndarray]) -> None:
    config = CylinderConfig.kitti()
    for scan in static_scans:
        image = dmlo_rs.project(scan, config)
        range_ref, reflectance_ref, index_ref = reference_project(scan, config)
        assert image.range.dtype == np.float32 and image.range.shape == (64, 1792)
        assert image.index.dtype == np.int64
        np.testing.assert_array_equal(image.index, index_ref)
        np.testing.assert_array_equal(image.range, range_ref)
        np.testing.assert_array_equal(image.reflectance, reflectance_ref)
        assert image.num_non_finite == 0
        kept = int((image.index >= 0).sum())
        assert kept > 0.6 * 64 * 1792
        assert image.num_out_of_view > 0  # the crop drops the top/bottom beams and the back columns


def test_round_trip_stays_within_half_a_cell(static_scans: list[np.ndarray]) -> None:
    config = CylinderConfig.kitti()
    scan = static_scans[0]
    image = dmlo_rs.project(scan, config)
    rows, cols = np.nonzero(image.index >= 0)
    back = dmlo_rs.unproject(rows.astype(np.float64), cols.astype(np.float64), image.range[rows, cols], config)
    original = scan[image.index[rows, cols], :3].astype(np.float64)
    cos = np.sum(back * original, axis=1) / np.linalg.norm(back, axis=1) / np.linalg.norm(original, axis=1)
    angle = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    assert angle.max() <= np.hypot(0.2, 0.1) + 1e-3
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), np.linalg.norm(original, axis=1), rtol=1e-6)


def test_unproject_equals_the_numpy_reference() -> None:
    config = CylinderConfig.argoverse()
    rng = np.random.default_rng(0)
    rows, cols, ranges = rng.uniform(-1, 64, 500), rng.uniform(-1, 1792, 500), rng.uniform(0, 80, 500)
    out = dmlo_rs.unproject(rows, cols, ranges, config)
    assert out.dtype == np.float64 and out.shape == (500, 3)
    np.testing.assert_allclose(out, reference_unproject(rows, cols, ranges, config), atol=1e-9)
    # float32 inputs are accepted.
    out32 = dmlo_rs.unproject(rows.astype(np.float32), cols.astype(np.float32), ranges.astype(np.float32), config)
    np.testing.assert_allclose(out32, out, atol=1e-3)


# ---- projection: bad and odd input ---------------------------------------------------------------


def test_non_finite_points_are_dropped_and_counted() -> None:
    config = CylinderConfig.kitti()
    points = np.array(
        [[10, 0, 0, 0.5], [np.nan, 0, 0, 0], [1, np.inf, 0, 0], [5, 0, 0, 0.25], [0, 0, 0, 1]], np.float32
    )
    image = dmlo_rs.project(points, config)
    assert image.num_non_finite == 2
    assert image.num_out_of_view == 1
    row, col = int(config.row_of_zero_elevation), int(config.col_of_zero_azimuth)
    assert image.index[row, col] == 3 and image.range[row, col] == 5.0 and image.reflectance[row, col] == 0.25
    assert (image.index >= 0).sum() == 1


def test_empty_scan_and_xyz_only_and_float64() -> None:
    config = CylinderConfig.kitti()
    empty = dmlo_rs.project(np.zeros((0, 4), np.float32), config)
    assert (empty.index == -1).all() and (empty.range == 0).all()
    points = np.array([[10, 1, 0, 0.5], [4, -3, -1, 0.1]], np.float32)
    xyz = dmlo_rs.project(points[:, :3].copy(), config)
    full = dmlo_rs.project(points, config)
    np.testing.assert_array_equal(xyz.range, full.range)
    assert (xyz.reflectance == 0).all()
    np.testing.assert_array_equal(dmlo_rs.project(points.astype(np.float64), config).range, full.range)


def test_non_contiguous_points_equal_a_contiguous_copy(static_scans: list[np.ndarray]) -> None:
    config = CylinderConfig.kitti()
    strided = static_scans[0][::2]
    assert not strided.flags.c_contiguous
    np.testing.assert_array_equal(
        dmlo_rs.project(strided, config).index, dmlo_rs.project(np.ascontiguousarray(strided), config).index
    )
    fortran = np.asfortranarray(static_scans[0])
    np.testing.assert_array_equal(dmlo_rs.project(fortran, config).range, dmlo_rs.project(static_scans[0], config).range)


def test_project_rejects_bad_input_naming_the_argument() -> None:
    config = CylinderConfig.kitti()
    with pytest.raises(TypeError, match="points"):
        dmlo_rs.project(np.zeros((10, 4), np.int32), config)
    with pytest.raises(TypeError, match="points"):
        dmlo_rs.project([[1.0, 2.0, 3.0]], config)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="points"):
        dmlo_rs.project(np.zeros((10, 5), np.float32), config)
    with pytest.raises(ValueError, match="points"):
        dmlo_rs.project(np.zeros(12, np.float32), config)
    with pytest.raises(ValueError, match="num_threads"):
        dmlo_rs.project(np.zeros((1, 4), np.float32), config, num_threads=0)
    with pytest.raises(ValueError, match="cols"):
        dmlo_rs.unproject(np.zeros(3), np.zeros(2), np.zeros(3), config)
    with pytest.raises(ValueError, match="ranges"):
        dmlo_rs.unproject(np.zeros(1), np.zeros(1), np.array([np.nan]), config)


# ---- ground truth --------------------------------------------------------------------------------


def test_ground_truth_flow_is_zero_between_two_static_scans(static_scans: list[np.ndarray]) -> None:
    config = CylinderConfig.kitti()
    ref, tgt = (dmlo_rs.project(scan, config) for scan in static_scans)
    flow, valid = dmlo_rs.ground_truth_flow(ref.range, tgt.range, np.eye(4), config)
    assert flow.shape == (2, 64, 1792) and flow.dtype == np.float32
    assert valid.shape == (64, 1792) and valid.dtype == np.bool_
    # The car stands still: most reference cells see the same surface again within 0.1 m.
    assert valid.sum() > 0.5 * (ref.range > 0).sum()
    magnitude = np.hypot(flow[0][valid], flow[1][valid])
    assert np.mean(magnitude < 0.5) > 0.99
    assert (flow[:, ~valid] == 0).all()


def test_ground_truth_flow_follows_equations_5_to_8_for_a_known_motion(static_scans: list[np.ndarray]) -> None:
    config = CylinderConfig.kitti()
    scan = static_scans[0]
    T = yaw_pitch_roll(np.radians(3.0), np.radians(0.5), np.radians(-0.3), (-1.2, 0.3, 0.05))
    moved = scan.copy()
    moved[:, :3] = (scan[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
    ref, tgt = dmlo_rs.project(scan, config), dmlo_rs.project(moved, config)
    flow, valid = dmlo_rs.ground_truth_flow(ref.range, tgt.range, T, config, max_range_error=0.1)
    flow_ref, valid_ref = reference_ground_truth(ref.range, tgt.range, T, config, 0.1)
    # Validity may differ only where a test sits exactly on a rounding or 0.1 m boundary.
    assert np.mean(valid != valid_ref) < 1e-4
    both = valid & valid_ref
    assert both.sum() > 0.3 * (ref.range > 0).sum()
    np.testing.assert_allclose(flow[:, both], flow_ref[:, both], atol=1e-3)
    # A 3° yaw moves content ~15 columns to the left (azimuth grows → column falls).
    assert abs(np.median(flow[1][valid]) + 15) < 3


def test_ground_truth_wraps_a_full_circle_image(static_scans: list[np.ndarray]) -> None:
    config = CylinderConfig(width=1801, height=68)
    scan = static_scans[0]
    T = yaw_pitch_roll(np.radians(10.0), 0.0, 0.0, (0.0, 0.0, 0.0))
    moved = scan.copy()
    moved[:, :3] = (scan[:, :3].astype(np.float64) @ T[:3, :3].T).astype(np.float32)
    ref, tgt = dmlo_rs.project(scan, config), dmlo_rs.project(moved, config)
    flow, valid = dmlo_rs.ground_truth_flow(ref.range, tgt.range, T, config)
    # Cells near the back (columns 0..50) wrap to the other side with Δcol = -50, not +1750.
    back = valid[:, :40]
    assert back.sum() > 100
    np.testing.assert_allclose(flow[1][:, :40][back], -50.0, atol=0.01)
    np.testing.assert_allclose(flow[1][valid], -50.0, atol=0.01)


def test_ground_truth_rejects_bad_input() -> None:
    config = CylinderConfig.kitti()
    image = np.ones((64, 1792), np.float32)
    with pytest.raises(ValueError, match="tgt_range"):
        dmlo_rs.ground_truth_flow(image, image[:, :100], np.eye(4), config)
    with pytest.raises(ValueError, match="T_tgt_ref"):
        dmlo_rs.ground_truth_flow(image, image, np.eye(3), config)
    with pytest.raises(ValueError, match="T_tgt_ref"):
        dmlo_rs.ground_truth_flow(image, image, 2 * np.eye(4), config)
    with pytest.raises(TypeError, match="ref_range"):
        dmlo_rs.ground_truth_flow(image.astype(np.int32), image, np.eye(4), config)
    bad = image.copy()
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="ref_range"):
        dmlo_rs.ground_truth_flow(bad, image, np.eye(4), config)
    with pytest.raises(ValueError, match="max_range_error"):
        dmlo_rs.ground_truth_flow(image, image, np.eye(4), config, max_range_error=-1.0)
    # Non-contiguous and float64 images are accepted.
    flow, valid = dmlo_rs.ground_truth_flow(
        np.asfortranarray(image), image.astype(np.float64), np.eye(4, dtype=np.float32), config
    )
    assert valid.all() and np.abs(flow).max() < 1e-6
