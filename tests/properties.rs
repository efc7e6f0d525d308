//! Property-based tests of the crate's public entry points (issue 25, and the odometry's loop of issue
//! 24): random and adversarial input (NaN, infinities, huge coordinates, empty and mismatched slices, any
//! settings) gives a valid result or an `Error`, never a panic or a hang; and exact pairs give their
//! motion back, wherever they lie.
//!
//! Few cases each, so that `cargo test --release` stays fast; no regression files are written (a
//! failure prints its minimal case: add it to the unit tests of the module at fault).

use dmlo_rs::dense_match::DenseFlow;
use dmlo_rs::nms::nms_wrapping;
use dmlo_rs::odometry::config::OdometryConfig;
use dmlo_rs::odometry::moving::MovingObjectNetwork;
use dmlo_rs::odometry::pipeline::{FrameMatcher, Odometry, Scan};
use dmlo_rs::projection::{project_flat, unproject_many, CylinderConfig};
use dmlo_rs::ransac::{ransac_rigid_voted, RansacConfig, Refit};
use dmlo_rs::ray_noise::RayNoise;
use dmlo_rs::rigid::rigid_transform;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use proptest::prelude::*;
use proptest::test_runner::Config;

/// `cases` for CI; `DMLO_PROPERTY_SCALE=50` runs fifty times as many to hunt for bugs.
fn config(cases: u32) -> Config {
    let scale: f64 = std::env::var("DMLO_PROPERTY_SCALE")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1.0);
    Config {
        cases: ((cases as f64 * scale) as u32).max(1),
        failure_persistence: None,
        ..Config::default()
    }
}

/// Floats as a scan or a pose may hold them: mostly ordinary, sometimes what breaks arithmetic.
fn coordinate() -> impl Strategy<Value = f64> {
    prop_oneof![
        6 => -150.0..150.0f64,
        1 => prop::sample::select(vec![
            0.0, -0.0, 1e-300, 1e-30, 1e7, -1e7, 1e15, 1e30, 3.4e38, 1e300, f64::MAX, f64::MIN,
            f64::NAN, f64::INFINITY, f64::NEG_INFINITY,
        ]),
        1 => any::<f64>(),
    ]
}

fn points(max: usize) -> impl Strategy<Value = Vec<Point3<f64>>> {
    prop::collection::vec(
        (coordinate(), coordinate(), coordinate()).prop_map(|(x, y, z)| Point3::new(x, y, z)),
        0..max,
    )
}

fn cylinder_config() -> impl Strategy<Value = CylinderConfig> {
    let kitti = CylinderConfig::kitti();
    prop_oneof![
        3 => Just(kitti),
        3 => (-5.0..30.0f64, 1.0..40.0f64, 0.1..2.0f64, 0.1..5.0f64, 0.0..1.0f64, 0.0..1.0f64).prop_map(
            |(up, span, vertical, horizontal, h, w)| CylinderConfig {
                fov_up_deg: up,
                fov_down_deg: up - span,
                vertical_resolution_deg: vertical,
                horizontal_resolution_deg: horizontal,
                height: ((span / vertical + 1.0) * h).max(1.0) as usize,
                width: ((360.0 / horizontal) * w).max(1.0) as usize,
            }
        ),
        1 => (any::<f64>(), any::<f64>(), any::<f64>(), any::<f64>(), any::<usize>(), any::<usize>()).prop_map(
            |(up, down, vertical, horizontal, height, width)| CylinderConfig {
                fov_up_deg: up,
                fov_down_deg: down,
                vertical_resolution_deg: vertical,
                horizontal_resolution_deg: horizontal,
                height,
                width,
            }
        ),
        1 => (prop::sample::select(vec![1e-7, 1e-5, 1e-300, 0.0, -0.2, f64::NAN]), 1usize..40_000_000).prop_map(
            |(resolution, width)| CylinderConfig {
                horizontal_resolution_deg: resolution,
                width,
                ..CylinderConfig::kitti()
            }
        ),
    ]
}

fn assert_rigid(transform: &Isometry3<f64>) {
    let matrix = transform.to_homogeneous();
    assert!(matrix.iter().all(|v| v.is_finite()), "{matrix}");
    let rotation = transform.rotation.to_rotation_matrix().into_inner();
    assert!(
        (rotation.transpose() * rotation - nalgebra::Matrix3::identity())
            .abs()
            .max()
            < 1e-6
    );
    assert!(rotation.determinant() > 0.0);
}

