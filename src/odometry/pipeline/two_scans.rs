//! [`Odometry::register_pair`]: the motion between two scans, with no motion model or initial guess.

use nalgebra::Matrix4;

use super::matching::symmetric;
use super::rematching::search_starts;
use super::{
    as_points, kept_points, normalised, FrameDiagnostics, FrameMatcher, KeptPoints, Matched,
    Notice, Odometry, Scan, Stopwatch,
};
use crate::error::{Error, Result};
use crate::odometry::config::ReflectanceScale;
use crate::odometry::mapping::refine_consecutive_pair;
use crate::pair::PairMotion;

/// The motion between two scans ([`Odometry::register_pair`]).
#[derive(Debug, Clone)]
pub struct RegisteredPair {
    /// `T_tgt_ref` (`p_t = T p_r`): with symmetric matching the midpoint of both directions, refined
    /// by NDT when `map_refined` says so.
    pub transform: Matrix4<f64>,
    /// The matches behind it, their points in the frames of the scans given (with symmetric matching
    /// both directions', the backward ones turned round) and RANSAC's inliers among them.
    pub matches: PairMotion,
    /// Whether NDT against the reference refined the motion (it converged); `None` when it did not
    /// run (mapping off, too few inliers, or a large motion).
    pub map_refined: Option<bool>,
    /// Matching rounds: 1 for a consecutive pair; for a large motion the wide window's, then the
    /// model's own.
    pub rounds: usize,
    /// What the odometry said about the scans (the reflectance scale chosen on them, a switch to the
    /// range-only model).
    pub notices: Vec<Notice>,
}

impl<M: FrameMatcher> Odometry<M> {
    /// The motion `T_tgt_ref` between `reference` and `target`, with no motion model or initial guess
    /// (`dmlo register`): the pair's back end on the network's flow, both ways with
    /// `matching.symmetric`, then refined against the reference as a one-scan map when mapping is on
    /// and RANSAC kept `motion_model.min_inliers` inliers. `large_motion`: scans far apart (several
    /// frames or metres) are matched with the wide window (the matcher's
    /// [`FrameMatcher::has_wide_window`], the paper's D = 40 at inference, §IV-D) from the configured
    /// search starts and then again with the reference moved by the estimate (`large_motion`
    /// settings), one way only and without tilt votes. Points flagged in [`Scan::moving`] are left out,
    /// and of a consecutive pair given without flags those the moving-object network flags; timestamps and sweep times are not read. A scan with fewer than `min_points` finite points is an
    /// error naming it: with no motion model to fall back on, the identity would be a silent wrong
    /// answer. The drive's poses and diagnostics are untouched; the reflectance scale is chosen here if
    /// no scan chose it before, as [`Odometry::register`] chooses it.
    pub fn register_pair(
        &mut self,
        reference: Scan<'_>,
        target: Scan<'_>,
        large_motion: bool,
    ) -> Result<RegisteredPair> {
        let mut pair = self.registered_pair(reference, target, large_motion)?;
        if same_scan(&reference, &target) {
            // A scan does not move against itself, whatever the network's sub-pixel flow says.
            pair.transform = Matrix4::identity();
            pair.matches.transform = nalgebra::Isometry3::identity();
        }
        let needed = self.config.motion_model.min_inliers as usize;
        if pair.matches.num_inliers < needed {
            self.notices.push(Notice::TooFewInliers {
                inliers: pair.matches.num_inliers,
                needed,
                large_motion,
            });
        }
        pair.notices = std::mem::take(&mut self.notices);
        Ok(pair)
    }

