//! Motion compensation of skewed sweeps by the constant-velocity prediction.

use super::{as_points, FrameMatcher, Odometry};
use crate::deskew::{deskew, sweep_times, SweepPattern};
use crate::error::Result;
use crate::odometry::motion::rigid_inverse;
use crate::rigid::isometry_from_matrix;

impl<M: FrameMatcher> Odometry<M> {
    /// The sweep moved into the sensor frame of its pose's moment by the per-frame velocity: the
    /// sensor's motion over one period is the inverse of `T_tgt_ref` (a sweep lasts one period however
    /// many scans went missing before it).
    pub(super) fn deskewed(
        &self,
        cloud: &[[f32; 4]],
        times: Option<&[f64]>,
    ) -> Result<Vec<[f32; 4]>> {
        let d = &self.config.deskew;
        let pattern = SweepPattern {
            clockwise: d.clockwise,
            reference_azimuth_deg: d.reference_azimuth_deg,
        };
        let flat: &[f32] = cloud.as_flattened();
        let derived;
        let times = match times {
            Some(times) => times,
            None => {
                derived = sweep_times(flat, 4, &pattern)?;
                &derived[..]
            }
        };
        let motion = isometry_from_matrix(&rigid_inverse(self.motion.velocity()), "velocity")?;
        let moved = deskew(flat, 4, times, &motion)?;
        Ok(moved
            .chunks_exact(4)
            .map(|p| [p[0], p[1], p[2], p[3]])
            .collect())
    }

    /// The first deskewed scan's reference, measured before any velocity was, deskewed too (its own
    /// motion is the velocity just measured) and encoded again: a skewed scan matched against a deskewed
    /// one loses the skew's cancellation between two sweeps of the same motion, and with mapping the map
    /// then holds only deskewed scans.
    pub(super) fn deskew_reference(&mut self) -> Result<()> {
        let Some(reference) = self.reference.as_ref().filter(|r| !r.deskewed) else {
            return Ok(());
        };
        let cloud = self.deskewed(&reference.cloud, reference.times.as_deref())?;
        let projected = self.project(&cloud)?;
        let features = self.matcher.encode(&projected.image)?;
        let reference = self.reference.as_mut().expect("checked above");
        if let Some(map) = &mut self.map {
            map.restart(&as_points(&cloud), &reference.pose, &projected.points)?;
        }
        reference.cloud = cloud;
        reference.range = projected.range;
        reference.points = projected.points;
        reference.features = features;
        reference.deskewed = true;
        Ok(())
    }
}
