use nalgebra::Vector3;

use super::*;
use crate::ray_noise::{ray_noise_refit, RayNoise};
use crate::rigid::rigid_transform;

#[allow(clippy::type_complexity)]
fn scene(
    seed: u64,
    n: usize,
    outlier_ratio: f64,
    noise: f64,
) -> (
    Vec<Point3<f64>>,
    Vec<Point3<f64>>,
    Isometry3<f64>,
    Vec<bool>,
) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let truth = Isometry3::new(
        Vector3::new(0.9, -0.05, 0.02),
        Vector3::new(0.003, -0.002, 0.04),
    );
    let mut src = Vec::new();
    let mut dst = Vec::new();
    let mut is_inlier = Vec::new();
    for i in 0..n {
        let p = Point3::new(
            rng.random_range(-40.0..40.0),
            rng.random_range(-40.0..40.0),
            rng.random_range(-2.0..3.0),
        );
        let outlier = (i as f64) < outlier_ratio * n as f64;
        let q = if outlier {
            Point3::new(
                rng.random_range(-40.0..40.0),
                rng.random_range(-40.0..40.0),
                rng.random_range(-2.0..3.0),
            )
        } else {
            truth * p
                + Vector3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                ) * noise
        };
        src.push(p);
        dst.push(q);
        is_inlier.push(!outlier);
    }
    (src, dst, truth, is_inlier)
}

/// The (src, dst) pairs `result` marks as inliers.
fn inlier_pairs(
    src: &[Point3<f64>],
    dst: &[Point3<f64>],
    result: &RansacResult,
) -> (Vec<Point3<f64>>, Vec<Point3<f64>>) {
    (0..src.len())
        .filter(|&i| result.inliers[i])
        .map(|i| (src[i], dst[i]))
        .unzip()
}

/// `work` run in a rayon pool of `threads` threads.
fn in_pool<T: Send>(threads: usize, work: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(work)
}

#[test]
fn recovers_a_known_motion_with_80_percent_outliers() {
    let (src, dst, truth, is_inlier) = scene(21, 1000, 0.8, 0.02);
    let result = ransac_rigid(&src, &dst, &RansacConfig::default()).unwrap();
    let rotation_error = (result.transform.rotation.inverse() * truth.rotation)
        .angle()
        .to_degrees();
    let translation_error = (result.transform.translation.vector - truth.translation.vector).norm();
    assert!(rotation_error < 0.05, "rotation error {rotation_error}°");
    assert!(
        translation_error < 0.02,
        "translation error {translation_error} m"
    );
    let wrong = result
        .inliers
        .iter()
        .zip(&is_inlier)
        .filter(|(a, b)| a != b)
        .count();
    assert!(wrong <= 3, "{wrong} matches misclassified");
    assert_eq!(
        result.num_inliers,
        result.inliers.iter().filter(|&&v| v).count()
    );
    // The answer is the least-squares fit on its inliers, not a noisy 3-match sample.
    let (inlier_src, inlier_dst) = inlier_pairs(&src, &dst, &result);
    let refit = rigid_transform(&inlier_src, &inlier_dst, None).unwrap();
    assert!(
        (refit.to_homogeneous() - result.transform.to_homogeneous())
            .abs()
            .max()
            < 1e-9
    );
    assert!(result.iterations <= 1000 && result.iterations > 0);
}

#[test]
fn answer_is_the_least_squares_fit_of_its_inliers_even_when_that_shrinks_the_consensus() {
    // Noise near the threshold: refits move matches in and out of the inlier set, and some
    // refit keeps fewer matches than the motion before it. The answer is still the fixed point
    // of "least squares on the inliers" (a refit is never rejected for its smaller consensus).
    for seed in 0..40 {
        let noise = [0.06, 0.08][(seed % 2) as usize];
        let (src, dst, _, _) = scene(100 + seed, 300, 0.4, noise);
        let config = RansacConfig {
            seed,
            ..Default::default()
        };
        let result = ransac_rigid(&src, &dst, &config).unwrap();
        let (inlier_src, inlier_dst) = inlier_pairs(&src, &dst, &result);
        let refit = rigid_transform(&inlier_src, &inlier_dst, None).unwrap();
        let gap = (refit.to_homogeneous() - result.transform.to_homogeneous())
            .abs()
            .max();
        assert!(
            gap < 1e-9,
            "seed {seed}: the answer is {gap} from the fit of its inliers"
        );
    }
}

