//! The points of a scan the odometry keeps: finite returns at a sensor's ranges, and not flagged moving.

use nalgebra::Point3;

use super::Scan;
use crate::error::{Error, Result};

/// A point closer than this to the sensor (m) is no return: sensors see nothing within decimetres, and
/// points at the origin are the no-return markers some drivers write (nuScenes keyframes hold them). Such
/// points are left out, as non-finite ones are. The same figure as `dmlo.datasets.MIN_RETURN_RANGE_M`.
pub const MIN_RETURN_RANGE_M: f64 = 0.01;

/// A point farther than this from the sensor (m) is no LiDAR measurement (no automotive sensor reaches a
/// kilometre): garbage bytes, or the wrong unit or frame. Such points are left out; a scan most of whose
/// returns lie out there is refused. The same figure as `dmlo.datasets.MAX_SENSOR_RANGE_M`.
pub const MAX_SENSOR_RANGE_M: f64 = 1000.0;

/// A scan's points as the odometry keeps them.
pub(super) struct KeptPoints {
    /// Per point: finite, [`MIN_RETURN_RANGE_M`] to [`MAX_SENSOR_RANGE_M`] from the sensor, and not
    /// flagged moving.
    pub(super) keep: Vec<bool>,
    /// Those points.
    pub(super) kept: Vec<[f32; 4]>,
    /// The reflectance of every point at a sensor's range, moving or not: what the reflectance scale is
    /// chosen from.
    pub(super) finite_reflectance: Vec<f32>,
    /// Finite points.
    pub(super) finite: usize,
    /// Finite points other than the origin.
    pub(super) returns: usize,
    /// Points whose coordinates are finite and not the origin, whatever their reflectance: the returns
    /// the plausibility check counts, as `dmlo.datasets.check_plausible_scan` does.
    pub(super) located: usize,
    /// Those of them at a sensor's ranges.
    pub(super) located_in_range: usize,
}

impl KeptPoints {
    /// Points at a sensor's range ([`MIN_RETURN_RANGE_M`] to [`MAX_SENSOR_RANGE_M`]), moving or not.
    pub(super) fn in_range(&self) -> usize {
        self.finite_reflectance.len()
    }

    /// Refuses (naming the scan `name`) a scan that cannot be a LiDAR scan in metres: fewer than half
    /// of its returns lie [`MIN_RETURN_RANGE_M`] to [`MAX_SENSOR_RANGE_M`] from the sensor — what a scan
    /// in millimetres, far from its sensor's origin, or of garbage bytes reads as. The check
    /// `dmlo.datasets.check_plausible_scan` makes of a file; a scan without returns is not refused here
    /// (it has too few points to match).
    pub(super) fn check_plausible(&self, name: &'static str, points: usize) -> Result<()> {
        if 2 * self.located_in_range >= self.located {
            return Ok(());
        }
        Err(Error::invalid(
            name,
            format!(
                "not a plausible LiDAR scan: {} of its {} returns (points with finite \
                 coordinates other than the origin; {points} points in all) lie {MIN_RETURN_RANGE_M} m to {MAX_SENSOR_RANGE_M} m \
                 from the sensor; coordinates not in metres in the sensor's frame (millimetres? a \
                 world frame?), or garbage data",
                self.located_in_range,
                self.located
            ),
        ))
    }

    /// What was counted against `min_points`: the finite points kept, and those left out besides the
    /// non-finite ones.
    pub(super) fn counted(&self) -> String {
        let left_out: Vec<String> = [
            (
                self.finite - self.returns,
                "at the origin (no return)".to_string(),
            ),
            (
                self.returns - self.in_range(),
                format!("under {MIN_RETURN_RANGE_M} m or over {MAX_SENSOR_RANGE_M} m away"),
            ),
            (
                self.in_range() - self.kept.len(),
                "flagged moving".to_string(),
            ),
        ]
        .into_iter()
        .filter(|(count, _)| *count > 0)
        .map(|(count, why)| format!("{count} {why}"))
        .collect();
        if left_out.is_empty() {
            return format!("{} finite points", self.kept.len());
        }
        format!(
            "{} finite points left to match ({} left out)",
            self.kept.len(),
            left_out.join(", ")
        )
    }
}

/// The points of `scan` the odometry keeps (a `moving` mask of the wrong length is an error naming it).
pub(super) fn kept_points(scan: &Scan<'_>) -> Result<KeptPoints> {
    check_one_per_point(scan.moving, "moving", "flag", scan.points.len())?;
    let mut finite_reflectance = Vec::with_capacity(scan.points.len());
    let (mut finite_points, mut returns, mut located, mut located_in_range) = (0, 0, 0, 0);
    let keep: Vec<bool> = scan
        .points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let finite = p.iter().all(|v| v.is_finite());
            let finite_xyz = p[..3].iter().all(|v| v.is_finite());
            // In f64, whose squares of f32 values never overflow.
            let (x, y, z) = (f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            let range = (x * x + y * y + z * z).sqrt();
            let at_range = (MIN_RETURN_RANGE_M..=MAX_SENSOR_RANGE_M).contains(&range);
            located += usize::from(finite_xyz && range > 0.0);
            located_in_range += usize::from(finite_xyz && at_range);
            let returned = finite && range > 0.0;
            let in_range = returned && at_range;
            finite_points += usize::from(finite);
            returns += usize::from(returned);
            if in_range {
                finite_reflectance.push(p[3]);
            }
            in_range && !scan.moving.is_some_and(|m| m[i])
        })
        .collect();
    Ok(KeptPoints {
        kept: kept_rows(scan.points, &keep),
        keep,
        finite_reflectance,
        finite: finite_points,
        returns,
        located,
        located_in_range,
    })
}

/// Checks that `values` (the scan's `name`: one `what` a point), when given, has one entry per point.
pub(super) fn check_one_per_point<T>(
    values: Option<&[T]>,
    name: &'static str,
    what: &str,
    points: usize,
) -> Result<()> {
    match values {
        Some(values) if values.len() != points => Err(Error::invalid(
            name,
            format!(
                "expected one {what} per point ({points}), got {}",
                values.len()
            ),
        )),
        _ => Ok(()),
    }
}

/// The rows of `values` whose `keep` flag is set.
pub(super) fn kept_rows<T: Copy>(values: &[T], keep: &[bool]) -> Vec<T> {
    values
        .iter()
        .zip(keep)
        .filter(|&(_, &kept)| kept)
        .map(|(value, _)| *value)
        .collect()
}

pub(super) fn as_points(cloud: &[[f32; 4]]) -> Vec<Point3<f64>> {
    cloud
        .iter()
        .map(|p| Point3::new(p[0] as f64, p[1] as f64, p[2] as f64))
        .collect()
}
