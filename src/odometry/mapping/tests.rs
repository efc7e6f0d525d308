use nalgebra::{Isometry3, Matrix4, Point3, Translation3, UnitQuaternion, Vector3};

use super::*;
use crate::projection::{project, CylinderConfig};
use crate::test_scenes::yard_scan;

struct Scan {
    cloud: Vec<Point3<f64>>,
    points: Vec<f32>,
}

fn scan_at(pose: &Isometry3<f64>, seed: u64) -> Scan {
    let raw = yard_scan(pose, seed, 150_000, &[(6.0, 4.0), (9.0, -5.0)]);
    let projection = project(&raw, &CylinderConfig::kitti()).unwrap();
    let points = projection.point_image(&raw);
    let cloud = raw
        .iter()
        .map(|p| Point3::new(p[0] as f64, p[1] as f64, p[2] as f64))
        .collect();
    Scan { cloud, points }
}

fn pose(forward_m: f64, left_m: f64, yaw_deg: f64) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(forward_m, left_m, 0.0),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw_deg.to_radians()),
    )
}

fn off(a: &Matrix4<f64>, b: &Matrix4<f64>) -> (f64, f64) {
    pose_difference(a, b)
}

/// A map holding the yard seen from the origin.
fn yard_map() -> LocalMap {
    yard_map_with(MappingConfig::default())
}

/// The same with `config`.
fn yard_map_with(config: MappingConfig) -> LocalMap {
    let mut map = LocalMap::new(config).unwrap();
    let first = scan_at(&Isometry3::identity(), 1);
    map.insert(&first.cloud, &Matrix4::identity(), &first.points)
        .unwrap();
    map
}

#[test]
fn a_scan_is_refined_against_the_map_from_the_dmlo_pose() {
    let map = yard_map();
    let truth = pose(0.9, 0.05, 1.0);
    let scan = scan_at(&truth, 2);
    let dmlo = (truth * pose(0.05, -0.03, 0.3)).to_homogeneous();
    let refined = map
        .refine(
            &scan.cloud,
            &scan.points,
            &dmlo,
            None,
            &CylinderConfig::kitti(),
        )
        .unwrap();
    assert!(refined.converged && refined.start == Some(MapStart::Dmlo));
    assert!(!refined.upright_only);
    let (moved, turned) = off(&refined.pose, &truth.to_homogeneous());
    assert!(moved < 0.02 && turned < 0.1, "{moved} m, {turned}°");
}

#[test]
fn a_pose_far_from_the_prediction_also_starts_from_it_and_the_better_score_wins() {
    let map = yard_map();
    let truth = pose(1.6, 0.0, 0.5);
    let scan = scan_at(&truth, 3);
    let wrong = pose(0.7, 0.6, -4.0).to_homogeneous(); // a wrong consensus
    let predicted = (truth * pose(0.04, 0.0, 0.2)).to_homogeneous();
    let cylinder = CylinderConfig::kitti();
    let refined = map
        .refine(
            &scan.cloud,
            &scan.points,
            &wrong,
            Some(&predicted),
            &cylinder,
        )
        .unwrap();
    assert!(refined.converged);
    assert_eq!(refined.start, Some(MapStart::MotionModel));
    let (moved, turned) = off(&refined.pose, &truth.to_homogeneous());
    assert!(moved < 0.02 && turned < 0.1, "{moved} m, {turned}°");
    // From the wrong pose alone NDT stays out of the truth's basin.
    let alone = map
        .refine(&scan.cloud, &scan.points, &wrong, None, &cylinder)
        .unwrap();
    assert!(off(&alone.pose, &truth.to_homogeneous()).0 > 0.1);
    // Close to the DMLO pose the prediction is not tried.
    let near = (truth * pose(0.1, 0.0, 0.0)).to_homogeneous();
    let refined = map
        .refine(
            &scan.cloud,
            &scan.points,
            &near,
            Some(&predicted),
            &cylinder,
        )
        .unwrap();
    assert_eq!(refined.start, Some(MapStart::Dmlo));
}

#[test]
fn a_standing_car_is_aligned_to_its_keyframe_by_its_planes() {
    let map = yard_map();
    let scan = scan_at(&Isometry3::identity(), 4); // the same place, other samples
    let dmlo = pose(0.01, 0.0, 0.05).to_homogeneous();
    let refined = map
        .refine(
            &scan.cloud,
            &scan.points,
            &dmlo,
            None,
            &CylinderConfig::kitti(),
        )
        .unwrap();
    assert_eq!(refined.start, Some(MapStart::Standing));
    assert_eq!(refined.degenerate_directions, Some(0));
    let (moved, turned) = off(&refined.pose, &Matrix4::identity());
    assert!(moved < 0.003 && turned < 0.02, "{moved} m, {turned}°");
}

