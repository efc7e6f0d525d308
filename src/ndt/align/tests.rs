use super::*;
use crate::ndt::NdtMapConfig;
use nalgebra::{Matrix4, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A flat patch `origin + u·a + v·b`, `u, v ∈ [0, 1]`.
type Patch = ([f64; 3], [f64; 3], [f64; 3]);

/// A street-like scene: ground, three walls (one tilted), boxes and poles.
fn scene_patches() -> Vec<Patch> {
    let mut patches = vec![
        ([-20.0, -15.0, 0.0], [40.0, 0.0, 0.0], [0.0, 30.0, 0.0]),
        ([18.0, -15.0, 0.0], [0.0, 30.0, 0.0], [0.0, 0.0, 6.0]),
        ([-20.0, 12.0, 0.0], [38.0, 0.0, 0.0], [0.0, 0.5, 5.0]),
        ([-20.0, -14.0, 0.0], [30.0, 0.0, 0.0], [0.0, 0.0, 4.0]),
    ];
    for (corner, size) in [
        ([4.0, 3.0, 0.0], [4.0, 1.8, 1.5]),
        ([-6.0, -5.0, 0.0], [2.0, 2.0, 3.0]),
        ([9.0, -7.0, 0.0], [1.0, 5.0, 2.0]),
        ([-12.0, 6.0, 0.0], [3.0, 1.0, 1.0]),
    ] {
        let [x, y, z] = corner;
        let [dx, dy, dz] = size;
        patches.extend([
            ([x, y, z], [dx, 0.0, 0.0], [0.0, 0.0, dz]),
            ([x, y + dy, z], [dx, 0.0, 0.0], [0.0, 0.0, dz]),
            ([x, y, z], [0.0, dy, 0.0], [0.0, 0.0, dz]),
            ([x + dx, y, z], [0.0, dy, 0.0], [0.0, 0.0, dz]),
            ([x, y, z + dz], [dx, 0.0, 0.0], [0.0, dy, 0.0]),
        ]);
    }
    patches
}

/// `count` points drawn uniformly over the scene's area, with 1 cm noise, plus poles.
fn sample_scene(count: usize, seed: u64) -> Vec<Point3<f64>> {
    let patches = scene_patches();
    let area = |(_, a, b): &Patch| Vector3::from(*a).cross(&Vector3::from(*b)).norm();
    let total: f64 = patches.iter().map(area).sum();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut points = Vec::with_capacity(count);
    let poles = [[2.0, -8.0], [-3.0, 9.0], [12.0, 4.0]];
    while points.len() < count {
        let point = if rng.random::<f64>() < 0.1 {
            let [x, y] = poles[rng.random_range(0..poles.len())];
            let angle: f64 = rng.random::<f64>() * std::f64::consts::TAU;
            Vector3::new(
                x + 0.15 * angle.cos(),
                y + 0.15 * angle.sin(),
                rng.random::<f64>() * 5.0,
            )
        } else {
            let mut pick = rng.random::<f64>() * total;
            let patch = patches
                .iter()
                .find(|patch| {
                    pick -= area(patch);
                    pick <= 0.0
                })
                .unwrap_or(&patches[0]);
            let (origin, a, b) = patch;
            Vector3::from(*origin)
                + Vector3::from(*a) * rng.random::<f64>()
                + Vector3::from(*b) * rng.random::<f64>()
        };
        let noise = Vector3::new(
            rng.random::<f64>(),
            rng.random::<f64>(),
            rng.random::<f64>(),
        ) - Vector3::repeat(0.5);
        points.push(Point3::from(point + noise * 0.02));
    }
    points
}

fn map_of(points: &[Point3<f64>]) -> NdtMap {
    let mut map = NdtMap::new(NdtMapConfig::default()).unwrap();
    map.insert(points).unwrap();
    map
}

fn motion(translation: [f64; 3], axis_angle_deg: [f64; 3]) -> Isometry3<f64> {
    Isometry3::new(
        Vector3::from(translation),
        Vector3::from(axis_angle_deg).map(f64::to_radians),
    )
}

/// Translation (m) and rotation (deg) of `estimate⁻¹ · truth`.
fn errors(estimate: &Isometry3<f64>, truth: &Isometry3<f64>) -> (f64, f64) {
    let delta = estimate.inverse() * truth;
    (
        delta.translation.vector.norm(),
        delta.rotation.angle().to_degrees(),
    )
}

/// Map from one sample of the scene; the source an independent sample seen from `T_map_source`.
fn map_and_source(truth: &Isometry3<f64>) -> (NdtMap, Vec<Point3<f64>>) {
    let map = map_of(&sample_scene(40_000, 1));
    let source = sample_scene(8_000, 2)
        .iter()
        .map(|p| truth.inverse_transform_point(p))
        .collect();
    (map, source)
}

/// [`map_and_source`] aligned from `initial`.
fn align_scene(truth: &Isometry3<f64>, initial: &Isometry3<f64>) -> NdtResult {
    let (map, source) = map_and_source(truth);
    map.align(&source, initial, &NdtAlignConfig::default())
        .unwrap()
}

fn assert_recovers(result: &NdtResult, truth: &Isometry3<f64>) {
    let (translation, rotation) = errors(&result.transform, truth);
    assert!(result.converged, "{result:?}");
    assert!(
        translation < 0.01 && rotation < 0.05,
        "error {translation:.4} m {rotation:.4}°: {result:?}"
    );
    // A well-constrained scene: every direction is solved for.
    assert_eq!(result.degenerate_directions, 0, "{result:?}");
}

#[test]
fn recovers_a_known_motion_from_identity() {
    let truth = motion([0.5, -0.2, 0.05], [0.3, -0.2, 3.0]);
    assert_recovers(&align_scene(&truth, &Isometry3::identity()), &truth);
}

#[test]
fn recovers_the_inverse_motion() {
    let truth = motion([0.5, -0.2, 0.05], [0.3, -0.2, 3.0]).inverse();
    assert_recovers(&align_scene(&truth, &Isometry3::identity()), &truth);
}

#[test]
fn recovers_from_a_noisy_start() {
    let truth = motion([1.0, 0.3, -0.1], [0.0, 0.5, -8.0]);
    let initial = truth * motion([0.25, -0.15, 0.1], [0.8, -0.5, 1.5]);
    let result = align_scene(&truth, &initial);
    assert_recovers(&result, &truth);
    assert!(
        result.score > 0.1 && result.num_correspondences > 1000,
        "{result:?}"
    );
}

#[test]
fn result_is_identical_for_one_and_four_threads() {
    let truth = motion([0.4, 0.1, 0.0], [0.0, 0.0, 2.0]);
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| align_scene(&truth, &Isometry3::identity()))
    };
    assert_eq!(run(1), run(4));
}