#[test]
fn with_the_ray_noise_refit_the_answer_is_that_refit_of_its_inliers() {
    let (src, dst, truth, _) = scene(25, 600, 0.5, 0.03);
    let noise = RayNoise {
        range_ratio: 2.0,
        ..Default::default()
    };
    let config = RansacConfig {
        refit: Refit::RayNoise {
            noise: noise.clone(),
            bearing_threshold_deg: 0.0,
        },
        ..Default::default()
    };
    let result = ransac_rigid(&src, &dst, &config).unwrap();
    let (inlier_src, inlier_dst) = inlier_pairs(&src, &dst, &result);
    let closed_form = rigid_transform(&inlier_src, &inlier_dst, None).unwrap();
    let refit = ray_noise_refit(&inlier_src, &inlier_dst, &closed_form, &noise).unwrap();
    assert_eq!(result.transform, refit.transform);
    assert_ne!(result.transform, closed_form);
    let rotation_error = (result.transform.rotation.inverse() * truth.rotation).angle();
    assert!(rotation_error.to_degrees() < 0.05);
    let threads = |n: usize| in_pool(n, || ransac_rigid(&src, &dst, &config).unwrap());
    assert_eq!(threads(1), threads(3));
    // A target point at the sensor's origin has no ray: refused by name, not skipped silently.
    let mut at_origin = dst.clone();
    at_origin[7] = Point3::origin();
    assert!(matches!(
        ransac_rigid(&src, &at_origin, &config),
        Err(Error::InvalidArgument {
            argument: "dst",
            ..
        })
    ));
    assert!(ransac_rigid(&src, &at_origin, &RansacConfig::default()).is_ok());
}

#[test]
fn a_refit_solves_as_the_svd_solve_then_its_gauss_newton_refit() {
    let (src, dst, _, is_inlier) = scene(31, 300, 0.0, 0.03);
    assert!(is_inlier.iter().all(|&inlier| inlier));
    let closed_form = rigid_transform(&src, &dst, None).unwrap();
    assert_eq!(Refit::PointToPoint.solve(&src, &dst).unwrap(), closed_form);
    let noise = RayNoise {
        range_ratio: 2.0,
        ..Default::default()
    };
    let ray = Refit::RayNoise {
        noise: noise.clone(),
        bearing_threshold_deg: 0.2,
    };
    let refined = ray_noise_refit(&src, &dst, &closed_form, &noise).unwrap();
    assert_eq!(ray.solve(&src, &dst).unwrap(), refined.transform);
    assert_ne!(refined.transform, closed_form);
    // Its own settings are checked before anything is solved.
    let bad = Refit::RayNoise {
        noise: RayNoise {
            range_ratio: 0.0,
            ..Default::default()
        },
        bearing_threshold_deg: 0.2,
    };
    assert!(matches!(
        bad.solve(&src, &dst),
        Err(Error::InvalidArgument {
            argument: "range_ratio",
            ..
        })
    ));
}

#[test]
fn ray_noise_inliers_lie_in_an_ellipsoid_stretched_across_the_ray_at_range() {
    let matches = Matches::new(
        &[Point3::new(60.0, 0.0, 0.0); 4],
        &[
            Point3::new(60.0, 0.15, 0.0), // 0.15 m across the ray at 60 m: within 0.2°
            Point3::new(60.0, 0.0, -0.25), // 0.25 m across: beyond 0.2° (0.209 m)
            Point3::new(60.15, 0.0, 0.0), // 0.15 m along the ray: beyond the 0.1 m threshold
            Point3::new(60.07, 0.1, 0.0), // (0.07/0.1)² + (0.1/0.209)² = 0.72
        ],
        None,
    );
    let tan = 0.2f64.to_radians().tan();
    let identity = Isometry3::identity();
    assert_eq!(
        matches.ray_inlier_mask(&identity, 0.1, tan),
        [true, false, false, true]
    );
    // Within the threshold's own radius the test is the Euclidean one.
    assert_eq!(
        matches.ray_inlier_mask(&identity, 0.1, 0.0),
        matches.inlier_mask(&identity, 0.01)
    );
    let near = Matches::new(
        &[Point3::new(5.0, 0.0, 0.0)],
        &[Point3::new(5.0, 0.09, 0.0)],
        None,
    );
    assert_eq!(near.ray_inlier_mask(&identity, 0.1, tan), [true]);
}

/// A highway pair: many road matches that agree on no motion at all (the rings locked) with a
/// low vote, fewer matches on posts that agree on the true motion, and outliers.
#[allow(clippy::type_complexity)]
fn locked_rings(seed: u64) -> (Vec<Point3<f64>>, Vec<Point3<f64>>, Vec<f64>, Isometry3<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let truth = Isometry3::new(Vector3::new(-1.0, 0.05, 0.0), Vector3::new(0.0, 0.0, 0.03));
    let (mut src, mut dst, mut votes) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..600 {
        let angle: f64 = rng.random_range(0.0..std::f64::consts::TAU);
        let range: f64 = rng.random_range(4.0..15.0);
        let road = Point3::new(range * angle.cos(), range * angle.sin(), -1.73);
        let post = Point3::new(
            rng.random_range(-30.0..30.0),
            rng.random_range(-12.0..12.0),
            rng.random_range(-1.0..3.0),
        );
        let (p, q, vote) = match i % 6 {
            0..=3 => (road, road, 0.05), // locked: the same point in both scans
            4 => (post, truth * post, 1.0),
            _ => {
                let q = Point3::new(
                    rng.random_range(-30.0..30.0),
                    rng.random_range(-12.0..12.0),
                    rng.random_range(-1.0..3.0),
                );
                (post, q, rng.random_range(0.05..1.0))
            }
        };
        src.push(p);
        dst.push(q);
        votes.push(vote);
    }
    (src, dst, votes, truth)
}