    fn registered_pair(
        &mut self,
        reference: Scan<'_>,
        target: Scan<'_>,
        large_motion: bool,
    ) -> Result<RegisteredPair> {
        if large_motion && !self.matcher.has_wide_window() {
            return Err(Error::Model(
                "large_motion: the matcher has no wide window (the model's frame_wide.onnx)".into(),
            ));
        }
        // Far apart (a loop closure), the cars of one scan are gone or parked elsewhere in the other: they
        // cannot agree on a motion, and the parked ones the network would flag are good matches.
        let detect_moving = !large_motion;
        let reference_cloud = self.pair_cloud(reference, "reference", detect_moving)?;
        let target_cloud = self.pair_cloud(target, "target", detect_moving)?;
        if large_motion {
            let target = self.project(&target_cloud)?;
            let features = self.matcher.encode(&target.image)?;
            let large = &self.config.large_motion;
            let starts = search_starts(&large.search_ahead_m, &large.search_yaw_deg);
            let far = self.register_far(&reference_cloud, &target, &features, &starts)?;
            return Ok(registered(far, None));
        }
        let reference = self.project(&reference_cloud)?;
        let reference_features = self.matcher.encode(&reference.image)?;
        let target = self.project(&target_cloud)?;
        let target_features = self.matcher.encode(&target.image)?;
        let flow = self.forward_flow(&reference_features, &reference.range, &target_features)?;
        let pair = if self.config.matching.symmetric {
            let (mut unused, mut watch) = (FrameDiagnostics::default(), Stopwatch::new());
            let (forward, backward) = self.matched_both_ways(
                &reference.range,
                &reference.points,
                &reference_features,
                &target,
                &target_features,
                &flow,
                &mut unused,
                &mut watch,
            )?;
            let min_inliers = self.config.motion_model.min_inliers as usize;
            symmetric(forward, backward, min_inliers)
        } else {
            self.match_flow(
                &reference.range,
                &target.range,
                &flow,
                &reference.points,
                None,
                true,
            )?
        };
        let min_inliers = self.config.motion_model.min_inliers as usize;
        if !self.config.mapping.enabled || pair.motion.num_inliers < min_inliers {
            return Ok(registered(pair, None));
        }
        // The reference is the map: a standing pair by point-to-plane ICP, a near one by its upright
        // surfaces, any other by NDT, as the drive decides near its keyframe.
        let refined = refine_consecutive_pair(
            &as_points(&reference_cloud),
            &as_points(&target_cloud),
            &reference.points,
            &target.points,
            &pair.transform,
            &self.config.mapping_config(),
            &self.cylinder,
        )?;
        let map_refined = Some(refined.is_some());
        let mut result = registered(pair, map_refined);
        if let Some(refined) = refined {
            result.transform = refined;
        }
        Ok(result)
    }

    /// A pair's scan (`name`): its finite points at a sensor's ranges not flagged moving (by the caller,
    /// or with `detect_moving` by the moving-object network), reflectance brought to the model's scale;
    /// at least `min_points` (and 3) of them, in a plausible scan.
    fn pair_cloud(
        &mut self,
        scan: Scan<'_>,
        name: &'static str,
        detect_moving: bool,
    ) -> Result<Vec<[f32; 4]>> {
        let detected = if detect_moving {
            self.detect_moving(&scan, false)?.map(|(flags, _)| flags)
        } else {
            None
        };
        let scan = match &detected {
            Some(moving) => Scan {
                moving: Some(moving),
                ..scan
            },
            None => scan,
        };
        let points = kept_points(&scan)?;
        points.check_plausible(name, scan.points.len())?;
        let min_points = self.points_needed();
        if points.kept.len() < min_points {
            return Err(Error::invalid(
                name,
                format!(
                    "{}, fewer than the {min_points} needed to register a pair (config.min_points)",
                    points.counted()
                ),
            ));
        }
        let KeptPoints {
            kept,
            finite_reflectance,
            ..
        } = points;
        let values = scan.has_reflectance.then_some(&finite_reflectance[..]);
        let index = self.frames;
        let scale = self.reflectance_for(values, finite_reflectance.len(), min_points, index)?;
        Ok(normalised(kept, scale.unwrap_or(ReflectanceScale::Unit)))
    }
}

/// Whether two scans are the same: their points bit for bit, their reflectance and their moving flags.
fn same_scan(a: &Scan<'_>, b: &Scan<'_>) -> bool {
    let bits = |p: &[f32; 4]| p.map(f32::to_bits);
    a.has_reflectance == b.has_reflectance
        && a.moving == b.moving
        && a.points.len() == b.points.len()
        && a.points
            .iter()
            .zip(b.points)
            .all(|(p, q)| bits(p) == bits(q))
}

fn registered(pair: Matched, map_refined: Option<bool>) -> RegisteredPair {
    RegisteredPair {
        transform: pair.transform,
        matches: pair.motion,
        map_refined,
        rounds: pair.rounds,
        notices: Vec::new(),
    }
}
