#![forbid(unsafe_code)]
//! Motion compensation ("deskewing") of a spinning LiDAR's sweep.
//!
//! A spinning sensor fires its columns one after the other while the vehicle moves: a 10 Hz sweep at
//! 15 m/s ends 1.5 m from where it began, and every point is in the sensor frame of the moment it was
//! measured. Given each point's time within the sweep and the sensor's motion over one sweep (the
//! odometry's constant-velocity prediction), [`deskew`] moves every point into the sensor frame of one
//! reference moment, so the scan is one rigid snapshot again.
//!
//! Times are fractions of a sweep period relative to the reference moment (0), so a full sweep spans
//! one unit, e.g. [−½, ½) when the reference is mid-sweep. For sensors that report no per-point
//! times, [`sweep_times`] derives them from the azimuth, as KISS-ICP does for KITTI: the HDL-64E
//! turns clockwise seen from above, and KITTI's poses (and this crate's simulator) refer to the moment
//! it looks forward, half a turn from the seam behind the car.
//!
//! Between the reference and time `s` the sensor rotates by `s` times the sweep's rotation vector and
//! translates by `s` times its translation: constant angular and linear velocity, the motion model the
//! simulator's distorted sweeps are cast with.

use nalgebra::{Isometry3, Matrix3, UnitQuaternion, Vector3};
use rayon::prelude::*;

use crate::error::{Error, Result};

/// How a spinning sensor's sweep is laid out in azimuth, for [`sweep_times`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SweepPattern {
    /// The sensor turns clockwise seen from above (Velodyne, KITTI); `false`: counter-clockwise.
    pub clockwise: bool,
    /// Azimuth (degrees, counter-clockwise from x forward) the sensor looks at the reference moment;
    /// the sweep's seam lies opposite.
    pub reference_azimuth_deg: f64,
}

impl Default for SweepPattern {
    /// KITTI's HDL-64E and the simulator: clockwise, poses at the forward-looking moment.
    fn default() -> Self {
        SweepPattern {
            clockwise: true,
            reference_azimuth_deg: 0.0,
        }
    }
}

impl SweepPattern {
    /// Checks the reference azimuth is finite.
    pub fn validate(&self) -> Result<()> {
        if !self.reference_azimuth_deg.is_finite() {
            return Err(Error::invalid(
                "reference_azimuth_deg",
                format!("must be finite, got {}", self.reference_azimuth_deg),
            ));
        }
        Ok(())
    }

    /// The sweep time in [−½, ½] of a point at `(x, y)`; a non-finite point has no azimuth and gets
    /// the reference time 0 (it stays non-finite when deskewed).
    pub fn time_of(&self, x: f64, y: f64) -> f64 {
        if !(x.is_finite() && y.is_finite()) {
            return 0.0;
        }
        let reference = self.reference_azimuth_deg.to_radians();
        // Azimuth from the reference direction, wrapped into (−π, π].
        let mut angle = y.atan2(x) - reference;
        angle -= std::f64::consts::TAU * (angle / std::f64::consts::TAU).round();
        let turned = angle / std::f64::consts::TAU;
        // Clockwise: points counter-clockwise of the reference were measured before it.
        // `+ 0.0` turns the −0 of a point straight at the reference into 0.
        if self.clockwise {
            -turned + 0.0
        } else {
            turned + 0.0
        }
    }
}

/// Sweep times (see the module docs) of the `columns`-wide rows of `points` (x, y, z first), from
/// their azimuth.
pub fn sweep_times(points: &[f32], columns: usize, pattern: &SweepPattern) -> Result<Vec<f64>> {
    check_layout(points, columns)?;
    pattern.validate()?;
    Ok(points
        .par_chunks_exact(columns)
        .map(|p| pattern.time_of(p[0] as f64, p[1] as f64))
        .collect())
}

/// Points (row-major, `columns` ≥ 3 values a point, x y z first; the rest is copied) moved into the
/// sensor frame of the reference moment.
///
/// `motion` is the sensor's motion over one sweep period, `T_reference_next`: the pose one period after
/// the reference moment, in the reference frame (the inverse of the odometry's `T_tgt_ref`). `times`
/// (one per point, fractions of a period, see the module docs) must be finite. Non-finite points stay
/// non-finite.
pub fn deskew(
    points: &[f32],
    columns: usize,
    times: &[f64],
    motion: &Isometry3<f64>,
) -> Result<Vec<f32>> {
    check_layout(points, columns)?;
    let count = points.len() / columns;
    if times.len() != count {
        return Err(Error::invalid(
            "times",
            format!("has {} entries for {count} points", times.len()),
        ));
    }
    if let Some(i) = times
        .iter()
        .position(|t| t.is_nan() || t.abs() > MAX_SWEEP_TIME)
    {
        return Err(Error::invalid(
            "times",
            format!(
                "entry {i} is {} periods from the reference; expected sweep times in sensor periods \
                 (−0.5…0.5 around the reference, at most ±{MAX_SWEEP_TIME})",
                if times[i].abs() < 1e6 { format!("{}", times[i]) } else { format!("{:e}", times[i]) }
            ),
        ));
    }
    let rotation = motion.rotation.scaled_axis();
    let translation = motion.translation.vector;
    if !(rotation.iter().chain(translation.iter())).all(|v| v.is_finite()) {
        return Err(Error::invalid("motion", "has non-finite entries"));
    }
    // A sweep that turns half a revolution has no unique rotation to interpolate (nor is it a vehicle).
    if rotation.norm() >= std::f64::consts::FRAC_PI_2 {
        return Err(Error::invalid(
            "motion",
            format!(
                "turns {:.1}° in one sweep; at most 90° can be interpolated",
                rotation.norm().to_degrees()
            ),
        ));
    }
    let table = PoseTable::new(times, &rotation, &translation);
    let mut out = points.to_vec();
    out.par_chunks_exact_mut(columns)
        .zip(times.par_iter())
        .for_each(|(point, &time)| {
            let (r, t) = table.at(time);
            let p = Vector3::new(point[0] as f64, point[1] as f64, point[2] as f64);
            let moved = r * p + t;
            point[0] = moved.x as f32;
            point[1] = moved.y as f32;
            point[2] = moved.z as f32;
        });
    Ok(out)
}