proptest! {
    #![proptest_config(config(64))]

    #[test]
    fn project_gives_a_consistent_image_or_an_error(
        cloud in prop::collection::vec(coordinate(), 0..1200),
        channels in prop::sample::select(vec![3usize, 4, 4, 0, 2, 5]),
        config in cylinder_config(),
    ) {
        let flat: Vec<f32> = cloud.iter().map(|&v| v as f32).collect();
        if let Ok(projection) = project_flat(&flat, channels, &config) {
            let n = flat.len() / channels;
            let cells = config.height * config.width;
            prop_assert_eq!(projection.range.len(), cells);
            prop_assert_eq!(projection.index.len(), cells);
            let mut seen = vec![false; n];
            for (cell, &index) in projection.index.iter().enumerate() {
                let range = projection.range[cell];
                prop_assert!(range.is_finite() && range >= 0.0);
                prop_assert_eq!(index >= 0, range > 0.0);
                if index >= 0 {
                    prop_assert!((index as usize) < n && !seen[index as usize]);
                    seen[index as usize] = true;
                }
            }
            prop_assert!(projection.num_non_finite + projection.num_out_of_view + projection.num_valid() <= n);
        }
    }

    #[test]
    fn unproject_gives_finite_points_or_an_error(
        locations in prop::collection::vec((coordinate(), coordinate(), coordinate()), 0..50),
        config in cylinder_config(),
    ) {
        let rows: Vec<f64> = locations.iter().map(|l| l.0).collect();
        let cols: Vec<f64> = locations.iter().map(|l| l.1).collect();
        let ranges: Vec<f64> = locations.iter().map(|l| l.2).collect();
        if let Ok(unprojected) = unproject_many(&rows, &cols, &ranges, &config) {
            prop_assert_eq!(unprojected.len(), rows.len());
        }
    }

    #[test]
    fn rigid_transform_is_rigid_or_an_error(
        src in points(40),
        shift in (coordinate(), coordinate(), coordinate()),
        weights in prop::option::of(prop::collection::vec(coordinate(), 0..40)),
    ) {
        let dst: Vec<Point3<f64>> = src.iter().map(|p| p + Vector3::new(shift.0, shift.1, shift.2)).collect();
        if let Ok(transform) = rigid_transform(&src, &dst, weights.as_deref()) {
            assert_rigid(&transform);
        }
    }

    #[test]
    fn ransac_gives_a_consistent_result_or_an_error(
        src in points(60),
        random_dst in points(60),
        exact in any::<bool>(),
        votes in prop::option::of(prop::collection::vec(coordinate(), 0..60)),
        threshold in prop_oneof![4 => 1e-3..1.0f64, 1 => coordinate()],
        confidence in prop_oneof![4 => 0.5..0.9999f64, 1 => coordinate()],
        max_iterations in prop_oneof![4 => 1usize..300, 1 => Just(0usize)],
        seed in any::<u64>(),
        batch_size in prop_oneof![4 => 1usize..100, 1 => Just(0usize)],
        refine_iterations in 0usize..12,
        ray_noise in any::<bool>(),
        range_ratio in prop_oneof![4 => 0.5..20.0f64, 1 => coordinate()],
        bearing in prop_oneof![4 => 0.0..1.0f64, 1 => coordinate()],
    ) {
        let dst = if exact { src.iter().map(|p| p + Vector3::new(0.3, -0.2, 0.1)).collect() } else { random_dst };
        let refit = if ray_noise {
            Refit::RayNoise {
                noise: RayNoise { range_ratio, max_iterations: 20 },
                bearing_threshold_deg: bearing,
            }
        } else {
            Refit::PointToPoint
        };
        let config = RansacConfig {
            threshold, confidence, max_iterations, seed, batch_size, refine_iterations, refit,
        };
        if let Ok(result) = ransac_rigid_voted(&src, &dst, votes.as_deref(), &config) {
            assert_rigid(&result.transform);
            prop_assert_eq!(result.inliers.len(), src.len());
            prop_assert_eq!(result.num_inliers, result.inliers.iter().filter(|&&b| b).count());
            prop_assert!(result.num_inliers >= 1);
            prop_assert!(result.rmse.is_finite() && result.rmse >= 0.0);
            prop_assert!(result.iterations <= max_iterations.max(1));
        }
    }

    #[test]
    fn nms_keeps_distinct_valid_indices_or_errors(
        entries in prop::collection::vec((-2i64..300, -2i64..2000, prop_oneof![8 => -1.0..1.0f32, 1 => Just(f32::NAN), 1 => Just(f32::INFINITY)]), 0..300),
        radius in prop_oneof![4 => 0usize..5, 1 => Just(usize::MAX), 1 => Just(usize::MAX / 2)],
        top_n in prop::option::of(prop_oneof![0usize..400, Just(usize::MAX)]),
        period in prop::option::of(prop_oneof![0usize..3000, Just(usize::MAX)]),
    ) {
        let rows: Vec<i64> = entries.iter().map(|e| e.0).collect();
        let cols: Vec<i64> = entries.iter().map(|e| e.1).collect();
        let scores: Vec<f32> = entries.iter().map(|e| e.2).collect();
        if let Ok(kept) = nms_wrapping(&rows, &cols, &scores, radius, top_n, period) {
            prop_assert!(kept.len() <= top_n.unwrap_or(usize::MAX).min(entries.len()));
            let mut sorted = kept.clone();
            sorted.sort_unstable();
            sorted.dedup();
            prop_assert_eq!(sorted.len(), kept.len());
            prop_assert!(kept.iter().all(|&i| i < entries.len()));
            prop_assert!(kept.windows(2).all(|w| scores[w[0]] >= scores[w[1]]));
        }
    }
}

