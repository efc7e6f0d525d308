"""`dmlo_rs.RayScene` against closed-form ray intersections computed independently in numpy."""

from __future__ import annotations

import dmlo_rs
import numpy as np
import pytest

RNG = np.random.default_rng(1234)


def _random_rays(
    count: int, target: tuple[float, float, float] = (0.0, 0.0, 0.0), spread: float = 3.0
) -> tuple[np.ndarray, np.ndarray]:
    """Rays from around the origin, aimed at random points within `spread` of `target`."""
    origins = RNG.uniform(-2.0, 2.0, (count, 3))
    directions = np.asarray(target) + RNG.normal(scale=spread, size=(count, 3)) - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return origins, directions


def test_sphere_matches_quadratic_roots() -> None:
    center, radius = np.array([6.0, -1.0, 0.5]), 2.5
    origins, directions = _random_rays(4000, tuple(center))
    ranges, primitive, cosines = dmlo_rs.RayScene(
        ellipsoids=np.array([[*center, radius, radius, radius]])
    ).cast(origins, directions, 100.0)
    oc = origins - center
    b = np.einsum("ij,ij->i", oc, directions)
    disc = b**2 - (np.einsum("ij,ij->i", oc, oc) - radius**2)
    expected = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
    expected = np.where(expected > 0, expected, np.inf)  # origins are outside the sphere
    hit = np.isfinite(expected)
    assert hit.sum() > 200 and (~hit).sum() > 200
    np.testing.assert_array_equal(np.isfinite(ranges), hit)
    np.testing.assert_allclose(ranges[hit], expected[hit], atol=1e-9)
    assert (primitive[hit] == 0).all() and (primitive[~hit] == -1).all()
    normals = (origins[hit] + ranges[hit, None] * directions[hit] - center) / radius
    np.testing.assert_allclose(
        cosines[hit], np.abs(np.einsum("ij,ij->i", normals, directions[hit])), atol=1e-6
    )


def test_ground_plane_of_two_triangles() -> None:
    z0 = -1.73
    square = np.array(
        [[[-50, -50, z0], [50, -50, z0], [50, 50, z0]], [[-50, -50, z0], [50, 50, z0], [-50, 50, z0]]], float
    )
    origins, directions = _random_rays(4000)
    ranges, _, cosines = dmlo_rs.RayScene(triangles=square).cast(origins, directions, 200.0)
    t = (z0 - origins[:, 2]) / directions[:, 2]
    xy = origins[:, :2] + t[:, None] * directions[:, :2]
    expected = np.where((t > 0) & (np.abs(xy) <= 50).all(1), t, np.inf)
    hit = np.isfinite(expected)
    assert hit.sum() > 500
    np.testing.assert_array_equal(np.isfinite(ranges), hit)
    np.testing.assert_allclose(ranges[hit], expected[hit], rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(cosines[hit], np.abs(directions[hit, 2]), atol=1e-6)


def _rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    cz, sz, cy, sy, cx, sx = (
        np.cos(yaw),
        np.sin(yaw),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(roll),
        np.sin(roll),
    )
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    return rz @ ry @ rx


def test_oriented_box_matches_slab_method() -> None:
    center, half = np.array([8.0, 3.0, 1.0]), np.array([2.0, 1.0, 0.7])
    rotation = _rotation(0.6, 0.2, -0.3)
    boxes = np.concatenate([center, rotation.ravel(), half])[None]
    origins, directions = _random_rays(4000, tuple(center))
    ranges, _, _ = dmlo_rs.RayScene(boxes=boxes).cast(origins, directions, 100.0)
    o = (origins - center) @ rotation  # into the box frame (Rᵀ p)
    d = directions @ rotation
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - o) / d, (half - o) / d
    near = np.nanmax(np.minimum(t1, t2), axis=1)
    far = np.nanmin(np.maximum(t1, t2), axis=1)
    expected = np.where((near <= far) & (near > 0), near, np.inf)
    hit = np.isfinite(expected)
    assert hit.sum() > 100
    np.testing.assert_array_equal(np.isfinite(ranges), hit)
    np.testing.assert_allclose(ranges[hit], expected[hit], atol=1e-9)