/// Sweep times further than this from the reference are refused: they are not in periods (seconds of a
/// clock, nanoseconds) or not of this sweep.
pub const MAX_SWEEP_TIME: f64 = 2.0;

/// The sweep's poses at evenly spaced times over the range of the points' times, linearly interpolated
/// in between: the exact pose needs a sine and a cosine per point, the table two lookups. A step turns
/// at most 1/1024 of the sweep's rotation (< 0.1°), so interpolating the matrices errs by < 1e-9 of
/// the point's range, far below float32 resolution.
struct PoseTable {
    start: f64,
    step: f64,
    poses: Vec<(Matrix3<f64>, Vector3<f64>)>,
}

impl PoseTable {
    const STEPS: usize = 1024;

    fn new(times: &[f64], rotation: &Vector3<f64>, translation: &Vector3<f64>) -> Self {
        let (low, high) = times
            .iter()
            .fold((0.0f64, 0.0f64), |(lo, hi), &t| (lo.min(t), hi.max(t)));
        let step = (high - low) / Self::STEPS as f64;
        let poses = (0..=Self::STEPS)
            .map(|k| {
                let time = low + step * k as f64;
                let turn = UnitQuaternion::from_scaled_axis(time * rotation);
                (*turn.to_rotation_matrix().matrix(), time * translation)
            })
            .collect();
        PoseTable {
            start: low,
            step,
            poses,
        }
    }

    fn at(&self, time: f64) -> (Matrix3<f64>, Vector3<f64>) {
        if self.step == 0.0 {
            return self.poses[0];
        }
        let position = (time - self.start) / self.step;
        let index = (position.floor().max(0.0) as usize).min(Self::STEPS - 1);
        let fraction = position - index as f64;
        let (r0, t0) = &self.poses[index];
        let (r1, t1) = &self.poses[index + 1];
        (r0 + (r1 - r0) * fraction, t0 + (t1 - t0) * fraction)
    }
}

