use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

use super::{point_to_plane, surface_normals, PointToPlaneConfig};
use crate::projection::{project_flat, CylinderConfig};

/// A box room around the sensor (walls 6–9 m away, floor 1.7 m below, ceiling 2.5 m above), sampled
/// densely: every direction of the image sees a plane.
fn room() -> Vec<f32> {
    let mut points = Vec::new();
    let step = 0.05_f32;
    let (x0, x1, y0, y1, z0, z1) = (-6.0_f32, 9.0, -7.0, 8.0, -1.7, 2.5);
    let span = |a: f32, b: f32| {
        let n = ((b - a) / step) as usize;
        (0..=n).map(move |i| a + i as f32 * step)
    };
    for x in span(x0, x1) {
        for y in span(y0, y1) {
            points.extend_from_slice(&[x, y, z0, 0.0, x, y, z1, 0.0]);
        }
        for z in span(z0, z1) {
            points.extend_from_slice(&[x, y0, z, 0.0, x, y1, z, 0.0]);
        }
    }
    for y in span(y0, y1) {
        for z in span(z0, z1) {
            points.extend_from_slice(&[x0, y, z, 0.0, x1, y, z, 0.0]);
        }
    }
    points
}

/// The point image of `points` (N×4) moved by `transform`: each cell's kept point, NaN where empty.
fn point_image(points: &[f32], transform: &Isometry3<f64>, config: &CylinderConfig) -> Vec<f32> {
    let moved: Vec<f32> = points
        .chunks_exact(4)
        .flat_map(|p| {
            let q = transform
                * nalgebra::Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            [q.x as f32, q.y as f32, q.z as f32, p[3]]
        })
        .collect();
    let projection = project_flat(&moved, 4, config).unwrap();
    projection
        .index
        .iter()
        .flat_map(|&i| match usize::try_from(i) {
            Ok(i) => [moved[4 * i], moved[4 * i + 1], moved[4 * i + 2]],
            Err(_) => [f32::NAN; 3],
        })
        .collect()
}

fn motion(translation: [f64; 3], rotation_deg: [f64; 3]) -> Isometry3<f64> {
    let [rx, ry, rz] = rotation_deg.map(f64::to_radians);
    Isometry3::from_parts(
        Translation3::new(translation[0], translation[1], translation[2]),
        UnitQuaternion::from_scaled_axis(Vector3::new(rx, ry, rz)),
    )
}

#[test]
fn a_scan_aligned_with_itself_is_the_identity_and_a_small_motion_is_recovered() {
    let config = CylinderConfig::kitti();
    let scene = room();
    let reference = point_image(&scene, &Isometry3::identity(), &config);
    let settings = PointToPlaneConfig::default();
    let start = motion([0.004, -0.003, 0.002], [0.01, 0.0, -0.02]);
    let itself = point_to_plane(&reference, &reference, &config, &start, &settings)
        .unwrap()
        .unwrap();
    assert!(
        itself.translation.vector.norm() < 1e-9 && itself.rotation.angle() < 1e-9,
        "{itself}"
    );

    let truth = motion([0.05, -0.03, 0.01], [0.05, -0.03, 0.3]); // T_tgt_ref
    let target = point_image(&scene, &truth, &config);
    let found = point_to_plane(
        &reference,
        &target,
        &config,
        &Isometry3::identity(),
        &settings,
    )
    .unwrap()
    .unwrap();
    let error = truth.inverse() * found;
    assert!(error.translation.vector.norm() < 2e-3, "{error}");
    assert!(error.rotation.angle().to_degrees() < 0.01, "{error}");
}

#[test]
fn a_bare_floor_fixes_only_height_roll_and_pitch() {
    let config = CylinderConfig::kitti();
    let floor: Vec<f32> = (0..400)
        .flat_map(|i| (0..400).map(move |j| (i, j)))
        .flat_map(|(i, j)| [-20.0 + 0.1 * i as f32, -20.0 + 0.1 * j as f32, -1.7, 0.0])
        .collect();
    let reference = point_image(&floor, &Isometry3::identity(), &config);
    let target = point_image(&floor, &motion([0.0, 0.0, 0.01], [0.0, 0.0, 0.0]), &config);
    let start = motion([0.05, 0.03, 0.0], [0.0, 0.0, 1.0]);
    let found = point_to_plane(
        &reference,
        &target,
        &config,
        &start,
        &PointToPlaneConfig::default(),
    )
    .unwrap()
    .unwrap();
    // Along the floor and about its normal the start stays; its height moves to the truth.
    assert!(
        (found.translation.vector.x - 0.05).abs() < 1e-6
            && (found.translation.vector.y - 0.03).abs() < 1e-6
    );
    assert!((found.translation.vector.z - 0.01).abs() < 1e-3, "{found}");
    assert!((found.rotation.scaled_axis().z.to_degrees() - 1.0).abs() < 1e-6);
}

#[test]
fn normals_are_unknown_at_depth_edges_and_missing_neighbours() {
    let config = CylinderConfig::kitti();
    let reference = point_image(&room(), &Isometry3::identity(), &config);
    let normals = surface_normals(&reference, &config, 0.1).unwrap();
    let known = normals.iter().flatten().count();
    assert!(known > 10_000);
    // Every surface of the room is axis-aligned; only cells on a corner between two see both.
    let aligned = normals
        .iter()
        .flatten()
        .filter(|n| (n.x.abs().max(n.y.abs()).max(n.z.abs()) - 1.0).abs() < 1e-2)
        .count();
    assert!(aligned as f64 > 0.95 * known as f64, "{aligned} of {known}");
    assert!(normals[..config.width].iter().all(Option::is_none)); // the top row has no row above
}

#[test]
fn bad_inputs_are_refused_and_too_few_correspondences_give_none() {
    let config = CylinderConfig::kitti();
    let empty = vec![f32::NAN; 3 * config.height * config.width];
    let settings = PointToPlaneConfig::default();
    let nothing =
        point_to_plane(&empty, &empty, &config, &Isometry3::identity(), &settings).unwrap();
    assert!(nothing.is_none());
    assert!(point_to_plane(
        &empty[1..],
        &empty,
        &config,
        &Isometry3::identity(),
        &settings
    )
    .is_err());
    let mut infinite = empty.clone();
    infinite[0] = f32::INFINITY;
    assert!(point_to_plane(
        &empty,
        &infinite,
        &config,
        &Isometry3::identity(),
        &settings
    )
    .is_err());
    for bad in [
        PointToPlaneConfig {
            iterations: 0,
            ..settings
        },
        PointToPlaneConfig {
            huber: 0.0,
            ..settings
        },
        PointToPlaneConfig {
            max_distance: f64::NAN,
            ..settings
        },
        PointToPlaneConfig {
            min_information: 1.0,
            ..settings
        },
    ] {
        assert!(point_to_plane(&empty, &empty, &config, &Isometry3::identity(), &bad).is_err());
    }
}
