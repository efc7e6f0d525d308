use approx::assert_relative_eq;
use nalgebra::{Matrix3, Matrix4, Point3, Rotation3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::*;

fn sphere(center: [f64; 3], r: f64) -> Primitive {
    Primitive::Ellipsoid(Ellipsoid {
        center: Point3::from(center),
        radii: Vector3::repeat(r),
    })
}

#[test]
fn ray_hits_sphere_at_analytic_distance() {
    let scene = Scene::new(vec![sphere([10.0, 0.0, 0.0], 2.0)]).unwrap();
    let hit = scene
        .cast_ray(&Point3::origin(), &Vector3::x(), 100.0)
        .unwrap();
    assert_relative_eq!(hit.range, 8.0, epsilon = 1e-12);
    assert_eq!(hit.primitive, 0);
    assert_relative_eq!(hit.cos_incidence, 1.0, epsilon = 1e-12);
    assert!(scene
        .cast_ray(&Point3::origin(), &-Vector3::x(), 100.0)
        .is_none());
    assert!(scene
        .cast_ray(&Point3::origin(), &Vector3::x(), 7.9)
        .is_none());
}

#[test]
fn oriented_box_face_and_incidence() {
    // A 2 m cube rotated 45° about z, centred 10 m ahead: its near edge is at 10 − √2.
    let rotation =
        *Rotation3::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_4).matrix();
    let cube = Primitive::Box(OrientedBox {
        center: Point3::new(10.0, 0.0, 0.0),
        rotation,
        half_extents: Vector3::repeat(1.0),
    });
    let scene = Scene::new(vec![cube]).unwrap();
    let dir = Vector3::new(1.0, 0.0, 0.05).normalize();
    // The hit point must lie on the cube's surface.
    let hit = scene
        .cast_ray(&Point3::new(0.0, 0.2, 0.0), &dir, 50.0)
        .unwrap();
    let p = Point3::new(0.0, 0.2, 0.0) + dir * hit.range;
    let local = rotation.transpose() * (p - Point3::new(10.0, 0.0, 0.0));
    assert_relative_eq!(local.abs().max(), 1.0, epsilon = 1e-9);
    let straight = scene
        .cast_ray(&Point3::new(0.0, 0.0, 0.0), &Vector3::x(), 50.0)
        .unwrap();
    assert_relative_eq!(straight.range, 10.0 - 2f64.sqrt(), epsilon = 1e-12);
    assert_relative_eq!(
        straight.cos_incidence,
        std::f64::consts::FRAC_1_SQRT_2,
        epsilon = 1e-9
    );
}

#[test]
fn vertical_cylinder_side_and_cap() {
    let pole = Primitive::Cylinder(VerticalCylinder {
        base: Point3::new(5.0, 0.0, -1.0),
        height: 3.0,
        radius: 0.5,
    });
    let scene = Scene::new(vec![pole]).unwrap();
    let side = scene
        .cast_ray(&Point3::origin(), &Vector3::x(), 50.0)
        .unwrap();
    assert_relative_eq!(side.range, 4.5, epsilon = 1e-12);
    let from_above = scene
        .cast_ray(&Point3::new(5.2, 0.1, 10.0), &-Vector3::z(), 50.0)
        .unwrap();
    assert_relative_eq!(from_above.range, 8.0, epsilon = 1e-12);
    assert_relative_eq!(from_above.cos_incidence, 1.0, epsilon = 1e-12);
    // Passes above the top cap.
    assert!(scene
        .cast_ray(&Point3::new(0.0, 0.0, 2.5), &Vector3::x(), 50.0)
        .is_none());
}

#[test]
fn triangle_both_sides() {
    let tri = Primitive::Triangle(Triangle {
        vertices: [
            Point3::new(3.0, -1.0, -1.0),
            Point3::new(3.0, 1.0, -1.0),
            Point3::new(3.0, 0.0, 1.0),
        ],
    });
    let scene = Scene::new(vec![tri]).unwrap();
    assert_relative_eq!(
        scene
            .cast_ray(&Point3::origin(), &Vector3::x(), 9.0)
            .unwrap()
            .range,
        3.0,
        epsilon = 1e-12
    );
    assert_relative_eq!(
        scene
            .cast_ray(&Point3::new(6.0, 0.0, 0.0), &-Vector3::x(), 9.0)
            .unwrap()
            .range,
        3.0,
        epsilon = 1e-12
    );
    assert!(scene
        .cast_ray(&Point3::new(0.0, 0.5, 0.9), &Vector3::x(), 9.0)
        .is_none());
}