fn check_layout(points: &[f32], columns: usize) -> Result<()> {
    if columns < 3 {
        return Err(Error::invalid(
            "points",
            format!("need x, y, z: {columns} values a point"),
        ));
    }
    if points.len() % columns != 0 {
        return Err(Error::invalid(
            "points",
            format!(
                "{} values do not split into points of {columns}",
                points.len()
            ),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;
    use nalgebra::{Point3, Translation3};

    fn flat(points: &[[f32; 4]]) -> Vec<f32> {
        points.iter().flatten().copied().collect()
    }

    #[test]
    fn clockwise_sweep_times_match_the_kitti_convention() {
        let pattern = SweepPattern::default();
        let times = sweep_times(
            &flat(&[
                [10.0, 0.0, 0.0, 0.0],
                [0.0, 10.0, 0.0, 0.0],
                [0.0, -10.0, 0.0, 0.0],
                [-10.0, 1e-6, 0.0, 0.0],
            ]),
            4,
            &pattern,
        )
        .unwrap();
        // Forward at the reference; left (90° counter-clockwise) a quarter turn before, right after.
        assert_relative_eq!(times[0], 0.0);
        assert_relative_eq!(times[1], -0.25);
        assert_relative_eq!(times[2], 0.25);
        assert_relative_eq!(times[3], -0.5, epsilon = 1e-6);
    }

    #[test]
    fn counter_clockwise_sweep_and_reference_azimuth() {
        let pattern = SweepPattern {
            clockwise: false,
            reference_azimuth_deg: 90.0,
        };
        let times = sweep_times(&[0.0, 5.0, 0.0, 5.0, 0.0, 0.0], 3, &pattern).unwrap();
        assert_relative_eq!(times[0], 0.0);
        assert_relative_eq!(times[1], -0.25); // forward is 90° clockwise of the reference: earlier
    }

    #[test]
    fn undoes_a_sweep_cast_from_moving_poses() {
        // A sensor moving 1.2 m forward and turning 3° per sweep measures fixed world points, each in the
        // sensor frame of its own firing time; deskewing must return them in the reference frame.
        let motion = Isometry3::new(
            Vector3::new(1.2, 0.1, 0.02),
            Vector3::new(0.0, 0.0, 3f64.to_radians()),
        );
        // Away from the seam behind the sensor, where a point's firing time jumps by a whole period.
        let world: Vec<Point3<f64>> = (0..360_i32)
            .filter(|i| (i - 180).abs() > 10)
            .map(|i| {
                let a = (i as f64).to_radians();
                Point3::new(20.0 * a.cos(), 15.0 * a.sin(), -1.5 + 0.01 * i as f64)
            })
            .collect();
        let pattern = SweepPattern::default();
        let mut measured = Vec::new();
        let mut times = Vec::new();
        for p in &world {
            // Fixed point iteration: the firing time depends on the azimuth the moving sensor sees.
            let mut time = pattern.time_of(p.x, p.y);
            for _ in 0..20 {
                let pose = Isometry3::from_parts(
                    Translation3::from(time * motion.translation.vector),
                    UnitQuaternion::from_scaled_axis(time * motion.rotation.scaled_axis()),
                );
                let seen = pose.inverse() * p;
                time = pattern.time_of(seen.x, seen.y);
            }
            let pose = Isometry3::from_parts(
                Translation3::from(time * motion.translation.vector),
                UnitQuaternion::from_scaled_axis(time * motion.rotation.scaled_axis()),
            );
            let seen = pose.inverse() * p;
            measured.extend([seen.x as f32, seen.y as f32, seen.z as f32]);
            times.push(time);
        }
        let derived = sweep_times(&measured, 3, &pattern).unwrap();
        for (a, b) in derived.iter().zip(&times) {
            assert_relative_eq!(a, b, epsilon = 1e-5);
        }
        let fixed = deskew(&measured, 3, &derived, &motion).unwrap();
        for (p, q) in fixed.chunks_exact(3).zip(&world) {
            assert_relative_eq!(p[0] as f64, q.x, epsilon = 1e-4);
            assert_relative_eq!(p[1] as f64, q.y, epsilon = 1e-4);
            assert_relative_eq!(p[2] as f64, q.z, epsilon = 1e-4);
        }
    }

    #[test]
    fn identity_motion_and_reference_time_leave_points_alone() {
        let points = flat(&[[1.0, 2.0, 3.0, 0.5], [-4.0, 5.0, -6.0, 0.25]]);
        let moved = Isometry3::new(Vector3::new(1.0, 0.0, 0.0), Vector3::new(0.0, 0.0, 0.05));
        assert_eq!(deskew(&points, 4, &[0.0, 0.0], &moved).unwrap(), points);
        assert_eq!(
            deskew(&points, 4, &[0.3, -0.4], &Isometry3::identity()).unwrap(),
            points
        );
    }

    #[test]
    fn extra_columns_are_copied() {
        let points = flat(&[[1.0, 0.0, 0.0, 0.75]]);
        let motion = Isometry3::translation(2.0, 0.0, 0.0);
        let out = deskew(&points, 4, &[0.5], &motion).unwrap();
        assert_eq!(out, vec![2.0, 0.0, 0.0, 0.75]);
    }

    #[test]
    fn bad_input_is_named() {
        let points = flat(&[[1.0, 0.0, 0.0, 0.0]]);
        let still = Isometry3::identity();
        let message = |e: Error| e.to_string();
        assert!(
            message(deskew(&points, 4, &[0.0, 0.1], &still).unwrap_err()).starts_with("times:")
        );
        assert!(
            message(deskew(&points, 4, &[f64::NAN], &still).unwrap_err()).contains("NaN periods")
        );
        let nanoseconds = deskew(&points, 4, &[1.6e18], &still).unwrap_err();
        assert!(message(nanoseconds).contains("expected sweep times in sensor periods"));
        assert!(message(deskew(&points[..3], 4, &[], &still).unwrap_err()).starts_with("points:"));
        assert!(
            message(deskew(&points, 2, &[0.0, 0.0], &still).unwrap_err()).starts_with("points:")
        );
        let spin = Isometry3::new(Vector3::zeros(), Vector3::new(0.0, 0.0, 2.0));
        assert!(message(deskew(&points, 4, &[0.0], &spin).unwrap_err()).starts_with("motion:"));
        let bad = SweepPattern {
            clockwise: true,
            reference_azimuth_deg: f64::INFINITY,
        };
        assert!(message(sweep_times(&points, 4, &bad).unwrap_err())
            .starts_with("reference_azimuth_deg"));
    }

    #[test]
    fn non_finite_points_stay_non_finite() {
        let points = vec![f32::NAN, 0.0, 0.0, 1.0, 0.0, 0.0];
        let times = sweep_times(&points, 3, &SweepPattern::default()).unwrap();
        assert_eq!(times, vec![0.0, 0.0]);
        let motion = Isometry3::translation(1.0, 0.0, 0.0);
        let out = deskew(&points, 3, &times, &motion).unwrap();
        assert!(out[0].is_nan());
        assert_eq!(&out[3..], &[1.0, 0.0, 0.0]);
    }
}
