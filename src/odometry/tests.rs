use approx::assert_relative_eq;
use nalgebra::{Isometry3, Matrix4, Point3, Translation3, UnitQuaternion, Vector3};

use super::clock::FrameClock;
use super::motion::{
    matrix_power, nearest_rigid, pose_difference, rigid_inverse, Fallback, MotionLimits,
    MotionModel, PairEvidence,
};
use crate::error::Error;

fn motion(forward_m: f64, yaw_deg: f64) -> Matrix4<f64> {
    // T_tgt_ref of a car that drove `forward_m` along x and turned by `yaw_deg`.
    let pose = Isometry3::from_parts(
        Translation3::new(forward_m, 0.0, 0.0),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw_deg.to_radians()),
    );
    pose.inverse().to_homogeneous()
}

fn scene() -> Vec<Point3<f64>> {
    // Points spread over a street, not collinear.
    (0..60)
        .map(|i| {
            let i = i as f64;
            Point3::new(
                5.0 + (i * 0.37).sin() * 20.0,
                (i * 0.91).cos() * 15.0,
                -1.5 + (i % 7.0) * 0.4,
            )
        })
        .collect()
}

fn moved(points: &[Point3<f64>], transform: &Matrix4<f64>) -> Vec<Point3<f64>> {
    points
        .iter()
        .map(|p| transform.transform_point(p))
        .collect()
}

/// A model that measured a velocity of 1 m a frame.
fn driving() -> MotionModel {
    let mut model = MotionModel::new(MotionLimits::default());
    model.update(
        &Matrix4::identity(),
        &motion(1.0, 0.0).try_inverse().unwrap(),
        1,
    );
    model
}

#[test]
fn matrix_power_is_the_repeated_product() {
    let step = motion(1.3, 2.0);
    let mut product = Matrix4::identity();
    for n in 0..12 {
        assert_relative_eq!(matrix_power(&step, n), product, epsilon = 1e-12);
        product *= step;
    }
}

#[test]
fn pose_difference_measures_the_relative_motion() {
    let a = motion(2.0, 5.0);
    let b = a * motion(0.5, 10.0);
    let (moved, turned) = pose_difference(&a, &b);
    assert_relative_eq!(moved, 0.5, epsilon = 1e-12);
    assert_relative_eq!(turned, 10.0, epsilon = 1e-9);
    let (moved, turned) = pose_difference(&a, &a);
    assert!(moved < 1e-12 && turned < 1e-9);
}

#[test]
fn the_velocity_is_measured_between_consecutive_frames_only() {
    let mut model = MotionModel::new(MotionLimits::default());
    assert!(!model.is_measured());
    assert_eq!(model.predicted(3), Matrix4::identity());
    let pose = motion(2.0, 0.0).try_inverse().unwrap();
    model.update(&Matrix4::identity(), &pose, 2); // across a gap: not a per-frame motion
    assert!(!model.is_measured());
    model.update(&Matrix4::identity(), &pose, 1);
    assert!(model.is_measured());
    assert_relative_eq!(*model.velocity(), motion(2.0, 0.0), epsilon = 1e-12);
    assert_relative_eq!(model.predicted(3)[(0, 3)], -6.0, epsilon = 1e-12);
}

#[test]
fn too_few_inliers_or_road_votes_take_the_prediction() {
    let mut model = driving();
    let predicted = model.predicted(1);
    let pair = PairEvidence::new(motion(1.05, 0.0), 9, None, &[], &[]);
    let judged = model.judge(&pair, &predicted, 1);
    assert_eq!(judged.fallback, Some(Fallback::ConstantVelocity));
    assert_eq!(judged.motion, predicted);
    let pair = PairEvidence::new(motion(1.05, 0.0), 100, Some(4.9), &[], &[]);
    assert_eq!(
        model.judge(&pair, &predicted, 1).fallback,
        Some(Fallback::DegenerateScene)
    );
    let pair = PairEvidence::new(motion(1.05, 0.0), 100, Some(5.0), &[], &[]);
    let judged = model.judge(&pair, &predicted, 1);
    assert_eq!(judged.fallback, None);
    assert_eq!(judged.motion, motion(1.05, 0.0));
}

