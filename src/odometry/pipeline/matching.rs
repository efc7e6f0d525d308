//! A pair's motion from the network's flow: the back end one way, or both ways and their midpoint,
//! judged by the motion model.

use nalgebra::{Matrix4, Point3};

use super::{FrameDiagnostics, FrameMatcher, Matched, Odometry, Projected, Reference, Stopwatch};
use crate::dense_match::DenseFlow;
use crate::error::Result;
use crate::odometry::motion::{midpoint_motion, rigid_inverse, Fallback, PairEvidence};
use crate::pair::{match_pair, PairImages, PairMotion};

impl<M: FrameMatcher> Odometry<M> {
    /// A pair's forward flow: of the reference's cells that hold a point, or of every cell when matched
    /// both ways (each direction's round trip reads the other's flow at any cell).
    pub(super) fn forward_flow(
        &self,
        reference: &M::Features,
        ref_range: &[f32],
        target: &M::Features,
    ) -> Result<DenseFlow> {
        if self.config.matching.symmetric {
            self.matcher.flow(reference, target)
        } else {
            self.occupied_flow(reference, ref_range, target)
        }
    }

    /// The flow of the reference's cells that hold a point (`ref_range` > 0), the only ones the pair's
    /// back end reads.
    pub(super) fn occupied_flow(
        &self,
        reference: &M::Features,
        ref_range: &[f32],
        target: &M::Features,
    ) -> Result<DenseFlow> {
        self.matcher
            .flow_of_cells(reference, target, &occupied(ref_range))
    }

    /// The pair's back end on the forward flow of the reference `previous` into `target`, tilt votes as
    /// the config says.
    pub(super) fn forward_pair(
        &self,
        previous: &Reference<M::Features>,
        target: &Projected,
        flow: &DenseFlow,
    ) -> Result<Matched> {
        self.match_flow(
            &previous.range,
            &target.range,
            flow,
            &previous.points,
            None,
            true,
        )
    }

    /// The pair's back end on a flow (`leave_out`: reference cells not matched), tilt votes as the
    /// config says (`tilt_votes`) or one vote each.
    pub(super) fn match_flow(
        &self,
        ref_range: &[f32],
        tgt_range: &[f32],
        flow: &DenseFlow,
        ref_points: &[f32],
        leave_out: Option<&[bool]>,
        tilt_votes: bool,
    ) -> Result<Matched> {
        let images = PairImages {
            ref_points: Some(ref_points),
            leave_out,
            ..PairImages::new(ref_range, tgt_range, &flow.flow, &flow.confidence)
        };
        Ok(Matched::new(match_pair(
            &images,
            &self.cylinder,
            &self.pair_config,
            tilt_votes,
        )?))
    }

    #[allow(clippy::too_many_arguments)]
    pub(super) fn motion_from_flow(
        &mut self,
        previous: &Reference<M::Features>,
        target: &Projected,
        features: &M::Features,
        gap: usize,
        diagnostics: &mut FrameDiagnostics,
        watch: &mut Stopwatch,
    ) -> Result<Matrix4<f64>> {
        diagnostics.gap = Some(gap);
        let predicted = self.motion.predicted(gap);
        let pair = if self.beyond_window(gap, &predicted) {
            let pair = self.matched_from_prediction(
                previous,
                target,
                features,
                &predicted,
                gap,
                diagnostics,
            )?;
            watch.lap("rematch", diagnostics);
            pair
        } else {
            let flow = self.forward_flow(&previous.features, &previous.range, features)?;
            watch.lap("matching", diagnostics);
            let pair = if self.config.matching.symmetric {
                let (forward, backward) = self.matched_both_ways(
                    &previous.range,
                    &previous.points,
                    &previous.features,
                    target,
                    features,
                    &flow,
                    diagnostics,
                    watch,
                )?;
                diagnostics.count_matches(&forward);
                diagnostics.backward_inliers = Some(backward.motion.num_inliers);
                let min_inliers = self.config.motion_model.min_inliers as usize;
                symmetric(forward, backward, min_inliers)
            } else {
                let pair = self.forward_pair(previous, target, &flow)?;
                watch.lap("pair", diagnostics);
                diagnostics.count_matches(&pair);
                pair
            };
            let pair = self.rematched_if_better(
                pair,
                previous,
                target,
                features,
                &predicted,
                gap,
                diagnostics,
            )?;
            if diagnostics.rematch_rounds.is_some() {
                watch.lap("rematch", diagnostics);
            }
            pair
        };
        diagnostics.inlier_votes = pair.motion.inlier_votes;
        let evidence = PairEvidence::new(
            pair.transform,
            pair.motion.num_inliers,
            pair.motion.inlier_votes,
            &pair.motion.source,
            &pair.motion.target,
        );
        let judged = self.motion.judge(&evidence, &predicted, gap);
        if let Some(fallback) = judged.fallback {
            diagnostics.fallback = Some(fallback);
        }
        let mut motion = judged.motion;
        if let (false, Some(ahead)) = (
            self.motion.is_measured(),
            self.config.motion_model.start_check_m,
        ) {
            let others = self.other_starts(previous, target, features, &motion, ahead)?;
            diagnostics.ambiguous_start = Some(!others.is_empty());
            if let Some(forward) = self.forward_start(&motion, others) {
                diagnostics.fallback = Some(Fallback::ForwardStart);
                diagnostics.count_matches(&forward);
                diagnostics.inlier_votes = forward.motion.inlier_votes;
                motion = forward.transform;
            }
            watch.lap("start_check", diagnostics);
        }
        Ok(motion)
    }

