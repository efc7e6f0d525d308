//! Scenes the unit tests scan: a box yard around the sensor, ray-cast in closed form.

use nalgebra::{Isometry3, Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// `rays` random rays (azimuth all round, elevation −24° to 2°) cast into a box yard — walls 14–25 m
/// away, a floor 1.7 m below, vertical posts of 0.3 m radius at `posts` (x, y) — from a sensor at `pose`
/// (`T_yard_sensor`); the hits in the sensor's frame, reflectance 0.4.
pub(crate) fn yard_scan(
    pose: &Isometry3<f64>,
    seed: u64,
    rays: usize,
    posts: &[(f64, f64)],
) -> Vec<[f32; 4]> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let inverse = pose.inverse();
    (0..rays)
        .filter_map(|_| {
            let azimuth = rng.random_range(-180.0f64..180.0).to_radians();
            let elevation = rng.random_range(-24.0f64..2.0).to_radians();
            let d = pose.rotation
                * Vector3::new(
                    elevation.cos() * azimuth.cos(),
                    elevation.cos() * azimuth.sin(),
                    elevation.sin(),
                );
            let o = pose.translation.vector;
            let mut t = f64::INFINITY;
            for (axis, low, high) in [(0, -14.0, 25.0), (1, -16.0, 18.0)] {
                if d[axis].abs() > 1e-9 {
                    let wall = if d[axis] > 0.0 { high } else { low };
                    t = t.min((wall - o[axis]) / d[axis]);
                }
            }
            if d.z < -1e-9 {
                t = t.min((-1.7 - o.z) / d.z);
            }
            for &(px, py) in posts {
                // The nearer root of |o + t d − c|² = r² in the plane.
                let (ox, oy) = (o.x - px, o.y - py);
                let a = d.x * d.x + d.y * d.y;
                let b = ox * d.x + oy * d.y;
                let disc = b * b - a * (ox * ox + oy * oy - 0.09);
                if a > 1e-12 && disc >= 0.0 {
                    let hit = (-b - disc.sqrt()) / a;
                    if hit > 0.0 {
                        t = t.min(hit);
                    }
                }
            }
            let p = inverse * Point3::from(o + d * t);
            t.is_finite()
                .then_some([p.x as f32, p.y as f32, p.z as f32, 0.4])
        })
        .collect()
}
