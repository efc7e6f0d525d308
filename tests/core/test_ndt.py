"""Scan-to-map NDT (`dmlo_rs.NdtMap`): synthetic scenes with known motion (checked with scipy), real
KITTI scans of a standing car (the motion must be ~0), and bad input."""

from __future__ import annotations

import multiprocessing
import sys
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from scipy.spatial.transform import Rotation

import dmlo_rs
from support import rigid, transform_points

FloatArray = npt.NDArray[np.float64]


# ---- helpers -------------------------------------------------------------------------------------------


def pose_errors(estimate: FloatArray, truth: FloatArray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) of estimate⁻¹ · truth."""
    delta = np.linalg.inv(estimate) @ truth
    angle = Rotation.from_matrix(delta[:3, :3]).magnitude()
    return float(np.linalg.norm(delta[:3, 3])), float(np.degrees(angle))


def street_scene(count: int, seed: int) -> FloatArray:
    """`count` points on a street-like scene (ground, walls, boxes, poles) with ±1 cm noise."""
    rng = np.random.default_rng(seed)
    patches = [  # origin, edge a, edge b
        ((-25, -12, 0), (45, 0, 0), (0, 24, 0)),
        ((20, -12, 0), (0, 24, 0), (0, 0, 7)),
        ((-25, 11, 0), (45, 0, 0), (0, -0.8, 6)),
        ((-25, -12, 0), (35, 0, 0), (0, 0, 3.5)),
    ]
    for (x, y, z), (dx, dy, dz) in [
        ((3, 2, 0), (4.5, 1.8, 1.6)),
        ((-7, -6, 0), (2.5, 2.5, 2.5)),
        ((11, -4, 0), (1.2, 4.0, 1.8)),
        ((-14, 4, 0), (3.0, 1.5, 1.2)),
    ]:
        patches += [
            ((x, y, z), (dx, 0, 0), (0, 0, dz)),
            ((x, y + dy, z), (dx, 0, 0), (0, 0, dz)),
            ((x, y, z), (0, dy, 0), (0, 0, dz)),
            ((x + dx, y, z), (0, dy, 0), (0, 0, dz)),
            ((x, y, z + dz), (dx, 0, 0), (0, dy, 0)),
        ]
    origins, edges_a, edges_b = (np.array([p[i] for p in patches], dtype=float) for i in range(3))
    areas = np.linalg.norm(np.cross(edges_a, edges_b), axis=1)
    on_patches = count - count // 10
    which = rng.choice(len(patches), size=on_patches, p=areas / areas.sum())
    u, v = rng.random((2, on_patches, 1))
    surface = origins[which] + u * edges_a[which] + v * edges_b[which]
    poles = np.array([[1.5, -7.0], [-4.0, 8.0], [14.0, 5.0]])
    on_poles = count - on_patches
    centre = poles[rng.integers(len(poles), size=on_poles)]
    angle = rng.random(on_poles) * 2 * np.pi
    pole_points = np.column_stack(
        [centre[:, 0] + 0.2 * np.cos(angle), centre[:, 1] + 0.2 * np.sin(angle), rng.random(on_poles) * 6]
    )
    points = np.vstack([surface, pole_points])
    return points + rng.uniform(-0.01, 0.01, points.shape)


@pytest.fixture(scope="module")
def scene_map() -> dmlo_rs.NdtMap:
    ndt_map = dmlo_rs.NdtMap(voxel_size=1.0)
    ndt_map.insert(street_scene(40_000, seed=1))
    return ndt_map


def read_kitti_scan(path: Path) -> npt.NDArray[np.float32]:
    return np.fromfile(path, dtype=np.float32).reshape(-1, 4)


# ---- synthetic scenes with known motion ----------------------------------------------------------------

MOTION = rigid([0.5, -0.2, 0.05], [0.3, -0.2, 3.0])


@pytest.mark.parametrize(
    ("truth", "start"),
    [
        pytest.param(MOTION, np.eye(4), id="forward"),
        pytest.param(np.linalg.inv(MOTION), np.eye(4), id="inverse"),
        pytest.param(MOTION, MOTION @ rigid([0.25, -0.15, 0.1], [0.8, -0.5, 1.5]), id="noisy-start"),
    ],
)
def test_recovers_known_motion(scene_map: dmlo_rs.NdtMap, truth: FloatArray, start: FloatArray) -> None:
    # The source is an independent sample of the scene seen from T_map_source = truth.
    source = transform_points(np.linalg.inv(truth), street_scene(8_000, seed=2))
    result = scene_map.align(source, start)
    translation_error, rotation_error = pose_errors(result.transform, truth)
    assert result.converged, result
    assert translation_error < 0.01, result
    assert rotation_error < 0.05, result
    assert result.num_correspondences > 1_000
    assert result.transform.dtype == np.float64 and result.transform.shape == (4, 4)
    # A well-constrained scene: nothing is held back by the degeneracy analysis.
    assert result.degenerate_directions == 0, result
    assert result.translation_eigenvalues.shape == result.rotation_eigenvalues.shape == (3,)
    assert result.translation_eigenvalues[-1] == result.rotation_eigenvalues[-1] == 1.0


def test_float32_with_reflectance_equals_float64(scene_map: dmlo_rs.NdtMap) -> None:
    source = transform_points(np.linalg.inv(MOTION), street_scene(4_000, seed=3))
    with_reflectance = np.column_stack([source, np.full(len(source), 0.5)]).astype(np.float32)
    as_float32 = scene_map.align(with_reflectance, np.eye(4))
    as_float64 = scene_map.align(source.astype(np.float32).astype(np.float64), np.eye(4))
    np.testing.assert_array_equal(as_float32.transform, as_float64.transform)


def test_same_result_for_any_thread_count(scene_map: dmlo_rs.NdtMap) -> None:
    source = transform_points(np.linalg.inv(MOTION), street_scene(8_000, seed=4))
    one = scene_map.align(source, np.eye(4), num_threads=1)
    three = scene_map.align(source, np.eye(4), num_threads=3)
    np.testing.assert_array_equal(one.transform, three.transform)
    assert (one.iterations, one.score) == (three.iterations, three.score)


def test_non_contiguous_input_is_read_correctly(scene_map: dmlo_rs.NdtMap) -> None:
    source = transform_points(np.linalg.inv(MOTION), street_scene(4_000, seed=5))
    strided = np.asfortranarray(np.column_stack([source, source]))[:, :3]
    np.testing.assert_array_equal(
        scene_map.align(strided, np.eye(4)).transform, scene_map.align(np.ascontiguousarray(source), np.eye(4)).transform
    )


_FORKED_MAP: dict[str, dmlo_rs.NdtMap] = {}


def _align_in_child(source: FloatArray) -> FloatArray:
    return _FORKED_MAP["map"].align(source, np.eye(4), num_threads=2).transform


@pytest.mark.skipif(sys.platform != "linux", reason="fork start method")
def test_align_works_in_a_forked_child(scene_map: dmlo_rs.NdtMap) -> None:
    # The parent's rayon pool has no threads in a fork()ed child (PyTorch DataLoader workers): the
    # binding must build a new pool there instead of hanging.
    source = transform_points(np.linalg.inv(MOTION), street_scene(4_000, seed=11))
    in_parent = scene_map.align(source, np.eye(4), num_threads=2).transform
    _FORKED_MAP["map"] = scene_map
    with multiprocessing.get_context("fork").Pool(1) as pool:
        in_child = pool.apply_async(_align_in_child, (source,)).get(timeout=60)
    np.testing.assert_array_equal(in_child, in_parent)


def test_sliding_window_keeps_recent_scans() -> None:
    ndt_map = dmlo_rs.NdtMap(voxel_size=1.0, max_scans=2)
    far_block = street_scene(5_000, seed=6) + [500.0, 0.0, 0.0]
    ndt_map.insert(far_block)
    alone = dmlo_rs.NdtMap(voxel_size=1.0, max_scans=2)
    for seed in (7, 8):
        scan = street_scene(5_000, seed=seed)
        ndt_map.insert(scan)
        alone.insert(scan)
    assert ndt_map.num_scans == 2
    # The far block was evicted: the map is the two recent scans, exactly as if built from them alone.
    assert ndt_map.num_voxels == alone.num_voxels
    assert ndt_map.num_occupied_voxels == alone.num_occupied_voxels
    with pytest.raises(dmlo_rs.RegistrationError, match="need at least 20"):
        ndt_map.align(far_block - [500.0, 0.0, 0.0], rigid([500.0, 0, 0], [0, 0, 0]))
    ndt_map.clear()
    assert (ndt_map.num_scans, ndt_map.num_voxels) == (0, 0)



def test_a_scan_inserted_at_its_pose_builds_the_map_of_its_transformed_points() -> None:
    scan = street_scene(20_000, seed=9)
    pose = rigid([4.0, -1.5, 0.3], [1.0, -2.0, 30.0])
    placed = dmlo_rs.NdtMap(voxel_size=1.0)
    placed.insert_scan(scan.astype(np.float32), pose)
    reference = dmlo_rs.NdtMap(voxel_size=1.0)
    reference.insert(transform_points(pose, scan.astype(np.float32).astype(np.float64)))
    # numpy and nalgebra may round a coordinate differently, which can move a point across a voxel face.
    assert abs(placed.num_voxels - reference.num_voxels) <= 2
    source = street_scene(20_000, seed=10)
    start = pose @ rigid([0.25, -0.15, 0.1], [0.8, -0.5, 1.5])
    got, expected = placed.align(source, start), reference.align(source, start)
    np.testing.assert_allclose(got.transform, expected.transform, atol=1e-6)
    np.testing.assert_allclose(got.transform, pose, atol=0.02)
    with pytest.raises(ValueError, match="transform: expected shape"):
        placed.insert_scan(scan, np.eye(3))
    with pytest.raises(ValueError, match="transform: last row"):
        placed.insert_scan(scan, np.ones((4, 4)))
    nan_row = scan.copy()
    nan_row[3] = np.nan
    with pytest.raises(ValueError, match="points: row 3 is not finite"):
        placed.insert_scan(nan_row, pose)

# ---- real KITTI scans of a standing car ----------------------------------------------------------------


@pytest.fixture(scope="module")
def kitti_pair(shared_data: Path) -> tuple[dmlo_rs.NdtMap, npt.NDArray[np.float32]]:
    folder = shared_data / "kitti_raw_static"
    ndt_map = dmlo_rs.NdtMap(voxel_size=1.0)
    ndt_map.insert(read_kitti_scan(folder / "0000000000.bin"))
    return ndt_map, read_kitti_scan(folder / "0000000001.bin")


def test_kitti_static_scan_aligns_to_identity(kitti_pair: tuple[dmlo_rs.NdtMap, npt.NDArray[np.float32]]) -> None:
    ndt_map, scan = kitti_pair
    result = ndt_map.align(scan, np.eye(4))
    translation_error, rotation_error = pose_errors(result.transform, np.eye(4))
    assert result.converged, result
    assert translation_error < 0.02 and rotation_error < 0.1, result
    assert result.degenerate_directions == 0, (result.translation_eigenvalues, result.rotation_eigenvalues)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kitti_static_scan_recovers_from_perturbed_start(
    kitti_pair: tuple[dmlo_rs.NdtMap, npt.NDArray[np.float32]], seed: int
) -> None:
    ndt_map, scan = kitti_pair
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=3)
    axis = rng.normal(size=3)
    start = rigid(list(0.3 * direction / np.linalg.norm(direction)), list(2.0 * axis / np.linalg.norm(axis)))
    result = ndt_map.align(scan, start)
    translation_error, rotation_error = pose_errors(result.transform, np.eye(4))
    assert result.converged, result
    assert translation_error < 0.02 and rotation_error < 0.1, result


# ---- bad input -----------------------------------------------------------------------------------------


def test_bad_map_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="voxel_size"):
        dmlo_rs.NdtMap(voxel_size=0.0)
    with pytest.raises(ValueError, match="max_scans"):
        dmlo_rs.NdtMap(max_scans=0)
    with pytest.raises(ValueError, match="min_points_per_voxel"):
        dmlo_rs.NdtMap(min_points_per_voxel=2)
    with pytest.raises(ValueError, match="min_eigenvalue_ratio"):
        dmlo_rs.NdtMap(min_eigenvalue_ratio=2.0)


def test_bad_points_are_refused(scene_map: dmlo_rs.NdtMap) -> None:
    ndt_map = dmlo_rs.NdtMap()
    with pytest.raises(ValueError, match="points_world: is empty"):
        ndt_map.insert(np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"points_world: expected shape \(N, 3\) or \(N, 4\)"):
        ndt_map.insert(np.zeros((10, 2)))
    with pytest.raises(TypeError, match="points_world: expected a 2-D float32 or float64"):
        ndt_map.insert(np.zeros((10, 3), dtype=np.int32))
    with pytest.raises(TypeError, match="points_world"):
        ndt_map.insert([[0.0, 0.0, 0.0]])
    nan_scan = street_scene(100, seed=9)
    nan_scan[42, 1] = np.nan
    with pytest.raises(ValueError, match="points_world: row 42 is not finite"):
        ndt_map.insert(nan_scan)
    assert ndt_map.num_scans == 0
    with pytest.raises(ValueError, match="map: is empty"):
        ndt_map.align(street_scene(100, seed=9), np.eye(4))
    with pytest.raises(ValueError, match="points: row 42 is not finite"):
        scene_map.align(nan_scan, np.eye(4))
    with pytest.raises(ValueError, match="points: is empty"):
        scene_map.align(np.zeros((0, 4), dtype=np.float32), np.eye(4))


def test_bad_transforms_and_options_are_refused(scene_map: dmlo_rs.NdtMap) -> None:
    source = street_scene(2_000, seed=10)
    scaled = np.diag([2.0, 1.0, 1.0, 1.0])
    reflected = np.diag([1.0, 1.0, -1.0, 1.0])
    projective = np.eye(4)
    projective[3, 0] = 0.5
    for bad in (scaled, reflected, projective, np.full((4, 4), np.nan)):
        with pytest.raises(ValueError, match="initial_transform"):
            scene_map.align(source, bad)
    with pytest.raises(ValueError, match=r"initial_transform: expected shape \(4, 4\)"):
        scene_map.align(source, np.eye(3))
    with pytest.raises(ValueError, match="neighbours"):
        scene_map.align(source, np.eye(4), neighbours="all")
    with pytest.raises(ValueError, match="outlier_ratio"):
        scene_map.align(source, np.eye(4), outlier_ratio=1.0)
    with pytest.raises(ValueError, match="max_iterations"):
        scene_map.align(source, np.eye(4), max_iterations=0)
    with pytest.raises(ValueError, match="num_threads"):
        scene_map.align(source, np.eye(4), num_threads=0)
    with pytest.raises(dmlo_rs.RegistrationError, match="need at least 20 point pairs, got 0"):
        scene_map.align(source, rigid([1000.0, 0.0, 0.0], [0.0, 0.0, 0.0]))
    # Wrong arguments are plain ValueErrors, never the data-dependent RegistrationError callers fall back on.
    with pytest.raises(ValueError) as refused:
        scene_map.align(source, np.eye(4), outlier_ratio=1.0)
    assert not isinstance(refused.value, dmlo_rs.RegistrationError)