    /// The forward pair (`flow`, reference → target) and the target matched back against the reference
    /// from the cached features (`T_ref_tgt`), each without the cells whose flow the other direction's
    /// flow does not lead back to within `matching.consistency_px`.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn matched_both_ways(
        &self,
        ref_range: &[f32],
        ref_points: &[f32],
        ref_features: &M::Features,
        target: &Projected,
        features: &M::Features,
        flow: &DenseFlow,
        diagnostics: &mut FrameDiagnostics,
        watch: &mut Stopwatch,
    ) -> Result<(Matched, Matched)> {
        let back = self.matcher.flow(features, ref_features)?;
        watch.lap("network_backward", diagnostics);
        let wraps = self.cylinder.wraps_azimuth();
        let (forward_out, backward_out) = match self.config.matching.consistency_px {
            Some(limit) => (
                Some(round_trip_outliers(flow, &back, wraps, limit)),
                Some(round_trip_outliers(&back, flow, wraps, limit)),
            ),
            None => (None, None),
        };
        let forward = self.match_flow(
            ref_range,
            &target.range,
            flow,
            ref_points,
            forward_out.as_deref(),
            true,
        )?;
        watch.lap("pair", diagnostics);
        let backward = self.match_flow(
            &target.range,
            ref_range,
            &back,
            &target.points,
            backward_out.as_deref(),
            true,
        )?;
        watch.lap("backward", diagnostics);
        Ok((forward, backward))
    }
}

/// Which cells of a range image hold a point: the only ones whose flow the pair's back end reads.
pub(super) fn occupied(range: &[f32]) -> Vec<bool> {
    range.iter().map(|&range| range > 0.0).collect()
}

/// One motion from a pair matched both ways: the midpoint of the forward motion and the inverted
/// backward one, with both directions' matches (the backward ones turned round). A direction with fewer
/// than `min_inliers` inliers is left out; with neither, the forward pair goes on to the motion model.
pub(super) fn symmetric(forward: Matched, backward: Matched, min_inliers: usize) -> Matched {
    let reverse = Matched {
        transform: rigid_inverse(&backward.transform),
        motion: PairMotion {
            transform: backward.motion.transform.inverse(),
            source: backward.motion.target,
            target: backward.motion.source,
            ..backward.motion
        },
        rounds: backward.rounds,
    };
    match (
        forward.motion.num_inliers >= min_inliers,
        reverse.motion.num_inliers >= min_inliers,
    ) {
        (true, true) => {}
        (false, true) => return reverse,
        _ => return forward,
    }
    let transform = midpoint_motion(&forward.transform, &reverse.transform);
    let joined = |a: &[Point3<f64>], b: &[Point3<f64>]| [a, b].concat();
    Matched {
        motion: PairMotion {
            transform: forward.motion.transform,
            source: joined(&forward.motion.source, &reverse.motion.source),
            target: joined(&forward.motion.target, &reverse.motion.target),
            cells: [forward.motion.cells, reverse.motion.cells].concat(),
            inliers: [forward.motion.inliers, reverse.motion.inliers].concat(),
            num_inliers: forward.motion.num_inliers + reverse.motion.num_inliers,
            inlier_votes: forward
                .motion
                .inlier_votes
                .zip(reverse.motion.inlier_votes)
                .map(|(a, b)| a + b),
        },
        transform,
        rounds: forward.rounds,
    }
}

/// Per cell, whether following `flow` and then `back` (read at the nearest cell of the match) lands
/// further than `limit` pixels from where it started, or the match leaves the image: optical flow's
/// forward–backward consistency check, in float32.
pub(super) fn round_trip_outliers(
    flow: &DenseFlow,
    back: &DenseFlow,
    wraps: bool,
    limit: f64,
) -> Vec<bool> {
    let (height, width) = (flow.height, flow.width);
    let cells = height * width;
    let limit = limit as f32;
    (0..cells)
        .map(|cell| {
            let (row, col) = (cell / width, cell % width);
            let (d_row, d_col) = (flow.flow[cell], flow.flow[cells + cell]);
            let at_row = (row as f32 + d_row).round_ties_even() as i64;
            let mut at_col = (col as f32 + d_col).round_ties_even() as i64;
            if wraps {
                at_col = at_col.rem_euclid(width as i64);
            }
            if at_row < 0 || at_row >= height as i64 || at_col < 0 || at_col >= width as i64 {
                return true;
            }
            let at = at_row as usize * width + at_col as usize;
            (d_row + back.flow[at]).hypot(d_col + back.flow[cells + at]) > limit
        })
        .collect()
}