def test_vertical_cylinder_side_and_caps() -> None:
    base, height, radius = np.array([5.0, 0.0, -2.0]), 4.0, 0.8
    origins, directions = _random_rays(6000, (5.0, 0.0, 0.0))
    ranges, _, _ = dmlo_rs.RayScene(cylinders=np.array([[*base, height, radius]])).cast(
        origins, directions, 100.0
    )
    o = origins - base
    a = directions[:, 0] ** 2 + directions[:, 1] ** 2
    b = o[:, 0] * directions[:, 0] + o[:, 1] * directions[:, 1]
    c = o[:, 0] ** 2 + o[:, 1] ** 2 - radius**2
    disc = b**2 - a * c
    side = (-b - np.sqrt(np.maximum(disc, 0))) / a
    side_z = o[:, 2] + side * directions[:, 2]
    side = np.where((disc >= 0) & (side > 0) & (side_z >= 0) & (side_z <= height), side, np.inf)
    caps = []
    for z in (0.0, height):
        t = (z - o[:, 2]) / directions[:, 2]
        xy = o[:, :2] + t[:, None] * directions[:, :2]
        caps.append(np.where((t > 0) & ((xy**2).sum(1) <= radius**2), t, np.inf))
    expected = np.minimum(side, np.minimum(*caps))
    hit = np.isfinite(expected)
    assert hit.sum() > 100
    np.testing.assert_array_equal(np.isfinite(ranges), hit)
    np.testing.assert_allclose(ranges[hit], expected[hit], atol=1e-9)


def test_closest_of_many_primitives_and_numbering() -> None:
    # A triangle behind a box behind a sphere behind a pole; primitives are numbered triangles, boxes,
    # cylinders, ellipsoids.
    triangles = np.array([[[30, -5, -5], [30, 5, -5], [30, 0, 5]]], float)
    boxes = np.concatenate([[20.0, 0, 0], np.eye(3).ravel(), [0.5, 5, 2]])[None]
    cylinders = np.array([[5.0, 0.0, -1.0, 2.0, 0.2]])
    ellipsoids = np.array([[10.0, 0, 0, 1, 1, 1]])
    scene = dmlo_rs.RayScene(triangles, boxes, cylinders, ellipsoids)
    assert len(scene) == 4
    origins = np.zeros((4, 3))
    origins[:, 2] = [0.0, 1.5, 3.0, 10.0]  # above the pole, above the sphere, above the box: the triangle
    directions = np.tile([1.0, 0, 0], (4, 1))
    ranges, primitive, _ = scene.cast(origins, directions, 100.0)
    np.testing.assert_array_equal(primitive, [2, 1, 0, -1])
    np.testing.assert_allclose(ranges[:3], [4.8, 19.5, 30.0])
    ranges, primitive, _ = scene.cast(np.array([[0, 0.5, 0.0]]), np.array([[1.0, 0, 0]]), 100.0)
    assert primitive[0] == 3 and ranges[0] == pytest.approx(
        10.0 - np.sqrt(0.75)
    )  # over the pole, into the sphere
    ranges, primitive, _ = scene.cast(np.array([[0, 1.0, 4.5]]), np.array([[1.0, 0, 0]]), 100.0)
    assert primitive[0] == -1  # the triangle is narrower than 4.5 m up there
    ranges, primitive, _ = scene.cast(np.array([[0, 0, 0.0]]), np.array([[1.0, 0, 0]]), 4.0)
    assert primitive[0] == -1 and np.isinf(ranges[0])  # beyond max_range