#[test]
fn votes_keep_locked_road_matches_from_outvoting_the_posts() {
    let (src, dst, votes, truth) = locked_rings(5);
    let config = RansacConfig::default();
    let counted = ransac_rigid(&src, &dst, &config).unwrap();
    assert!(
        counted.transform.translation.vector.norm() < 0.05,
        "the rings win a count"
    );
    let voted = ransac_rigid_voted(&src, &dst, Some(&votes), &config).unwrap();
    let error = voted.transform.inverse() * truth;
    assert!(error.translation.vector.norm() < 1e-6, "{error:?}");
    assert_eq!(voted.num_inliers, 100);
}

#[test]
fn equal_votes_change_nothing_and_voting_is_thread_independent() {
    let (src, dst, _, _) = scene(23, 500, 0.5, 0.05);
    let config = RansacConfig::default();
    let counted = ransac_rigid(&src, &dst, &config).unwrap();
    let ones = vec![1.0; src.len()];
    assert_eq!(
        ransac_rigid_voted(&src, &dst, Some(&ones), &config)
            .unwrap()
            .transform,
        counted.transform
    );
    let (src, dst, votes, _) = locked_rings(6);
    let config = RansacConfig {
        batch_size: 16,
        ..Default::default()
    };
    let run = |threads: usize| {
        in_pool(threads, || {
            ransac_rigid_voted(&src, &dst, Some(&votes), &config).unwrap()
        })
    };
    assert_eq!(run(1), run(3));
}

#[test]
fn bad_votes_are_named() {
    let (src, dst, _, _) = scene(24, 20, 0.0, 0.0);
    let config = RansacConfig::default();
    for votes in [
        vec![1.0; 19],
        vec![-1.0; 20],
        vec![f64::NAN; 20],
        vec![0.0; 20],
    ] {
        let err = ransac_rigid_voted(&src, &dst, Some(&votes), &config).unwrap_err();
        assert!(err.to_string().starts_with("votes:"), "{err}");
    }
    // Fewer than 3 matches with a vote: samples are drawn uniformly, never stuck.
    let mut two = vec![0.0; 20];
    two[0] = 1.0;
    two[1] = 1.0;
    ransac_rigid_voted(&src, &dst, Some(&two), &config).unwrap();
}

#[test]
fn same_seed_same_result_with_1_or_4_threads() {
    let (src, dst, _, _) = scene(22, 2000, 0.7, 0.05);
    let config = RansacConfig {
        seed: 9,
        batch_size: 16,
        ..Default::default()
    };
    let run = |threads: usize| in_pool(threads, || ransac_rigid(&src, &dst, &config).unwrap());
    let one = run(1);
    let four = run(4);
    assert_eq!(one, four);
    // The batch size changes only speed.
    let other_batches = in_pool(2, || {
        ransac_rigid(
            &src,
            &dst,
            &RansacConfig {
                batch_size: 100,
                ..config.clone()
            },
        )
        .unwrap()
    });
    assert_eq!(one, other_batches);
    let different_seed = ransac_rigid(&src, &dst, &RansacConfig { seed: 10, ..config }).unwrap();
    assert!(
        different_seed.iterations != one.iterations || different_seed.transform != one.transform
    );
}

#[test]
fn adaptive_iterations_stop_early_on_clean_data() {
    let (src, dst, truth, _) = scene(23, 500, 0.0, 0.0);
    let result = ransac_rigid(&src, &dst, &RansacConfig::default()).unwrap();
    assert_eq!(result.num_inliers, 500);
    assert!(result.iterations < 10, "{} iterations", result.iterations);
    assert!(
        (result.transform.to_homogeneous() - truth.to_homogeneous())
            .abs()
            .max()
            < 1e-9
    );
    assert!(result.rmse < 1e-9);
}