#[test]
fn near_the_keyframe_the_upright_surfaces_give_the_horizontal_motion() {
    let map = yard_map();
    let truth = pose(0.3, 0.0, 0.2);
    let scan = scan_at(&truth, 5);
    let dmlo = (truth * pose(0.04, 0.02, 0.1)).to_homogeneous();
    let refined = map
        .refine(
            &scan.cloud,
            &scan.points,
            &dmlo,
            None,
            &CylinderConfig::kitti(),
        )
        .unwrap();
    assert!(refined.converged && refined.upright_only);
    assert_eq!(refined.start, Some(MapStart::Dmlo));
    let (moved, turned) = off(&refined.pose, &truth.to_homogeneous());
    assert!(moved < 0.02 && turned < 0.1, "{moved} m, {turned}°");
}

#[test]
fn scans_enter_the_map_as_keyframes_once_they_moved_or_turned_enough() {
    let mut map = LocalMap::new(MappingConfig {
        max_scans: 2,
        ..Default::default()
    })
    .unwrap();
    assert!(map.is_keyframe(&Matrix4::identity()) && map.last_keyframe().is_none());
    let scan = scan_at(&Isometry3::identity(), 6);
    for (i, step) in [
        pose(0.0, 0.0, 0.0),
        pose(2.0, 0.0, 0.0),
        pose(4.0, 0.0, 0.0),
    ]
    .iter()
    .enumerate()
    {
        map.insert(&scan.cloud, &step.to_homogeneous(), &scan.points)
            .unwrap();
        assert_eq!(map.num_scans(), (i + 1).min(2));
    }
    assert_eq!(
        map.last_keyframe(),
        Some(&pose(4.0, 0.0, 0.0).to_homogeneous())
    );
    assert!(!map.is_keyframe(&pose(5.9, 0.0, 4.9).to_homogeneous()));
    assert!(map.is_keyframe(&pose(6.0, 0.0, 0.0).to_homogeneous()));
    assert!(map.is_keyframe(&pose(4.0, 0.0, 5.1).to_homogeneous()));
    map.restart(&scan.cloud, &Matrix4::identity(), &scan.points)
        .unwrap();
    assert_eq!(map.num_scans(), 1);
}

#[test]
fn upright_points_keep_the_walls_and_posts_and_leave_the_floor() {
    let scan = scan_at(&Isometry3::identity(), 7);
    let cylinder = CylinderConfig::kitti();
    let every = upright_points(&scan.points, &cylinder, 0.0).unwrap();
    let kept = scan
        .points
        .chunks_exact(3)
        .filter(|p| p[0].is_finite())
        .count();
    assert!(
        every.len() > kept / 10 && every.len() < kept,
        "{} of {kept}",
        every.len()
    );
    // A few floor cells at the foot of a wall or a post fit a plane across the corner.
    let floor = every.iter().filter(|p| p.z < -1.6).count();
    assert!(
        floor * 50 < every.len(),
        "{floor} of {} on the floor",
        every.len()
    );
    let thinned = upright_points(&scan.points, &cylinder, 0.75).unwrap();
    assert!(thinned.len() < every.len() / 2);
    let mut voxels: Vec<[i64; 3]> = thinned
        .iter()
        .map(|p| [0, 1, 2].map(|k| (p[k] as f32 / 0.75).floor() as i64))
        .collect();
    voxels.sort_unstable();
    voxels.dedup();
    assert_eq!(voxels.len(), thinned.len(), "two points of one voxel kept");
    assert!(matches!(
        upright_points(&scan.points[3..], &cylinder, 0.0),
        Err(Error::InvalidArgument {
            argument: "points",
            ..
        })
    ));
}