proptest! {
    #![proptest_config(config(32))]

    /// Exact pairs at any offset (UTM-like coordinates: issue 25, item 8) and with outliers: RANSAC
    /// finds every exact pair an inlier and no outlier, and the motion.
    #[test]
    fn ransac_recovers_a_motion_anywhere(
        n in 3usize..80,
        seed in any::<u64>(),
        offset in prop::sample::select(vec![0.0, 1e3, 1e6, 5e6, 1e7]),
        outlier_share in 0.0..0.3f64,
        axis in (-1.0..1.0f64, -1.0..1.0f64, 0.1..1.0f64),
        angle in -0.5..0.5f64,
        translation in (-3.0..3.0f64, -3.0..3.0f64, -1.0..1.0f64),
    ) {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let truth = Isometry3::from_parts(
            Translation3::new(translation.0, translation.1, translation.2),
            UnitQuaternion::from_scaled_axis(Vector3::new(axis.0, axis.1, axis.2).normalize() * angle),
        );
        let src: Vec<Point3<f64>> = (0..n)
            .map(|_| Point3::new(
                offset + rng.random_range(-20.0..20.0),
                offset + rng.random_range(-20.0..20.0),
                rng.random_range(-3.0..3.0),
            ))
            .collect();
        let outlier: Vec<bool> = (0..n).map(|i| i >= 3 && rng.random_bool(outlier_share)).collect();
        let dst: Vec<Point3<f64>> = src
            .iter()
            .zip(&outlier)
            .map(|(p, &bad)| {
                let moved = truth * p;
                if bad { moved + Vector3::new(5.0, rng.random_range(-9.0..9.0), 2.0) } else { moved }
            })
            .collect();
        let config = RansacConfig { threshold: 0.05, max_iterations: 2000, ..RansacConfig::default() };
        let result = ransac_rigid_voted(&src, &dst, None, &config).unwrap();
        for (i, (&inlier, &bad)) in result.inliers.iter().zip(&outlier).enumerate() {
            prop_assert_eq!(inlier, !bad, "pair {} of {}", i, n);
        }
        for p in &src {
            prop_assert!((result.transform * p - truth * p).norm() < 1e-3);
        }
    }
}

/// Found by `project_gives_a_consistent_image_or_an_error`: finite coordinates near `f32::MAX` gave an
/// infinite range in the image; such a point is out of view.
#[test]
fn a_point_beyond_a_float32_range_is_out_of_view() {
    let points = [3.4e38f32, 3.4e38, 0.0, 0.5, 10.0, 0.0, 0.0, 0.5];
    let projection = project_flat(&points, 4, &CylinderConfig::kitti()).unwrap();
    assert!(projection.range.iter().all(|r| r.is_finite()));
    assert_eq!((projection.num_valid(), projection.num_out_of_view), (1, 1));
}