#[test]
fn inliers_are_counted_exactly_far_from_the_origin() {
    // Georeferenced (UTM-like) coordinates: the same scene and motion moved millions of metres from
    // the origin must give the same consensus as near it.
    for (outlier_ratio, noise) in [(0.0, 0.0), (0.3, 0.02)] {
        let (src, dst, truth, is_inlier) = scene(26, 200, outlier_ratio, noise);
        let near = ransac_rigid(&src, &dst, &RansacConfig::default()).unwrap();
        assert_eq!(near.inliers, is_inlier);
        for offset in [1e6, 5e6, 1e7] {
            let shift = Isometry3::translation(offset, -0.7 * offset, 30.0);
            let (far_src, far_dst): (Vec<_>, Vec<_>) = src
                .iter()
                .zip(&dst)
                .map(|(p, q)| (shift * p, shift * q))
                .unzip();
            let far_truth = shift * truth * shift.inverse();
            let far = ransac_rigid(&far_src, &far_dst, &RansacConfig::default()).unwrap();
            assert_eq!(far.inliers, is_inlier, "offset {offset} m");
            assert_eq!(far.num_inliers, near.num_inliers, "offset {offset} m");
            assert!(
                far.iterations <= near.iterations.max(10),
                "offset {offset} m"
            );
            let rotation_error = (far.transform.rotation.inverse() * far_truth.rotation).angle();
            assert!(rotation_error.to_degrees() < 0.05, "offset {offset} m");
            // The motion moves the scene's own points as the truth does, to well under the noise.
            let worst = far_src
                .iter()
                .map(|p| (far.transform * p - far_truth * p).norm())
                .fold(0.0, f64::max);
            assert!(worst < 0.02 + noise, "offset {offset} m: {worst} m");
            assert!((far.rmse - near.rmse).abs() < 1e-6, "offset {offset} m");
            let threads = |n: usize| {
                in_pool(n, || {
                    ransac_rigid(&far_src, &far_dst, &RansacConfig::default())
                })
            };
            assert_eq!(threads(1), threads(3));
        }
    }
}

#[test]
fn a_local_scan_is_registered_into_far_map_coordinates() {
    // Source near its sensor, target in map coordinates millions of metres away: each side is
    // scored relative to a point of its own, not one shared reference between them.
    let (src, local_dst, truth, is_inlier) = scene(27, 200, 0.3, 0.02);
    let to_map = Isometry3::new(
        Vector3::new(4.5e6, 5.4e6, 120.0),
        Vector3::new(0.0, 0.0, 2.0),
    );
    let dst: Vec<_> = local_dst.iter().map(|q| to_map * q).collect();
    let result = ransac_rigid(&src, &dst, &RansacConfig::default()).unwrap();
    assert_eq!(result.inliers, is_inlier);
    let rotation_error = (result.transform.rotation.inverse() * (to_map * truth).rotation).angle();
    assert!(rotation_error.to_degrees() < 0.05);
}

#[test]
fn an_answer_without_any_inlier_is_an_error_not_an_empty_consensus() {
    // Only outliers and a threshold far below every residual: no motion has a single inlier.
    let (src, dst, _, _) = scene(28, 100, 1.0, 0.0);
    let config = RansacConfig {
        threshold: 1e-9,
        max_iterations: 50,
        ..Default::default()
    };
    assert!(matches!(
        ransac_rigid(&src, &dst, &config),
        Err(Error::Degenerate(_))
    ));
}

#[test]
fn few_degenerate_and_outlier_only_inputs_do_not_panic_or_hang() {
    let p = |x: f64| Point3::new(x, 2.0 * x, -x);
    assert_eq!(
        ransac_rigid(
            &[p(0.0), p(1.0)],
            &[p(0.0), p(1.0)],
            &RansacConfig::default()
        ),
        Err(Error::TooFewPoints { needed: 3, got: 2 })
    );
    let line: Vec<_> = (0..50).map(|i| p(i as f64)).collect();
    assert!(matches!(
        ransac_rigid(&line, &line, &RansacConfig::default()),
        Err(Error::Degenerate(_))
    ));
    let (src, dst, _, _) = scene(24, 300, 1.0, 0.0);
    let result = ransac_rigid(&src, &dst, &RansacConfig::default()).unwrap();
    assert!(result.num_inliers < 10);
    assert_eq!(result.iterations, 1000);
    for bad in [
        RansacConfig {
            threshold: 0.0,
            ..Default::default()
        },
        RansacConfig {
            confidence: 1.0,
            ..Default::default()
        },
        RansacConfig {
            max_iterations: 0,
            ..Default::default()
        },
    ] {
        assert!(matches!(
            ransac_rigid(&src, &dst, &bad),
            Err(Error::InvalidArgument { .. })
        ));
    }
    let three = [
        Point3::new(0.0, 0.0, 0.0),
        Point3::new(1.0, 0.0, 0.0),
        Point3::new(0.0, 1.0, 0.0),
    ];
    assert_eq!(
        ransac_rigid(&three, &three, &RansacConfig::default())
            .unwrap()
            .num_inliers,
        3
    );
}