fn random_scene(rng: &mut ChaCha8Rng, n: usize) -> Vec<Primitive> {
    let mut prims = Vec::new();
    let p = |rng: &mut ChaCha8Rng| {
        Point3::new(
            rng.random_range(-40.0..40.0),
            rng.random_range(-40.0..40.0),
            rng.random_range(-5.0..5.0),
        )
    };
    for k in 0..n {
        let c = p(rng);
        prims.push(match k % 4 {
            0 => Primitive::Triangle(Triangle {
                vertices: [
                    c,
                    c + Vector3::new(3.0, 0.5, 0.2),
                    c + Vector3::new(0.3, 2.0, 1.0),
                ],
            }),
            1 => Primitive::Box(OrientedBox {
                center: c,
                rotation: *Rotation3::from_euler_angles(rng.random(), rng.random(), rng.random())
                    .matrix(),
                half_extents: Vector3::new(
                    rng.random_range(0.1..3.0),
                    rng.random_range(0.1..3.0),
                    rng.random_range(0.1..3.0),
                ),
            }),
            2 => Primitive::Cylinder(VerticalCylinder {
                base: c,
                height: rng.random_range(0.5..6.0),
                radius: rng.random_range(0.05..1.0),
            }),
            _ => Primitive::Ellipsoid(Ellipsoid {
                center: c,
                radii: Vector3::new(
                    rng.random_range(0.2..3.0),
                    rng.random_range(0.2..3.0),
                    rng.random_range(0.2..3.0),
                ),
            }),
        });
    }
    prims
}

#[test]
fn bvh_agrees_with_brute_force() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let prims = random_scene(&mut rng, 2000);
    let scene = Scene::new(prims.clone()).unwrap();
    let mut hits = 0;
    for _ in 0..3000 {
        let origin = Point3::new(
            rng.random_range(-50.0..50.0),
            rng.random_range(-50.0..50.0),
            rng.random_range(-6.0..6.0),
        );
        let dir = Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-0.3..0.3),
        )
        .normalize();
        let brute = prims
            .iter()
            .enumerate()
            .filter_map(|(i, p)| p.intersect(&origin, &dir, 80.0).map(|t| (t, i)))
            .min_by(|a, b| a.0.total_cmp(&b.0));
        let fast = scene.cast_ray(&origin, &dir, 80.0);
        match (brute, fast) {
            (None, None) => {}
            (Some((t, _)), Some(hit)) => {
                hits += 1;
                assert_relative_eq!(hit.range, t, epsilon = 1e-9);
            }
            other => panic!("brute force and BVH disagree: {other:?}"),
        }
    }
    assert!(hits > 500, "too few hits ({hits}) to test anything");
}

#[test]
fn scan_is_independent_of_thread_count() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let scene = Scene::new(random_scene(&mut rng, 500)).unwrap();
    let pose = Matrix4::identity();
    let elevations: Vec<f64> = (0..16).map(|i| 2.0 - i as f64 * 1.7).collect();
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let a = one.install(|| scene.cast_scan(&pose, &elevations, 360, 100.0).unwrap());
    let b = scene.cast_scan(&pose, &elevations, 360, 100.0).unwrap();
    assert_eq!(a, b);
    assert!(a.iter().filter(|h| h.is_some()).count() > 100);
}

#[test]
fn scan_pose_moves_the_sensor() {
    // A wall at world x = 20; a sensor at x = 5 rotated 180° looks away from it through column 0 (azimuth 180°).
    let wall = Primitive::Box(OrientedBox {
        center: Point3::new(20.5, 0.0, 0.0),
        rotation: Matrix3::identity(),
        half_extents: Vector3::new(0.5, 50.0, 50.0),
    });
    let scene = Scene::new(vec![wall]).unwrap();
    let mut pose = Matrix4::identity();
    pose.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(Rotation3::from_axis_angle(&Vector3::z_axis(), std::f64::consts::PI).matrix());
    pose[(0, 3)] = 5.0;
    let hits = scene.cast_scan(&pose, &[0.0], 4, 100.0).unwrap();
    // Column 0 looks along lidar −x = world +x.
    assert_relative_eq!(hits[0].unwrap().range, 15.0, epsilon = 1e-9);
    assert!(hits[2].is_none());
}