#[test]
fn an_implausible_motion_gives_way_to_the_matches_that_agree_with_the_prediction() {
    let mut model = driving();
    let predicted = model.predicted(1);
    let truth = motion(1.05, 0.1); // within a few centimetres of the prediction
    let wrong = motion(0.0, 0.0); // a consensus of the rings: standing still
    let source = scene();
    let mut target = moved(&source, &truth);
    // A third of the matches follow the wrong consensus.
    for (i, point) in source.iter().enumerate().filter(|(i, _)| i % 3 == 0) {
        target[i] = *point;
    }
    let pair = PairEvidence::new(wrong, 40, None, &source, &target);
    let judged = model.judge(&pair, &predicted, 1);
    assert_eq!(judged.fallback, Some(Fallback::GuidedConsensus));
    assert_relative_eq!(judged.motion, truth, epsilon = 1e-9);
    assert!(!model.gated_last());
}

#[test]
fn an_implausible_motion_without_support_takes_the_prediction_but_never_twice_in_a_row() {
    let mut model = driving();
    let predicted = model.predicted(1);
    let wrong = motion(0.0, 0.0);
    let source = scene();
    let target = source.clone(); // every match stands still
    let pair = PairEvidence::new(wrong, 60, None, &source, &target);
    let judged = model.judge(&pair, &predicted, 1);
    assert_eq!(judged.fallback, Some(Fallback::ImplausibleMotion));
    assert_eq!(judged.motion, predicted);
    assert!(model.gated_last());
    // Then the prediction is the stale one: the pair is trusted again.
    let judged = model.judge(&pair, &predicted, 1);
    assert_eq!(judged.fallback, None);
    assert_eq!(judged.motion, wrong);
    assert!(!model.gated_last());
}

#[test]
fn nothing_is_implausible_before_a_velocity_or_beyond_the_horizon() {
    let mut fresh = MotionModel::new(MotionLimits::default());
    let pair = PairEvidence::new(motion(3.0, 0.0), 60, None, &[], &[]);
    assert_eq!(fresh.judge(&pair, &Matrix4::identity(), 1).fallback, None);
    let model = driving();
    let far = model.predicted(25);
    assert!(model.implausible(&motion(3.0, 0.0), &model.predicted(1), 1));
    assert!(!model.implausible(&motion(3.0, 0.0), &far, 25)); // beyond 20 frames
                                                              // The limits grow with the frames spanned.
    assert!(!model.implausible(&motion(2.5, 0.0), &model.predicted(2), 2));
    assert!(model.implausible(&motion(2.5, 4.0), &model.predicted(1), 1));
}

#[test]
fn bad_limits_are_named() {
    let cases: [(MotionLimits, &str); 5] = [
        (
            MotionLimits {
                min_inliers: 2,
                ..Default::default()
            },
            "min_inliers",
        ),
        (
            MotionLimits {
                max_deviation: f64::NAN,
                ..Default::default()
            },
            "max_deviation",
        ),
        (
            MotionLimits {
                guided_fraction: 1.5,
                ..Default::default()
            },
            "guided_fraction",
        ),
        (
            MotionLimits {
                prediction_horizon: 0,
                ..Default::default()
            },
            "prediction_horizon",
        ),
        (
            MotionLimits {
                threshold: 0.0,
                ..Default::default()
            },
            "threshold",
        ),
    ];
    for (limits, name) in cases {
        match limits.validate() {
            Err(Error::InvalidArgument { argument, .. }) => assert_eq!(argument, name),
            other => panic!("{name}: {other:?}"),
        }
    }
    let unlimited = MotionLimits {
        max_deviation: f64::INFINITY,
        ..Default::default()
    };
    assert!(unlimited.validate().is_ok());
}