def test_cast_scan_agrees_with_cast_along_the_scan_directions() -> None:
    rng = np.random.default_rng(5)
    ellipsoids = np.column_stack(
        [rng.uniform(-30, 30, (200, 3)) * [1, 1, 0.1], rng.uniform(0.3, 2, (200, 3))]
    )
    scene = dmlo_rs.RayScene(ellipsoids=ellipsoids)
    pose = np.eye(4)
    pose[:3, :3] = _rotation(0.7, 0.05, -0.02)
    pose[:3, 3] = [1.0, -2.0, 0.3]
    elevations = np.array([2.0, -1.0, -5.0, -12.0])
    ranges, primitive, _ = scene.cast_scan(pose, elevations, 500, 80.0)
    assert ranges.shape == primitive.shape == (4, 500)
    local = dmlo_rs.lidar_scan_directions(elevations, 500)
    assert local.shape == (2000, 3)
    np.testing.assert_allclose(np.linalg.norm(local, axis=1), 1.0)
    np.testing.assert_allclose(
        np.degrees(np.arcsin(local[:, 2])).reshape(4, 500), np.repeat(elevations[:, None], 500, 1)
    )
    world = local @ pose[:3, :3].T
    expected, expected_primitive, _ = scene.cast(np.tile(pose[:3, 3], (2000, 1)), world, 80.0)
    np.testing.assert_array_equal(primitive.ravel(), expected_primitive)
    np.testing.assert_allclose(ranges.ravel(), expected, atol=1e-9)
    assert (primitive >= 0).sum() > 100


def test_bad_input_names_the_argument() -> None:
    with pytest.raises(ValueError, match="boxes"):
        dmlo_rs.RayScene(boxes=np.zeros((2, 14)))
    with pytest.raises(ValueError, match="triangles"):
        dmlo_rs.RayScene(triangles=np.zeros((2, 3, 2)))
    with pytest.raises(ValueError, match="primitive 0 \\(ellipsoid\\)"):
        dmlo_rs.RayScene(ellipsoids=np.array([[0, 0, 0, 1, -1, 1.0]]))
    with pytest.raises(ValueError, match="primitive 1 \\(cylinder\\).*non-finite"):
        dmlo_rs.RayScene(cylinders=np.array([[0, 0, 0, 1, 1.0], [np.nan, 0, 0, 1, 1]]))
    with pytest.raises(ValueError, match="rotation"):
        dmlo_rs.RayScene(boxes=np.concatenate([[0, 0, 0], 2 * np.eye(3).ravel(), [1, 1, 1.0]])[None])
    with pytest.raises(TypeError):
        dmlo_rs.RayScene(cylinders=np.zeros((1, 5), dtype=np.float32))
    scene = dmlo_rs.RayScene(ellipsoids=np.array([[5, 0, 0, 1, 1, 1.0]]))
    with pytest.raises(ValueError, match="directions"):
        scene.cast(np.zeros((2, 3)), np.zeros((2, 3)), 10.0)
    with pytest.raises(ValueError, match="directions"):
        scene.cast(np.zeros((2, 3)), np.ones((3, 3)), 10.0)
    with pytest.raises(ValueError, match="origins"):
        scene.cast(np.full((1, 3), np.inf), np.ones((1, 3)), 10.0)
    with pytest.raises(ValueError, match="max_range"):
        scene.cast(np.zeros((1, 3)), np.ones((1, 3)), -1.0)
    with pytest.raises(ValueError, match="pose"):
        scene.cast_scan(np.ones((4, 4)), np.zeros(3), 10, 10.0)
    with pytest.raises(ValueError, match="pose"):
        scene.cast_scan(np.eye(3), np.zeros(3), 10, 10.0)
    with pytest.raises(ValueError, match="elevations_deg"):
        scene.cast_scan(np.eye(4), np.array([95.0]), 10, 10.0)
    with pytest.raises(ValueError, match="azimuth_count"):
        scene.cast_scan(np.eye(4), np.zeros(3), 0, 10.0)
    with pytest.raises(ValueError, match="azimuth_count.*exceeds"):
        scene.cast_scan(np.eye(4), np.zeros(64), 2_000_000, 10.0)
    with pytest.raises(ValueError, match="pose"):
        scene.cast_scan(np.tile(np.eye(4), (3, 1, 1)), np.zeros(2), 10, 10.0)  # 3 column poses for 10 columns
    empty = dmlo_rs.RayScene()
    assert len(empty) == 0
    ranges, primitive, _ = empty.cast(np.zeros((1, 3)), np.ones((1, 3)), 10.0)
    assert primitive[0] == -1