#[test]
fn scan_directions_follow_the_documented_layout() {
    let d = scan_directions(&[10.0, -20.0], 4).unwrap();
    assert_eq!(d.len(), 8);
    assert_relative_eq!(
        d[0],
        Vector3::new(-10f64.to_radians().cos(), 0.0, 10f64.to_radians().sin()),
        epsilon = 1e-12
    );
    assert_relative_eq!(
        d[6],
        Vector3::new(
            (-20f64).to_radians().cos(),
            0.0,
            (-20f64).to_radians().sin()
        ),
        epsilon = 1e-12
    );
    // Column 1 has azimuth 90° (left).
    assert!(d[1].y > 0.9);
}

#[test]
fn bad_input_is_reported() {
    let bad = Scene::new(vec![sphere([0.0, 0.0, 0.0], -1.0)]).unwrap_err();
    assert!(bad.to_string().contains("primitive 0 (ellipsoid)"), "{bad}");
    let skew = Primitive::Box(OrientedBox {
        center: Point3::origin(),
        rotation: Matrix3::repeat(0.5),
        half_extents: Vector3::repeat(1.0),
    });
    assert!(Scene::new(vec![skew]).is_err());
    let flat = Primitive::Triangle(Triangle {
        vertices: [
            Point3::origin(),
            Point3::new(1.0, 0.0, 0.0),
            Point3::new(2.0, 0.0, 0.0),
        ],
    });
    assert!(Scene::new(vec![flat]).is_err());
    let scene = Scene::new(vec![]).unwrap();
    assert!(scene
        .cast(&[Point3::origin()], &[Vector3::zeros()], 10.0)
        .is_err());
    assert!(scene.cast(&[Point3::origin()], &[], 10.0).is_err());
    assert!(scene
        .cast(&[Point3::origin()], &[Vector3::x()], f64::NAN)
        .is_err());
    assert!(scene
        .cast_scan(&Matrix4::repeat(1.0), &[0.0], 10, 10.0)
        .is_err());
    assert!(scene
        .cast_scan(&Matrix4::identity(), &[], 10, 10.0)
        .is_err());
    assert!(scene
        .cast_scan(&Matrix4::identity(), &[0.0], 0, 10.0)
        .is_err());
    assert_eq!(
        scene
            .cast(&[Point3::origin()], &[Vector3::x()], 10.0)
            .unwrap(),
        vec![None]
    );
}

#[test]
fn per_column_poses_move_each_column() {
    let wall = Primitive::Box(OrientedBox {
        center: Point3::new(20.5, 0.0, 0.0),
        rotation: Matrix3::identity(),
        half_extents: Vector3::new(0.5, 100.0, 100.0),
    });
    let scene = Scene::new(vec![wall]).unwrap();
    let columns = 8;
    let poses: Vec<Matrix4<f64>> = (0..columns)
        .map(|j| {
            let mut p = Matrix4::identity();
            p[(0, 3)] = j as f64; // the sensor advances 1 m per column
            p
        })
        .collect();
    let moving = scene
        .cast_scan_per_column(&poses, &[0.0], columns, 100.0)
        .unwrap();
    // Column 4 looks straight ahead (azimuth 0) from x = 4.
    assert_relative_eq!(moving[4].unwrap().range, 16.0, epsilon = 1e-9);
    let still = scene
        .cast_scan_per_column(&poses[..1], &[0.0], columns, 100.0)
        .unwrap();
    assert_eq!(
        still,
        scene.cast_scan(&poses[0], &[0.0], columns, 100.0).unwrap()
    );
    assert_relative_eq!(still[4].unwrap().range, 20.0, epsilon = 1e-9);
    assert!(scene
        .cast_scan_per_column(&poses[..3], &[0.0], columns, 100.0)
        .is_err());
}