#[test]
fn degenerate_inputs_are_errors() {
    let map = map_of(&sample_scene(5_000, 3));
    let config = NdtAlignConfig::default();
    let identity = Isometry3::identity();
    let source = sample_scene(500, 4);
    let argument_of = |result: Result<NdtResult>| match result {
        Err(Error::InvalidArgument { argument, .. }) => argument,
        other => panic!("expected InvalidArgument, got {other:?}"),
    };
    assert_eq!(argument_of(map.align(&[], &identity, &config)), "points");
    let mut with_nan = source.clone();
    with_nan[7].y = f64::NAN;
    assert_eq!(
        argument_of(map.align(&with_nan, &identity, &config)),
        "points"
    );
    let empty = NdtMap::new(NdtMapConfig::default()).unwrap();
    assert_eq!(argument_of(empty.align(&source, &identity, &config)), "map");
    let mut scaled = Matrix4::identity();
    scaled[(0, 0)] = 2.0;
    assert_eq!(
        argument_of(map.align_matrix(&source, &scaled, &config)),
        "initial_transform"
    );
    let mut reflected = Matrix4::identity();
    reflected[(2, 2)] = -1.0;
    assert_eq!(
        argument_of(map.align_matrix(&source, &reflected, &config)),
        "initial_transform"
    );
    let mut projective = Matrix4::identity();
    projective[(3, 0)] = 0.1;
    assert_eq!(
        argument_of(map.align_matrix(&source, &projective, &config)),
        "initial_transform"
    );
    let mut not_finite = Matrix4::identity();
    not_finite[(1, 3)] = f64::INFINITY;
    assert_eq!(
        argument_of(map.align_matrix(&source, &not_finite, &config)),
        "initial_transform"
    );
    let bad = NdtAlignConfig {
        outlier_ratio: 1.0,
        ..config.clone()
    };
    assert_eq!(
        argument_of(map.align(&source, &identity, &bad)),
        "outlier_ratio"
    );
    let bad = NdtAlignConfig {
        max_iterations: 0,
        ..config.clone()
    };
    assert_eq!(
        argument_of(map.align(&source, &identity, &bad)),
        "max_iterations"
    );
    let bad = NdtAlignConfig {
        degeneracy_threshold: 1.0,
        ..config.clone()
    };
    assert_eq!(
        argument_of(map.align(&source, &identity, &bad)),
        "degeneracy_threshold"
    );
    let bad = NdtAlignConfig {
        rotation_degeneracy_threshold: f64::NAN,
        ..config.clone()
    };
    assert_eq!(
        argument_of(map.align(&source, &identity, &bad)),
        "rotation_degeneracy_threshold"
    );
    let bad = NdtAlignConfig {
        source_far_range: -1.0,
        ..config.clone()
    };
    assert_eq!(
        argument_of(map.align(&source, &identity, &bad)),
        "source_far_range"
    );
    let bad = NdtAlignConfig {
        source_far_voxel_size: f64::INFINITY,
        ..config.clone()
    };
    assert_eq!(
        argument_of(map.align(&source, &identity, &bad)),
        "source_far_voxel_size"
    );
    let far_away = motion([500.0, 0.0, 0.0], [0.0, 0.0, 0.0]);
    assert_eq!(
        map.align(&source, &far_away, &config),
        Err(Error::TooFewPoints {
            needed: config.min_correspondences,
            got: 0
        })
    );
}

