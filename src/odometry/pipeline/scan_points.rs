//! The points of a scan the odometry keeps: finite, and not flagged moving.

use nalgebra::Point3;

use super::Scan;
use crate::error::{Error, Result};

/// A scan's points as the odometry keeps them.
pub(super) struct KeptPoints {
    /// Per point: finite and not flagged moving.
    pub(super) keep: Vec<bool>,
    /// Those points.
    pub(super) kept: Vec<[f32; 4]>,
    /// The reflectance of every finite point, moving or not: what the reflectance scale is chosen from.
    pub(super) finite_reflectance: Vec<f32>,
}

/// The points of `scan` the odometry keeps (a `moving` mask of the wrong length is an error naming it).
pub(super) fn kept_points(scan: &Scan<'_>) -> Result<KeptPoints> {
    check_one_per_point(scan.moving, "moving", "flag", scan.points.len())?;
    let mut finite_reflectance = Vec::with_capacity(scan.points.len());
    let keep: Vec<bool> = scan
        .points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let finite = p.iter().all(|v| v.is_finite());
            if finite {
                finite_reflectance.push(p[3]);
            }
            finite && !scan.moving.is_some_and(|m| m[i])
        })
        .collect();
    Ok(KeptPoints {
        kept: kept_rows(scan.points, &keep),
        keep,
        finite_reflectance,
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
