use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

use super::{cell_centre_points, match_pair, voxel_crowding, PairConfig, PairImages};
use crate::error::Error;
use crate::ground_truth::ground_truth_flow;
use crate::projection::{project, CylinderConfig};
use crate::test_scenes::yard_scan;

struct Pair {
    ref_range: Vec<f32>,
    tgt_range: Vec<f32>,
    flow: Vec<f32>,
    confidence: Vec<f32>,
    t_tgt_ref: Isometry3<f64>,
}

/// Two scans of the yard, the second after `t_tgt_ref`, with the ground-truth flow between them and full
/// confidence where it is valid.
fn yard_pair(t_tgt_ref: Isometry3<f64>) -> Pair {
    let config = CylinderConfig::kitti();
    let reference = project(&yard_scan(&Isometry3::identity(), 1, 200_000, &[]), &config).unwrap();
    let target = project(&yard_scan(&t_tgt_ref.inverse(), 2, 200_000, &[]), &config).unwrap();
    let truth =
        ground_truth_flow(&reference.range, &target.range, &t_tgt_ref, &config, 0.1).unwrap();
    Pair {
        confidence: truth
            .valid
            .iter()
            .map(|&v| if v { 1.0 } else { 0.0 })
            .collect(),
        flow: truth.flow,
        ref_range: reference.range,
        tgt_range: target.range,
        t_tgt_ref,
    }
}

fn motion(translation: [f64; 3], yaw_deg: f64) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(translation[0], translation[1], translation[2]),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw_deg.to_radians()),
    )
}

fn error(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    let e = a.inverse() * b;
    (e.translation.vector.norm(), e.rotation.angle().to_degrees())
}

#[test]
fn ground_truth_flow_gives_the_motion_with_and_without_votes() {
    let pair = yard_pair(motion([0.9, 0.1, 0.02], 1.5).inverse());
    let cylinder = CylinderConfig::kitti();
    let images = PairImages::new(
        &pair.ref_range,
        &pair.tgt_range,
        &pair.flow,
        &pair.confidence,
    );
    for (config, tilt_votes) in [
        (PairConfig::default(), true),
        (PairConfig::default(), false),
        (
            PairConfig {
                coherence: None,
                tilt_vote_floor: None,
                vote_voxel: None,
                ..Default::default()
            },
            true,
        ),
    ] {
        let result = match_pair(&images, &cylinder, &config, tilt_votes).unwrap();
        let (metres, degrees) = error(&result.transform, &pair.t_tgt_ref);
        assert!(metres < 0.02 && degrees < 0.05, "{metres} m, {degrees}°");
        assert_eq!(result.source.len(), config.max_matches);
        assert_eq!(
            result.inliers.iter().filter(|&&i| i).count(),
            result.num_inliers
        );
        assert!(result.num_inliers > result.source.len() / 2);
        let voted = tilt_votes && config.tilt_vote_floor.is_some();
        assert_eq!(result.inlier_votes.is_some(), voted);
        if let Some(votes) = result.inlier_votes {
            // The walls vote, the floor hardly: a consensus on upright surfaces.
            assert!(votes > 0.2 * result.num_inliers as f64, "{votes}");
        }
    }
}

#[test]
fn matches_follow_the_flow_and_leave_out_the_masked_cells() {
    let pair = yard_pair(motion([0.5, 0.0, 0.0], 0.0).inverse());
    let cylinder = CylinderConfig::kitti();
    let cells = cylinder.height * cylinder.width;
    // The left half of the image left out: every match comes from the right half.
    let leave_out: Vec<bool> = (0..cells)
        .map(|i| i % cylinder.width < cylinder.width / 2)
        .collect();
    let images = PairImages {
        leave_out: Some(&leave_out),
        ..PairImages::new(
            &pair.ref_range,
            &pair.tgt_range,
            &pair.flow,
            &pair.confidence,
        )
    };
    let result = match_pair(&images, &cylinder, &PairConfig::default(), true).unwrap();
    assert!(result
        .cells
        .iter()
        .all(|&[_, col]| col >= cylinder.width / 2));
    for ((source, target), &inlier) in result
        .source
        .iter()
        .zip(&result.target)
        .zip(&result.inliers)
    {
        if inlier {
            // Within the refits' inlier bounds (the threshold along the ray, a bearing's width across it).
            assert!((pair.t_tgt_ref * source - target).norm() < 0.2);
        }
    }
}

#[test]
fn a_pair_without_matches_has_no_motion_and_no_error() {
    let pair = yard_pair(Isometry3::identity());
    let cylinder = CylinderConfig::kitti();
    let everything = vec![true; cylinder.height * cylinder.width];
    let images = PairImages {
        leave_out: Some(&everything),
        ..PairImages::new(
            &pair.ref_range,
            &pair.tgt_range,
            &pair.flow,
            &pair.confidence,
        )
    };
    let result = match_pair(&images, &cylinder, &PairConfig::default(), true).unwrap();
    assert_eq!(result.transform, Isometry3::identity());
    assert_eq!(
        (result.source.len(), result.num_inliers, result.inlier_votes),
        (0, 0, None)
    );
}

#[test]
fn bad_settings_and_images_are_named() {
    let pair = yard_pair(Isometry3::identity());
    let cylinder = CylinderConfig::kitti();
    let images = PairImages::new(
        &pair.ref_range,
        &pair.tgt_range,
        &pair.flow,
        &pair.confidence,
    );
    let named = |config: PairConfig| match match_pair(&images, &cylinder, &config, true) {
        Err(Error::InvalidArgument { argument, .. }) => argument,
        other => panic!("expected an invalid argument, got {other:?}"),
    };
    assert_eq!(
        named(PairConfig {
            max_matches: 2,
            ..Default::default()
        }),
        "max_matches"
    );
    assert_eq!(
        named(PairConfig {
            tilt_vote_floor: Some(0.0),
            ..Default::default()
        }),
        "tilt_vote_floor"
    );
    assert_eq!(
        named(PairConfig {
            vote_voxel: Some(f64::NAN),
            ..Default::default()
        }),
        "vote_voxel"
    );
    let short = &pair.flow[1..];
    let images = PairImages::new(&pair.ref_range, &pair.tgt_range, short, &pair.confidence);
    assert!(matches!(
        match_pair(&images, &cylinder, &PairConfig::default(), true),
        Err(Error::InvalidArgument {
            argument: "flow",
            ..
        })
    ));
}

#[test]
fn crowding_counts_the_points_of_each_cube() {
    let points = [
        Point3::new(0.1, 0.1, 0.1),
        Point3::new(1.9, 1.9, 1.9),
        Point3::new(2.1, 0.0, 0.0),
        Point3::new(-0.1, 0.0, 0.0),
        Point3::new(-1.9, 0.0, 0.0),
    ];
    assert_eq!(voxel_crowding(&points, 2.0), vec![2, 2, 1, 2, 2]);
}

#[test]
fn virtual_points_sit_at_the_cell_centres() {
    let cylinder = CylinderConfig::kitti();
    let mut ranges = vec![0.0f32; cylinder.height * cylinder.width];
    ranges[5 * cylinder.width + 17] = 12.5;
    let points = cell_centre_points(&ranges, &cylinder).unwrap();
    let expected = cylinder.unproject(5.0, 17.0, 12.5);
    let cell = 3 * (5 * cylinder.width + 17);
    assert_eq!(
        &points[cell..cell + 3],
        &[expected.x as f32, expected.y as f32, expected.z as f32]
    );
    assert!(points[..cell].iter().all(|v| v.is_nan()));
    assert!(cell_centre_points(&ranges[1..], &cylinder).is_err());
}