#[test]
fn level_points_keep_the_near_scene_and_the_far_floor_and_leave_the_far_walls() {
    let scan = scan_at(&Isometry3::identity(), 7);
    let cylinder = CylinderConfig::kitti();
    let finite: Vec<Point3<f64>> = scan
        .points
        .chunks_exact(3)
        .filter(|p| p[0].is_finite())
        .map(|p| Point3::new(p[0] as f64, p[1] as f64, p[2] as f64))
        .collect();
    let count = |points: &[Point3<f64>], keep: &dyn Fn(&Point3<f64>) -> bool| {
        points.iter().filter(|p| keep(p)).count()
    };
    let near = |p: &Point3<f64>| p.coords.norm() <= 10.0;
    let far_walls = |p: &Point3<f64>| p.coords.norm() > 10.0 && p.z > -1.0;
    let far_floor = |p: &Point3<f64>| p.coords.norm() > 10.0 && p.z < -1.6;
    let level = level_points(&scan.points, &cylinder, 0.0, 10.0).unwrap();
    assert_eq!(count(&level, &near), count(&finite, &near));
    let (walls_kept, walls) = (count(&level, &far_walls), count(&finite, &far_walls));
    assert!(
        walls > 1000 && walls_kept * 20 < walls,
        "{walls_kept} of {walls} far wall points kept"
    );
    let (floor_kept, floor) = (count(&level, &far_floor), count(&finite, &far_floor));
    assert!(
        floor_kept * 10 > floor * 9,
        "{floor_kept} of {floor} far floor points kept"
    );
    let thinned = level_points(&scan.points, &cylinder, 0.75, 10.0).unwrap();
    assert_eq!(count(&thinned, &near), count(&finite, &near));
    assert!(count(&thinned, &far_floor) * 2 < floor_kept);
    assert_eq!(
        level_points(&scan.points, &cylinder, 0.4, f64::INFINITY)
            .unwrap()
            .len(),
        finite.len()
    );
    assert!(matches!(
        level_points(&scan.points[3..], &cylinder, 0.0, 10.0),
        Err(Error::InvalidArgument {
            argument: "points",
            ..
        })
    ));
}

#[test]
fn the_level_from_the_near_scene_and_the_far_floor_refines_the_pose_too() {
    let refine = |level_without_far_upright: bool| {
        let config = MappingConfig {
            far_range: 10.0,
            level_without_far_upright,
            ..Default::default()
        };
        let map = yard_map_with(config);
        let scan = scan_at(&pose(0.9, 0.05, 1.0), 2);
        let dmlo = (pose(0.9, 0.05, 1.0) * pose(0.05, -0.03, 0.3)).to_homogeneous();
        map.refine(
            &scan.cloud,
            &scan.points,
            &dmlo,
            None,
            &CylinderConfig::kitti(),
        )
        .unwrap()
    };
    let (whole, levelled) = (refine(false), refine(true));
    assert!(whole.converged && levelled.converged);
    let truth = pose(0.9, 0.05, 1.0).to_homogeneous();
    let (moved, turned) = off(&levelled.pose, &truth);
    assert!(moved < 0.02 && turned < 0.1, "{moved} m, {turned}°");
    // The second alignment starts where the first converged and may not move at all; its motion and
    // heading are the first's.
    assert_eq!(
        [levelled.pose[(0, 3)], levelled.pose[(1, 3)]],
        [whole.pose[(0, 3)], whole.pose[(1, 3)]]
    );
}

#[test]
fn the_level_alignment_takes_out_a_height_and_a_tilt_and_keeps_the_rest() {
    let map = yard_map_with(MappingConfig {
        far_range: 10.0,
        ..Default::default()
    });
    let truth = pose(0.9, 0.05, 1.0);
    let scan = scan_at(&truth, 2);
    let cylinder = CylinderConfig::kitti();
    // 4 cm too high and tilted 0.3° about the sensor's y axis, 2 cm off along x.
    let tilt = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.3_f64.to_radians());
    let start =
        (Isometry3::from_parts(Translation3::new(0.02, 0.0, 0.04), tilt) * truth).to_homogeneous();
    let cloud = map.level_cloud(&scan.points, &cylinder).unwrap();
    assert!(cloud.as_ref().is_some_and(|cloud| !cloud.is_empty()));
    let levelled = map.level(&start, cloud).unwrap();
    let truth = truth.to_homogeneous();
    assert!(
        (levelled[(2, 3)] - truth[(2, 3)]).abs() < 0.005,
        "height {}",
        levelled[(2, 3)]
    );
    let tilt_left = |pose: &Matrix4<f64>| pose[(2, 2)].acos().to_degrees();
    assert!(
        tilt_left(&levelled) < 0.05,
        "tilt {}°",
        tilt_left(&levelled)
    );
    // x, y and the heading stay the start's.
    assert_eq!(
        [levelled[(0, 3)], levelled[(1, 3)]],
        [start[(0, 3)], start[(1, 3)]]
    );
    // Without the split there is no level cloud, and the pose stays.
    let whole = LocalMap::new(MappingConfig {
        far_range: 10.0,
        level_without_far_upright: false,
        ..Default::default()
    })
    .unwrap();
    assert!(whole
        .level_cloud(&scan.points, &cylinder)
        .unwrap()
        .is_none());
    assert_eq!(whole.level(&start, None).unwrap(), start);
}