#[test]
fn planar_map_fixes_the_constrained_directions_and_stays_put_in_the_others() {
    // Only the ground: height, roll and pitch are observable, the in-plane motion is not. The solve
    // must recover the former and neither blow up nor wander off in the latter.
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let mut plane = |count: usize| -> Vec<Point3<f64>> {
        (0..count)
            .map(|_| {
                let (x, y, z) = (
                    rng.random::<f64>(),
                    rng.random::<f64>(),
                    rng.random::<f64>(),
                );
                Point3::new(40.0 * x - 20.0, 30.0 * y - 15.0, 0.02 * z - 0.01)
            })
            .collect()
    };
    let map = map_of(&plane(40_000));
    let truth = motion([0.0, 0.0, 0.1], [1.0, -0.5, 0.0]);
    let source: Vec<Point3<f64>> = plane(8_000)
        .iter()
        .map(|p| truth.inverse_transform_point(p))
        .collect();
    let result = map
        .align(&source, &Isometry3::identity(), &NdtAlignConfig::default())
        .unwrap();
    let estimate = result.transform;
    assert!(result.converged, "{result:?}");
    assert!((estimate.translation.z - 0.1).abs() < 0.002, "{result:?}");
    let up = estimate.rotation * Vector3::z();
    let true_up = truth.rotation * Vector3::z();
    assert!(up.angle(&true_up).to_degrees() < 0.02, "{result:?}");
    assert!(estimate.translation.vector.xy().norm() < 0.02, "{result:?}");
    // That start is far enough off (10 cm, 1°) for the weights to tilt the analysis: x and y have 6–7 %
    // of z's information there. From a start as close as the odometry's (a few cm) they are found
    // degenerate and held exactly where they started, while z, roll and pitch are still solved.
    let start = truth * motion([0.05, -0.03, 0.01], [0.05, 0.05, 0.1]);
    let result = map
        .align(&source, &start, &NdtAlignConfig::default())
        .unwrap();
    assert!(result.converged, "{result:?}");
    assert!(result.degenerate_directions >= 2, "{result:?}");
    let held = result.transform.translation.vector.xy() - start.translation.vector.xy();
    assert!(held.norm() < 1e-3, "{result:?}"); // the split directions are tilted by the 1 cm z offset
    assert!(
        (result.transform.translation.z - 0.1).abs() < 0.002,
        "{result:?}"
    );
    let up = result.transform.rotation * Vector3::z();
    assert!(up.angle(&true_up).to_degrees() < 0.02, "{result:?}");
}

/// Ground and two walls parallel to x, nothing else: `count` points with 1 cm noise over `x ∈ [x0, x1]`.
fn sample_corridor(count: usize, x_range: (f64, f64), seed: u64) -> Vec<Point3<f64>> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (x0, x1) = x_range;
    let (half_width, height) = (6.0, 4.0);
    let ground_share = 2.0 * half_width / (2.0 * half_width + 2.0 * height);
    (0..count)
        .map(|_| {
            let x = x0 + (x1 - x0) * rng.random::<f64>();
            let noise = Vector3::new(
                rng.random::<f64>(),
                rng.random::<f64>(),
                rng.random::<f64>(),
            ) - Vector3::repeat(0.5);
            let surface = if rng.random::<f64>() < ground_share {
                Vector3::new(x, half_width * (2.0 * rng.random::<f64>() - 1.0), 0.0)
            } else {
                let side = if rng.random::<bool>() {
                    half_width
                } else {
                    -half_width
                };
                Vector3::new(x, side, height * rng.random::<f64>())
            };
            Point3::from(surface + noise * 0.02)
        })
        .collect()
}

