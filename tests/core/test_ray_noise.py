"""The ray-noise refit (dmlo_rs.ray_noise_refit, ransac_rigid(refit="ray_noise")) against scipy's
least squares on the whitened residuals."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

import dmlo_rs

from support import frame_to_frame, rigid, transform_points

FloatArray = npt.NDArray[np.float64]


def scan_pairs(
    rng: np.random.Generator, n: int, truth: FloatArray, bearing_noise_deg: float, range_noise: float
) -> tuple[FloatArray, FloatArray]:
    """Street-like reference points 2–60 m around the sensor and their targets under `truth`, moved by
    Gaussian bearing noise across the ray and range noise along it."""
    ranges = rng.uniform(2, 60, n)
    azimuth = rng.uniform(-np.pi, np.pi, n)
    elevation = rng.uniform(-0.4, 0.03, n)
    src = ranges[:, None] * np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=1
    )
    dst = transform_points(truth, src)
    ray = dst / np.linalg.norm(dst, axis=1, keepdims=True)
    lateral = rng.normal(scale=np.radians(bearing_noise_deg), size=(n, 3)) * np.linalg.norm(dst, axis=1)[:, None]
    lateral -= ray * np.sum(lateral * ray, axis=1, keepdims=True)
    dst = dst + lateral + ray * rng.normal(scale=range_noise, size=(n, 1))
    return src, dst


def scipy_ray_noise_fit(src: FloatArray, dst: FloatArray, start: FloatArray, range_ratio: float) -> FloatArray:
    """The same maximum-likelihood motion by scipy: residuals whitened by Ω^½ = (I − nnᵀ)/r + nnᵀ/r*."""
    ranges = np.linalg.norm(dst, axis=1, keepdims=True)
    rays = dst / ranges

    def residuals(x: FloatArray) -> FloatArray:
        error = src @ Rotation.from_rotvec(x[:3]).as_matrix().T + x[3:] - dst
        along = np.sum(error * rays, axis=1, keepdims=True)
        return ((error - along * rays) / ranges + along * rays / range_ratio).ravel()

    x0 = np.concatenate([Rotation.from_matrix(start[:3, :3]).as_rotvec(), start[:3, 3]])
    solution = least_squares(residuals, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return rigid(list(solution.x[3:]), list(np.degrees(solution.x[:3])))


def rotation_error_deg(a: FloatArray, b: FloatArray) -> float:
    return float(np.degrees(Rotation.from_matrix(a[:3, :3].T @ b[:3, :3]).magnitude()))


@pytest.mark.parametrize("range_ratio", [0.5, 3.0, 30.0])
def test_refit_equals_scipy_least_squares(range_ratio: float) -> None:
    rng = np.random.default_rng(1)
    for _ in range(5):
        truth = rigid(list(rng.normal(scale=0.5, size=3)), list(rng.normal(scale=2.0, size=3)))
        src, dst = scan_pairs(rng, 300, truth, bearing_noise_deg=0.1, range_noise=0.03)
        start = dmlo_rs.rigid_transform(src, dst)
        refit = dmlo_rs.ray_noise_refit(src, dst, start, range_ratio=range_ratio)
        reference = scipy_ray_noise_fit(src, dst, start, range_ratio)
        np.testing.assert_allclose(refit.transform, reference, atol=1e-8)
        assert refit.converged and 1 <= refit.iterations <= 20
        assert refit.transform.dtype == np.float64 and refit.transform.shape == (4, 4)


def test_refit_weighs_distant_matches_down_and_beats_the_closed_form_solve() -> None:
    rng = np.random.default_rng(2)
    truth = rigid([0.8, 0.02, 0.0], [0.0, 0.1, 1.5])
    closed_form, refit = [], []
    for _ in range(30):
        src, dst = scan_pairs(rng, 400, truth, bearing_noise_deg=0.05, range_noise=0.02)
        start = dmlo_rs.rigid_transform(src, dst)
        closed_form.append(rotation_error_deg(start, truth))
        refit.append(rotation_error_deg(dmlo_rs.ray_noise_refit(src, dst, start, range_ratio=23.0).transform, truth))
    assert np.mean(refit) < 0.85 * np.mean(closed_form), (np.mean(refit), np.mean(closed_form))


def test_ransac_with_the_ray_noise_refit_answers_the_refit_of_its_inliers() -> None:
    rng = np.random.default_rng(3)
    truth = rigid([0.9, -0.05, 0.02], [0.2, -0.3, 2.5])
    src, dst = scan_pairs(rng, 800, truth, bearing_noise_deg=0.05, range_noise=0.02)
    outliers = rng.random(len(src)) < 0.5
    dst[outliers] = transform_points(truth, src[outliers]) + rng.normal(scale=2.0, size=(int(outliers.sum()), 3))
    plain = dmlo_rs.ransac_rigid(src, dst, seed=4)
    ray = dmlo_rs.ransac_rigid(src, dst, seed=4, refit="ray_noise", range_ratio=5.0)
    # Its fixed point: the closed-form solve of its inliers, refined under ray noise.
    inliers = ray.inliers
    start = dmlo_rs.rigid_transform(src[inliers], dst[inliers])
    expected = dmlo_rs.ray_noise_refit(src[inliers], dst[inliers], start, range_ratio=5.0).transform
    np.testing.assert_allclose(ray.transform, expected, atol=1e-12)
    assert not np.allclose(ray.transform, plain.transform, atol=1e-9)
    assert ray.num_inliers == inliers.sum() >= 0.45 * len(src)
    threads = [dmlo_rs.ransac_rigid(src, dst, seed=4, refit="ray_noise", range_ratio=5.0, num_threads=n) for n in (1, 2)]
    np.testing.assert_array_equal(threads[0].transform, threads[1].transform)
    np.testing.assert_array_equal(threads[0].inliers, threads[1].inliers)


def test_refit_rigid_solves_given_inliers_as_ransac_refits_do() -> None:
    rng = np.random.default_rng(5)
    truth = rigid([0.7, 0.1, -0.02], [0.1, 0.2, -1.0])
    src, dst = scan_pairs(rng, 300, truth, bearing_noise_deg=0.1, range_noise=0.03)
    closed_form = dmlo_rs.rigid_transform(src, dst)
    np.testing.assert_array_equal(dmlo_rs.refit_rigid(src, dst), closed_form)
    ray = dmlo_rs.refit_rigid(src, dst, refit="ray_noise", range_ratio=3.0)
    np.testing.assert_allclose(ray, scipy_ray_noise_fit(src, dst, closed_form, 3.0), atol=1e-8)
    assert ray.dtype == np.float64 and ray.shape == (4, 4)
    # RANSAC's answer is this solve of its own inliers.
    ransac = dmlo_rs.ransac_rigid(src, dst, seed=2, refit="ray_noise", range_ratio=3.0)
    refit = dmlo_rs.refit_rigid(src[ransac.inliers], dst[ransac.inliers], refit="ray_noise", range_ratio=3.0)
    np.testing.assert_allclose(ransac.transform, refit, atol=1e-12)


def test_bad_input_is_named() -> None:
    rng = np.random.default_rng(4)
    src, dst = scan_pairs(rng, 20, np.eye(4), 0.05, 0.02)
    with pytest.raises(ValueError, match="refit"):
        dmlo_rs.ransac_rigid(src, dst, refit="ray")
    with pytest.raises(ValueError, match="range_ratio"):
        dmlo_rs.ransac_rigid(src, dst, refit="ray_noise", range_ratio=0.0)
    with pytest.raises(ValueError, match="range_ratio"):
        dmlo_rs.ray_noise_refit(src, dst, np.eye(4), range_ratio=-1.0)
    with pytest.raises(ValueError, match="refit"):
        dmlo_rs.refit_rigid(src, dst, refit="plane")
    with pytest.raises(ValueError, match="range_ratio"):
        dmlo_rs.refit_rigid(src, dst, refit="ray_noise", range_ratio=float("nan"))
    with pytest.raises(dmlo_rs.RegistrationError):
        dmlo_rs.refit_rigid(src[:2], dst[:2], refit="ray_noise")
    for angle in (-0.1, 90.0, float("nan")):
        with pytest.raises(ValueError, match="bearing_threshold_deg"):
            dmlo_rs.ransac_rigid(src, dst, refit="ray_noise", bearing_threshold_deg=angle)
    at_origin = dst.copy()
    at_origin[3] = 0.0
    with pytest.raises(ValueError, match="dst: point 3 lies within"):
        dmlo_rs.ray_noise_refit(src, at_origin, np.eye(4))
    with pytest.raises(ValueError, match="dst: point 3 lies within"):
        dmlo_rs.ransac_rigid(src, at_origin, refit="ray_noise")
    with pytest.raises(ValueError, match="dst: point 3 lies within"):
        dmlo_rs.refit_rigid(src, at_origin, refit="ray_noise")
    # The closed-form refit needs no rays: a point at the origin is an ordinary point there.
    dmlo_rs.ransac_rigid(src, at_origin)
    with pytest.raises(ValueError, match="initial"):
        dmlo_rs.ray_noise_refit(src, dst, np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="initial"):
        dmlo_rs.ray_noise_refit(src, dst, np.eye(3))
    with pytest.raises(ValueError, match="src"):
        dmlo_rs.ray_noise_refit(np.full_like(src, np.nan), dst, np.eye(4))
    with pytest.raises(ValueError, match="max_iterations"):
        dmlo_rs.ray_noise_refit(src, dst, np.eye(4), max_iterations=0)
    with pytest.raises(dmlo_rs.RegistrationError):
        dmlo_rs.ray_noise_refit(src[:2], dst[:2], np.eye(4))
    line = np.outer(np.arange(1.0, 20.0), [1.0, 2.0, 0.1])
    with pytest.raises(dmlo_rs.RegistrationError, match="degenerate"):
        dmlo_rs.ray_noise_refit(line, line, np.eye(4))


# ---- in the odometry (config.ransac.refit) --------------------------------------------------------------


@pytest.fixture(scope="module")
def pair_scans(tmp_path_factory: pytest.TempPathFactory) -> list[np.ndarray]:
    from dmlo.datasets import open_sequence
    from dmlo.simulator import simulate_sequence

    out = tmp_path_factory.mktemp("drive")
    simulate_sequence(out, frames=2, seed=5, progress=False)
    sequence = open_sequence(out)
    return [sequence[i].points for i in range(len(sequence))]


def test_the_odometry_solves_its_pairs_as_configured(pair_scans: list[np.ndarray]) -> None:
    from dmlo.odometry import Odometry

    config = frame_to_frame()
    config.ransac.refit, config.ransac.ray_range_ratio = "ray_noise", 4.0
    pair = Odometry.from_default(config).register_pair(*pair_scans)
    src, dst = pair.source_points[pair.inliers], pair.target_points[pair.inliers]
    start = dmlo_rs.rigid_transform(src, dst)
    np.testing.assert_allclose(
        pair.T_tgt_ref, dmlo_rs.ray_noise_refit(src, dst, start, range_ratio=4.0).transform, atol=1e-12
    )
    config.ransac.refit = "point_to_point"
    plain = Odometry.from_default(config).register_pair(*pair_scans)
    src, dst = plain.source_points[plain.inliers], plain.target_points[plain.inliers]
    np.testing.assert_allclose(plain.T_tgt_ref, dmlo_rs.rigid_transform(src, dst), atol=1e-12)


@pytest.mark.parametrize(
    ("refit", "ratio", "message"),
    [("ray", 3.0, r"ransac.refit: must be one of point_to_point, ray_noise, got \"ray\""),
     ("ray_noise", 0.0, r"ransac.ray_range_ratio: must be a number > 0"),
     ("ray_noise", "3", r"ransac.ray_range_ratio: must be a number > 0")],
)
def test_a_bad_refit_setting_is_refused_up_front(refit: str, ratio: object, message: str) -> None:
    from dmlo.odometry import Odometry

    config = frame_to_frame()
    config.ransac.refit, config.ransac.ray_range_ratio = refit, ratio  # type: ignore[assignment]
    with pytest.raises(ValueError, match=message):
        Odometry.from_default(config)


@pytest.mark.parametrize(
    ("angle", "message"),
    [(-1.0, r"ransac.ray_bearing_threshold_deg: must be a number >= 0"),
     (90.0, r"ransac.ray_bearing_threshold_deg: must be a number >= 0 and < 90, got 90.0")],
)
def test_a_bad_bearing_threshold_is_refused_up_front(angle: float, message: str) -> None:
    from dmlo.odometry import Odometry

    config = frame_to_frame()
    config.ransac.ray_bearing_threshold_deg = angle
    with pytest.raises(ValueError, match=message):
        Odometry.from_default(config)