/// A stand-in for the network: the features are the range image, the flow one given offset everywhere
/// (possibly absurd), the confidence one given value (possibly NaN).
struct ConstantFlowMatcher {
    cylinder: CylinderConfig,
    offset: (f32, f32),
    confidence: f32,
}

impl FrameMatcher for ConstantFlowMatcher {
    type Features = Vec<f32>;

    fn cylinder(&self) -> &CylinderConfig {
        &self.cylinder
    }

    fn encode(&self, image: &[f32]) -> dmlo_rs::Result<Vec<f32>> {
        Ok(image[..image.len() / 2].to_vec())
    }

    fn flow(&self, reference: &Vec<f32>, _target: &Vec<f32>) -> dmlo_rs::Result<DenseFlow> {
        let cells = reference.len();
        let mut flow = vec![self.offset.0; cells];
        flow.extend(std::iter::repeat_n(self.offset.1, cells));
        Ok(DenseFlow {
            flow,
            confidence: vec![self.confidence; cells],
            height: self.cylinder.height,
            width: self.cylinder.width,
        })
    }

    fn has_wide_window(&self) -> bool {
        true
    }

    fn wide_flow(
        &self,
        reference: &Vec<f32>,
        target: &Vec<f32>,
        _target_image: &[f32],
    ) -> dmlo_rs::Result<DenseFlow> {
        self.flow(reference, target)
    }
}

/// A stand-in moving-object network: every cell's probability one given value (possibly NaN or beyond
/// [0, 1]), or an error when there is none.
struct ConstantMovingNetwork {
    cylinder: CylinderConfig,
    probability: Option<f32>,
}

impl MovingObjectNetwork for ConstantMovingNetwork {
    fn cylinder(&self) -> &CylinderConfig {
        &self.cylinder
    }

    fn probability(&self, range: &[f32], _height: &[f32]) -> dmlo_rs::Result<Vec<f32>> {
        match self.probability {
            Some(p) => Ok(vec![p; range.len()]),
            None => Err(dmlo_rs::Error::Model("moving.onnx: failed".into())),
        }
    }
}

/// A scan as a user may hand one over: a walled yard seen from `(x, 0)` (dense enough for the stand-in's
/// flow to find matches), some of its values replaced by what breaks arithmetic or reflectance scales.
fn odometry_scan(x: f64, seed: u64, corrupt: usize) -> Vec<[f32; 4]> {
    let mut points = Vec::with_capacity(20_000);
    let mut state = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    let mut next = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    for _ in 0..20_000 {
        let azimuth = next() * std::f64::consts::TAU;
        let elevation = (-24.0 + next() * 26.0f64).to_radians();
        let (dx, dy) = (azimuth.cos(), azimuth.sin());
        // The yard's walls: x in [-20, 25], y in [-15, 15] around the origin, the ground 1.7 m below.
        let to_wall = [
            ((25.0 - x) / dx),
            ((-20.0 - x) / dx),
            (15.0 / dy),
            (-15.0 / dy),
        ]
        .into_iter()
        .filter(|t| *t > 0.0)
        .fold(f64::INFINITY, f64::min);
        let to_ground = if elevation < 0.0 {
            1.7 / -elevation.tan()
        } else {
            f64::INFINITY
        };
        let reach = to_wall.min(to_ground);
        let z = (reach * elevation.tan()).max(-1.7);
        points.push([
            (reach * dx) as f32,
            (reach * dy) as f32,
            z as f32,
            next() as f32,
        ]);
    }
    let bad = [
        f32::NAN,
        f32::INFINITY,
        -f32::INFINITY,
        3.4e38,
        0.0,
        1e-30,
        300.0,
        70000.0,
    ];
    for k in 0..corrupt.min(points.len()) {
        let point = (next() * points.len() as f64) as usize;
        points[point][k % 4] = bad[(next() * bad.len() as f64) as usize];
    }
    points
}