#[test]
fn corridor_keeps_the_initial_estimate_along_its_axis_and_fixes_the_rest() {
    // The source is seen from `truth` and covers only the middle of the mapped corridor, so no end
    // wall tells where along x it is. Start 0.3 m off along the axis and a little off across it.
    let map = map_of(&sample_corridor(60_000, (-40.0, 40.0), 1));
    let truth = motion([2.0, 0.1, 0.05], [0.2, -0.3, 1.0]);
    let source: Vec<Point3<f64>> = sample_corridor(10_000, (-20.0, 20.0), 2)
        .iter()
        .map(|p| truth.inverse_transform_point(p))
        .collect();
    let along_axis = 0.3;
    let initial = Isometry3::from_parts(
        (truth.translation.vector + Vector3::new(along_axis, -0.08, 0.04)).into(),
        UnitQuaternion::from_scaled_axis(Vector3::new(0.3f64, -0.2, 0.8).map(f64::to_radians))
            * truth.rotation,
    );
    let result = map
        .align(&source, &initial, &NdtAlignConfig::default())
        .unwrap();
    let offset = result.transform.translation.vector - truth.translation.vector;
    assert!(result.converged, "{result:?}");
    assert_eq!(result.degenerate_directions, 1, "{result:?}");
    assert!(
        (offset.x - along_axis).abs() < 0.005,
        "x pulled off the initial estimate: {result:?}"
    );
    assert!(
        offset.y.abs() < 0.005 && offset.z.abs() < 0.005,
        "{result:?}"
    );
    let rotation_error = (result.transform.rotation.inverse() * truth.rotation)
        .angle()
        .to_degrees();
    assert!(
        rotation_error < 0.02,
        "rotation error {rotation_error}°: {result:?}"
    );

    // Without the analysis the weak in-plane information moves x (the old behaviour).
    let unaware = NdtAlignConfig {
        degeneracy_threshold: 0.0,
        rotation_degeneracy_threshold: 0.0,
        ..NdtAlignConfig::default()
    };
    let pulled = map.align(&source, &initial, &unaware).unwrap();
    let pulled_offset = pulled.transform.translation.x - truth.translation.x;
    assert_eq!(pulled.degenerate_directions, 0);
    assert!((pulled_offset - along_axis).abs() > 0.05, "{pulled:?}");
}

#[test]
fn rigid_matrix_round_trips() {
    let pose = motion([1.0, -2.0, 3.0], [10.0, 20.0, -30.0]);
    let back = isometry_from_matrix4(&pose.to_homogeneous(), "m").unwrap();
    assert!(errors(&back, &pose).0 < 1e-12 && errors(&back, &pose).1 < 1e-9);
}

#[test]
fn a_line_search_that_finds_no_decrease_stops_below_the_tolerances() {
    let truth = motion([0.3, -0.2, 0.05], [0.5, -0.3, 4.0]);
    let config = NdtAlignConfig::default();
    let (map, source) = map_and_source(&truth);
    let optimum = map.align(&source, &truth, &config).unwrap();
    assert!(optimum.converged, "{optimum:?}");
    let context = ScoreContext {
        gaussians: map.gaussians(),
        voxel_size: map.config().voxel_size,
        neighbours: config.neighbours,
        constants: ScoreConstants::new(config.outlier_ratio, map.config().voxel_size),
    };
    // The points the alignment scored.
    let thinned = range_voxel_downsample(
        &source,
        config.source_voxel_size,
        config.source_far_range,
        config.source_far_voxel_size,
    );
    let mut scorer = Scorer::new(&context, &thinned);
    let (translation_epsilon, rotation_epsilon) = (
        config.translation_epsilon,
        config.rotation_epsilon_deg.to_radians(),
    );
    // 2 cm along x from the optimum, the way the gradient rises: no length lowers the cost. Twelve halvings
    // would end far below the tolerances; the search stops at the first step below them instead of
    // evaluating on and failing.
    let at = scorer.evaluate(&optimum.transform);
    let mut uphill = Vector6::zeros();
    uphill[0] = 0.02_f64.copysign(at.gradient[0]);
    let uphill_search = line_search(
        &mut scorer,
        &optimum.transform,
        &at,
        &uphill,
        translation_epsilon,
        rotation_epsilon,
    );
    match uphill_search {
        LineSearch::Stalled => {}
        LineSearch::Decreased(_, _, step) => {
            panic!("expected the search to stop below the tolerances, it took the step {step}")
        }
        LineSearch::Failed => panic!("the search evaluated steps below the tolerances"),
    }
    // Downhill from a start 2 cm off, a step is taken.
    let off = motion([0.02, 0.0, 0.0], [0.0, 0.0, 0.0]) * optimum.transform;
    let at = scorer.evaluate(&off);
    let downhill = -at.gradient.normalize() * 0.005;
    assert!(matches!(
        line_search(
            &mut scorer,
            &off,
            &at,
            &downhill,
            translation_epsilon,
            rotation_epsilon
        ),
        LineSearch::Decreased(..)
    ));
}