#[test]
fn scans_without_timestamps_are_one_frame_apart() {
    let mut clock = FrameClock::new();
    assert_eq!(clock.frame(), None);
    let frames: Vec<u64> = (0..4).map(|_| clock.advance(None).unwrap().frame).collect();
    assert_eq!(frames, [0, 1, 2, 3]);
    assert_eq!(clock.period(), None);
}

#[test]
fn a_late_timestamp_counts_the_missing_scans() {
    let mut clock = FrameClock::new();
    let times = [0.0, 0.1, 0.2, 0.3, 0.6, 0.7, 1.3];
    let frames: Vec<u64> = times
        .iter()
        .map(|&t| clock.advance(Some(t)).unwrap().frame)
        .collect();
    assert_eq!(frames, [0, 1, 2, 3, 6, 7, 13]);
    assert_relative_eq!(clock.period().unwrap(), 0.1, epsilon = 1e-12);
}

#[test]
fn a_timestamp_that_goes_back_is_flagged_and_taken_for_the_next_frame() {
    let mut clock = FrameClock::new();
    clock.advance(Some(1.0)).unwrap();
    clock.advance(Some(1.1)).unwrap();
    let tick = clock.advance(Some(0.5)).unwrap();
    assert!(tick.out_of_order);
    assert_eq!(tick.frame, 2);
    assert!(!clock.advance(Some(0.6)).unwrap().out_of_order);
}

#[test]
fn a_non_finite_timestamp_is_refused_and_changes_nothing() {
    let mut clock = FrameClock::new();
    clock.advance(Some(0.0)).unwrap();
    let before = clock.clone();
    for bad in [f64::NAN, f64::INFINITY] {
        assert!(matches!(
            clock.advance(Some(bad)),
            Err(Error::InvalidArgument {
                argument: "timestamp",
                ..
            })
        ));
    }
    assert_eq!(clock, before);
}

#[test]
fn the_period_is_the_median_of_the_recent_intervals() {
    let mut clock = FrameClock::new();
    for t in [0.0, 0.1, 0.3, 0.35] {
        clock.advance(Some(t)).unwrap();
    }
    // Intervals 0.1, then 0.2 (two periods of 0.1: not consecutive), then 0.05.
    assert_relative_eq!(clock.period().unwrap(), 0.075, epsilon = 1e-12);
}

#[test]
fn a_pose_is_made_rigid_and_a_rigid_one_is_left_as_it_is() {
    let rigid = motion(1.3, 7.0) * motion(-0.4, -2.5);
    let kept = nearest_rigid(&rigid);
    assert_relative_eq!(kept, rigid, epsilon = 1e-14);
    // A rotation block off the rotations by 1e-3 (as a chain fed back through its velocity drifts).
    let mut skewed = rigid;
    skewed[(0, 1)] += 1e-3;
    skewed[(2, 2)] *= 1.0 + 1e-3;
    skewed[(3, 0)] = 1e-9;
    let fixed = nearest_rigid(&skewed);
    let rotation = fixed.fixed_view::<3, 3>(0, 0);
    assert_relative_eq!(
        rotation.transpose() * rotation,
        nalgebra::Matrix3::identity(),
        epsilon = 1e-14
    );
    assert_relative_eq!(rotation.determinant(), 1.0, epsilon = 1e-14);
    assert_eq!(fixed.row(3), Matrix4::<f64>::identity().row(3));
    assert_eq!(
        fixed.fixed_view::<3, 1>(0, 3),
        skewed.fixed_view::<3, 1>(0, 3)
    );
    assert!((fixed - rigid).abs().max() < 2e-3);
    assert_relative_eq!(
        rigid_inverse(&fixed) * fixed,
        Matrix4::identity(),
        epsilon = 1e-14
    );
}