#[test]
fn heading_and_level_take_their_angles_and_position_from_either_pose() {
    let angles =
        |yaw: f64, pitch: f64, roll: f64| UnitQuaternion::from_euler_angles(roll, pitch, yaw);
    let horizontal =
        Isometry3::from_parts(Translation3::new(10.0, -4.0, 0.3), angles(2.9, 0.01, -0.02));
    let level = Isometry3::from_parts(Translation3::new(10.2, -4.1, 0.5), angles(2.8, -0.05, 0.04));
    let pose = heading_and_level(&horizontal.to_homogeneous(), &level.to_homogeneous());
    let rotation = isometry_from_matrix(&pose, "pose").unwrap().rotation;
    let (roll, pitch, yaw) = rotation.euler_angles();
    assert!(
        (yaw - 2.9).abs() < 1e-12 && (pitch + 0.05).abs() < 1e-12 && (roll - 0.04).abs() < 1e-12
    );
    assert_eq!(
        [pose[(0, 3)], pose[(1, 3)], pose[(2, 3)]],
        [10.0, -4.0, 0.5]
    );
}

#[test]
fn a_pair_is_refined_against_its_reference_alone() {
    let cylinder = CylinderConfig::kitti();
    let config = MappingConfig::default();
    let reference = scan_at(&Isometry3::identity(), 8);
    // A scan with itself stands: the planes give the identity.
    let same = refine_consecutive_pair(
        &reference.cloud,
        &reference.cloud,
        &reference.points,
        &reference.points,
        &pose(0.005, 0.0, 0.02).to_homogeneous(),
        &config,
        &cylinder,
    )
    .unwrap()
    .unwrap();
    let (moved, turned) = off(&same, &Matrix4::identity());
    assert!(moved < 1e-4 && turned < 1e-3, "{moved} m, {turned}°");
    for truth in [pose(1.2, 0.1, 2.0), pose(0.3, 0.0, 0.5)] {
        let target = scan_at(&truth, 9);
        let t_tgt_ref = truth.inverse().to_homogeneous();
        let start = (truth * pose(0.04, -0.03, 0.2)).inverse().to_homogeneous();
        let refined = refine_consecutive_pair(
            &reference.cloud,
            &target.cloud,
            &reference.points,
            &target.points,
            &start,
            &config,
            &cylinder,
        )
        .unwrap()
        .expect("converges");
        let (moved, turned) = off(&refined, &t_tgt_ref);
        assert!(moved < 0.02 && turned < 0.1, "{moved} m, {turned}°");
    }
}

#[test]
fn bad_settings_are_named() {
    let cases: [(MappingConfig, &str); 5] = [
        (
            MappingConfig {
                keyframe_distance: -1.0,
                ..Default::default()
            },
            "keyframe_distance",
        ),
        (
            MappingConfig {
                downsample: f64::NAN,
                ..Default::default()
            },
            "downsample",
        ),
        (
            MappingConfig {
                downsample_far: -0.4,
                ..Default::default()
            },
            "downsample_far",
        ),
        (
            MappingConfig {
                far_range: f64::NAN,
                ..Default::default()
            },
            "far_range",
        ),
        (
            MappingConfig {
                voxel_size: 0.0,
                ..Default::default()
            },
            "voxel_size",
        ),
    ];
    for (config, name) in cases {
        match LocalMap::new(config) {
            Err(Error::InvalidArgument { argument, .. }) => assert_eq!(argument, name),
            other => panic!("{name}: {:?}", other.map(|_| ())),
        }
    }
}

#[test]
fn near_a_keyframe_a_scan_without_upright_surfaces_is_aligned_whole_not_refused() {
    let map = yard_map();
    let truth = pose(0.3, 0.0, 0.0);
    let scan = scan_at(&truth, 10);
    let split = align_near_keyframe(
        |points, start| map.align(points, start),
        &scan.cloud,
        &[],
        &truth.to_homogeneous(),
        &Matrix4::identity(),
    )
    .unwrap();
    assert!(split.is_none());
}
