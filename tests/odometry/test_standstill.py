"""A pair that stands still (issue 25, item 12): `register_pair` of a scan with itself is the identity, and
two real scans of a standing car come out within millimetres (projective point-to-plane ICP,
`dmlo.odometry.projective`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import dmlo_rs
from dmlo.datasets import open_sequence
from dmlo.metrics.trajectory import pose_difference
from dmlo.odometry import Odometry, OdometryConfig
from dmlo.odometry.projective import point_to_plane, surface_normals
from support import rigid


@pytest.fixture(scope="module")
def odometry() -> Odometry:
    return Odometry.from_default(OdometryConfig())


def test_a_scan_registered_with_itself_is_the_identity(odometry: Odometry, shared_data: Path) -> None:
    for name in ("odometry_01", "odometry_03", "raw_drive_22"):
        scan = open_sequence(shared_data / "kitti_real" / name)[0].points
        result = odometry.register_pair(scan, scan.copy())
        moved, turned = pose_difference(np.eye(4), result.T_tgt_ref)
        assert result.map_refined and moved <= 0.001 and turned <= 0.005, (name, moved, turned)


def test_a_standing_car_comes_out_within_millimetres(shared_data: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    sequence = open_sequence(shared_data / "kitti_raw_static")
    scans = [sequence[k].points for k in range(6)]

    def pair_motions() -> np.ndarray:
        odometry = Odometry.from_default(OdometryConfig())
        return np.array([pose_difference(np.eye(4), odometry.register_pair(a, b).T_tgt_ref) for a, b in zip(scans, scans[1:])])

    refined = pair_motions()
    monkeypatch.setattr("dmlo.odometry.pipeline.point_to_plane", lambda reference, target, transform, cylinder: transform)
    matches_alone = pair_motions()  # DMLO's estimate, which the planes refine
    assert refined[:, 0].max() < 0.003 and refined[:, 1].max() < 0.01, refined
    assert refined[:, 0].mean() < 0.5 * matches_alone[:, 0].mean(), (refined, matches_alone)


def test_point_to_plane_recovers_a_small_motion_and_leaves_open_directions_alone(shared_data: Path) -> None:
    cylinder = dmlo_rs.CylinderConfig.kitti()
    scan = open_sequence(shared_data / "kitti_real" / "odometry_03")[0].points

    def point_image(points: np.ndarray) -> np.ndarray:
        index = dmlo_rs.project(points.astype(np.float32), cylinder).index
        image = np.take(points[:, :3], np.maximum(index, 0), axis=0).astype(np.float32)
        image[index < 0] = np.nan
        return image

    truth = rigid([0.012, -0.008, 0.004], [0.02, -0.01, 0.05])  # T_tgt_ref: reference points into the target frame
    moved = scan.copy()
    moved[:, :3] = scan[:, :3] @ truth[:3, :3].T + truth[:3, 3]
    estimate = point_to_plane(point_image(scan), point_image(moved), np.eye(4), cylinder)
    error = np.linalg.inv(truth) @ estimate
    assert np.linalg.norm(error[:3, 3]) < 0.002
    assert Rotation.from_matrix(error[:3, :3]).magnitude() < np.radians(0.01)

    # A bare plane fixes only its normal direction, the height: the rest keeps the estimate given.
    xs, ys = np.meshgrid(np.linspace(-20, 20, 400), np.linspace(-20, 20, 400))
    floor = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, -1.7), np.zeros(xs.size)]).astype(np.float32)
    start = rigid([0.05, 0.03, 0.0], [0.0, 0.0, 0.0])
    lifted = floor.copy()
    lifted[:, 2] += 0.01
    estimate = point_to_plane(point_image(floor), point_image(lifted), start, cylinder)
    np.testing.assert_allclose(estimate[:2, 3], start[:2, 3], atol=1e-6)
    assert abs(estimate[2, 3] - 0.01) < 1e-3


def test_surface_normals_of_a_wall_and_its_edges() -> None:
    cylinder = dmlo_rs.CylinderConfig.kitti()
    ys, zs = np.meshgrid(np.linspace(-8, 8, 600), np.linspace(-1.5, 1.5, 120))
    wall = np.column_stack([np.full(ys.size, 10.0), ys.ravel(), zs.ravel(), np.zeros(ys.size)]).astype(np.float32)
    index = dmlo_rs.project(wall, cylinder).index
    image = np.take(wall[:, :3], np.maximum(index, 0), axis=0)
    image[index < 0] = np.nan
    normals = surface_normals(image)
    known = np.isfinite(normals[..., 0])
    assert known.sum() > 500
    np.testing.assert_allclose(np.abs(normals[known]), np.broadcast_to([1.0, 0.0, 0.0], normals[known].shape), atol=1e-3)
    # The wall's border cells lack a neighbour: unknown, not guessed.
    rows, cols = np.nonzero(np.isfinite(image[..., 0]))
    assert not known[rows.min(), cols.min()] and not known[rows.max(), cols.max()]