proptest! {
    #![proptest_config(config(32))]

    /// `Odometry::register` with any scans, masks (or a moving-object network's flags, whatever it
    /// answers), timestamps, sweep times, flows and settings gives a
    /// rigid, finite pose or a named error, never a panic; an error leaves the poses as they were. So
    /// does `Odometry::register_pair` of each scan with the one before (the poses untouched either way).
    #[test]
    fn odometry_registers_any_scan_or_names_what_is_wrong(
        scans in prop::collection::vec(
            (0.0..2.0f64, any::<u64>(), prop_oneof![3 => Just(0usize), 1 => 0usize..50, 1 => Just(25_000usize)],
             prop_oneof![6 => Just(20_000usize), 1 => 0usize..200]),
            1..5,
        ),
        offset in (prop_oneof![6 => -1.0..1.0f32, 1 => Just(f32::NAN), 1 => Just(1e30f32)],
                   prop_oneof![6 => -8.0..2.0f32, 1 => Just(f32::INFINITY)]),
        confidence in prop_oneof![6 => 0.0..1.0f32, 1 => Just(f32::NAN), 1 => Just(-1.0f32)],
        mapping in any::<bool>(),
        symmetric in any::<bool>(),
        deskew in any::<bool>(),
        timestamps in prop::collection::vec(prop_oneof![12 => 0.0..0.5f64, 1 => Just(f64::NAN), 1 => Just(-5.0)], 4),
        mask_share in prop_oneof![3 => Just(0.0f64), 1 => 0.0..1.0f64],
        min_points in prop_oneof![3 => Just(100u64), 1 => 0u64..5],
        large_motion in any::<bool>(),
        network in prop_oneof![
            3 => Just(None),
            1 => prop_oneof![Just(Some(0.2f32)), Just(Some(0.9f32)), Just(Some(f32::NAN)), Just(Some(7.0f32)), Just(None)].prop_map(Some),
        ],
    ) {
        let mut config = OdometryConfig::default();
        config.mapping.enabled = mapping;
        config.matching.symmetric = symmetric;
        config.deskew.enabled = deskew;
        config.min_points = min_points;
        let matcher = ConstantFlowMatcher { cylinder: CylinderConfig::kitti(), offset, confidence };
        let mut odometry = Odometry::new(matcher, config).unwrap();
        if let Some(probability) = network {
            odometry = odometry
                .with_moving_objects(ConstantMovingNetwork { cylinder: CylinderConfig::kitti(), probability })
                .unwrap();
        }
        let mut ahead = 0.0;
        let mut previous: Option<Vec<[f32; 4]>> = None;
        for (i, &(step, seed, corrupt, kept)) in scans.iter().enumerate() {
            ahead += step;
            let mut points = odometry_scan(ahead, seed, corrupt);
            points.truncate(kept);
            let moving: Vec<bool> = (0..points.len()).map(|k| (k as f64 * 0.618).fract() < mask_share).collect();
            let times: Vec<f64> = (0..points.len()).map(|k| (k as f64 / points.len().max(1) as f64) - 0.5).collect();
            let before = odometry.poses().len();
            let scan = Scan {
                points: &points,
                has_reflectance: i % 5 != 4,
                // With a network, the scans come without a mask for it to flag.
                moving: network.is_none().then_some(&moving[..]),
                timestamp: Some(timestamps[i % 4] + i as f64),
                point_times: (i % 2 == 1).then_some(&times[..]),
            };
            match odometry.register(scan) {
                Ok(pose) => {
                    let pose = pose.to_homogeneous();
                    prop_assert!(pose.iter().all(|v| v.is_finite()), "{}", pose);
                    let rotation = pose.fixed_view::<3, 3>(0, 0);
                    prop_assert!((rotation.transpose() * rotation - nalgebra::Matrix3::identity()).abs().max() < 1e-6);
                    prop_assert_eq!(odometry.poses().len(), before + 1);
                }
                Err(error) => {
                    prop_assert!(!error.to_string().is_empty());
                    prop_assert_eq!(odometry.poses().len(), before);
                }
            }
            if let Some(reference) = previous.replace(points.clone()) {
                let registered = odometry.poses().len();
                match odometry.register_pair(Scan::new(&reference), Scan::new(&points), large_motion) {
                    Ok(pair) => {
                        let transform = pair.transform;
                        prop_assert!(transform.iter().all(|v| v.is_finite()), "{}", transform);
                        let rotation = transform.fixed_view::<3, 3>(0, 0);
                        prop_assert!((rotation.transpose() * rotation - nalgebra::Matrix3::identity()).abs().max() < 1e-6);
                        prop_assert_eq!(pair.matches.source.len(), pair.matches.inliers.len());
                    }
                    Err(error) => prop_assert!(!error.to_string().is_empty()),
                }
                prop_assert_eq!(odometry.poses().len(), registered);
            }
        }
    }
}
