//! Matching from a guess instead of the identity: from the prediction when the motion outgrows the
//! network's window or a pair spans missing scans, and from search starts when there is no guess.

use nalgebra::{Matrix4, Point3};
use rayon::prelude::*;

use super::matching::occupied;
use super::{FrameDiagnostics, FrameMatcher, Matched, Odometry, Projected, Reference};
use crate::error::{Error, Result};
use crate::odometry::motion::{pose_difference, rigid_inverse, Fallback};
use crate::pair::PairMotion;
use crate::projection::CylinderConfig;

impl<M: FrameMatcher> Odometry<M> {
    /// Whether the predicted motion outgrows the network's window (`motion_model.match_from_prediction_m`)
    /// between consecutive scans; never before a velocity is measured.
    pub(super) fn beyond_window(&self, gap: usize, predicted: &Matrix4<f64>) -> bool {
        let m = &self.config.motion_model;
        let Some(limit) = m.match_from_prediction_m else {
            return false;
        };
        if !self.motion.is_measured() || gap as u64 > m.prediction_horizon {
            return false;
        }
        if m.rematch_gap
            .is_some_and(|rematch_gap| gap as u64 >= rematch_gap)
        {
            return false;
        }
        pose_difference(&Matrix4::identity(), predicted).0 > limit
    }

    /// The pair matched from the prediction: with the coarse windows placed where the prediction takes
    /// each cell (`motion_model.guided_windows`, by default with mapping) when the matcher can and that
    /// pair holds (enough inliers, a motion the prediction finds plausible), else in rounds of the
    /// reference moved by it.
    pub(super) fn matched_from_prediction(
        &self,
        previous: &Reference<M::Features>,
        target: &Projected,
        features: &M::Features,
        predicted: &Matrix4<f64>,
        gap: usize,
        diagnostics: &mut FrameDiagnostics,
    ) -> Result<Matched> {
        if self.config.guided_windows() {
            if let Some(pair) = self.guided_pair(previous, target, features, predicted)? {
                let holds = self.holds(&pair, predicted, gap);
                diagnostics.guided_windows = Some(holds);
                if holds {
                    diagnostics.count_matches(&pair);
                    return Ok(pair);
                }
            }
        }
        let rounds = self.config.prediction_rounds();
        let again = self.rematch(
            &previous.cloud,
            predicted,
            &target.range,
            features,
            1..=rounds,
            None,
            true,
        )?;
        diagnostics.rematch_rounds = Some(again.as_ref().map_or(0, |pair| pair.rounds));
        Ok(match again {
            Some(pair) => {
                diagnostics.count_matches(&pair);
                pair
            }
            None => Matched {
                motion: PairMotion {
                    transform: nalgebra::Isometry3::identity(),
                    source: Vec::new(),
                    target: Vec::new(),
                    cells: Vec::new(),
                    inliers: Vec::new(),
                    num_inliers: 0,
                    inlier_votes: None,
                },
                transform: *predicted,
                rounds: 0,
            },
        })
    }

    /// Whether a pair matched from the prediction can stand for the frame: `min_inliers` inliers and a
    /// motion the prediction finds plausible.
    fn holds(&self, pair: &Matched, predicted: &Matrix4<f64>, gap: usize) -> bool {
        pair.motion.num_inliers >= self.config.motion_model.min_inliers as usize
            && !self.motion.implausible(&pair.transform, predicted, gap)
    }

    /// The pair with the coarse windows placed where `predicted` takes each reference cell; `None` when the
    /// matcher cannot place them.
    fn guided_pair(
        &self,
        previous: &Reference<M::Features>,
        target: &Projected,
        features: &M::Features,
        predicted: &Matrix4<f64>,
    ) -> Result<Option<Matched>> {
        let expected = expected_flow(&previous.points, &self.cylinder, predicted);
        let Some(flow) = self.matcher.guided_flow_of_cells(
            &previous.features,
            features,
            &occupied(&previous.range),
            &expected,
        )?
        else {
            return Ok(None);
        };
        self.forward_pair(previous, target, &flow).map(Some)
    }

    /// The pair, or the pair matched again from the prediction (`motion_model.rematch_gap`) when it
    /// spans missing scans or its own motion would give way, and the re-match is usable and better.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn rematched_if_better(
        &self,
        pair: Matched,
        previous: &Reference<M::Features>,
        target: &Projected,
        features: &M::Features,
        predicted: &Matrix4<f64>,
        gap: usize,
        diagnostics: &mut FrameDiagnostics,
    ) -> Result<Matched> {
        let Some(rematch_gap) = self.config.motion_model.rematch_gap else {
            return Ok(pair);
        };
        if !self.motion.is_measured() {
            return Ok(pair);
        }
        let min_inliers = self.config.motion_model.min_inliers as usize;
        let gives_way = pair.motion.num_inliers < min_inliers
            || (!self.motion.gated_last()
                && self.motion.implausible(&pair.transform, predicted, gap));
        if (gap as u64) < rematch_gap && !gives_way {
            return Ok(pair);
        }
        let large = &self.config.large_motion;
        let mut tried = vec![self.rematch(
            &previous.cloud,
            predicted,
            &target.range,
            features,
            1..=large.max_rounds as usize,
            None,
            false,
        )?];
        // When the prediction's error outgrows the model's window too (a turn during the gap), the wide
        // window started from the prediction does better; beyond the prediction's horizon it is a guess,
        // and the search's starts join it.
        if self.matcher.has_wide_window() {
            let mut starts = vec![*predicted];
            if gap as u64 > self.config.motion_model.prediction_horizon {
                starts.extend(search_starts(&large.search_ahead_m, &large.search_yaw_deg));
            }
            tried.push(Some(self.register_far(
                &previous.cloud,
                target,
                features,
                &starts,
            )?));
        }
        diagnostics.rematch_rounds = Some(0);
        let usable = tried
            .into_iter()
            .flatten()
            .filter(|again| self.holds(again, predicted, gap));
        // The most inliers; on a tie the first tried (the model's own window).
        let best = usable.fold(None::<Matched>, |best, again| match best {
            Some(best) if best.motion.num_inliers >= again.motion.num_inliers => Some(best),
            _ => Some(again),
        });
        let Some(again) = best else {
            return Ok(pair);
        };
        if !gives_way && again.motion.num_inliers <= pair.motion.num_inliers {
            return Ok(pair);
        }
        diagnostics.rematch_rounds = Some(again.rounds);
        diagnostics.fallback = Some(Fallback::RematchedFromPrediction);
        diagnostics.count_matches(&again);
        Ok(again)
    }

    /// The pair matched again from the reference moved `ahead` metres forward and backward along its x
    /// axis (one round each), at each start that finds a motion of its own — `min_inliers` inliers,
    /// `min_inlier_votes` with tilt votes — further from `motion` than `motion_model.max_deviation`.
    /// Without a velocity the pair is matched from the identity, and where the scene repeats along the
    /// way (a guard rail's posts passed at highway speed) its motion can be an alias that looks as good as
    /// the truth.
    pub(super) fn other_starts(
        &self,
        previous: &Reference<M::Features>,
        target: &Projected,
        features: &M::Features,
        motion: &Matrix4<f64>,
        ahead: f64,
    ) -> Result<Vec<Matched>> {
        let limits = &self.config.motion_model;
        let mut held = Vec::new();
        for start in search_starts(&[ahead, -ahead], &[0.0]) {
            let again = self.rematch(
                &previous.cloud,
                &start,
                &target.range,
                features,
                1..=1,
                None,
                true,
            )?;
            let Some(again) = again else {
                continue;
            };
            let votes_hold = again
                .motion
                .inlier_votes
                .is_none_or(|votes| votes >= limits.min_inlier_votes);
            if votes_hold && pose_difference(&again.transform, motion).0 > limits.max_deviation {
                held.push(again);
            }
        }
        Ok(held)
    }

    /// Of `others`, the motion that drives forward at least `motion_model.start_max_reverse_m` (the one
    /// with the most inliers) when `motion` drives backwards further than that; `None` otherwise. A
    /// vehicle does not reverse at the speeds where a start's alias can pass for the truth.
    pub(super) fn forward_start(
        &self,
        motion: &Matrix4<f64>,
        others: Vec<Matched>,
    ) -> Option<Matched> {
        let limit = self.config.motion_model.start_max_reverse_m?;
        // `T_tgt_ref` of a sensor driving forward along its x axis moves the scene towards −x.
        if motion[(0, 3)] <= limit {
            return None;
        }
        others
            .into_iter()
            .filter(|other| other.transform[(0, 3)] < -limit)
            .max_by_key(|other| other.motion.num_inliers)
    }

    /// `T_tgt_ref` of `reference` and the target scan with no usable guess but `starts`: the wide window
    /// from every start, the start with the most inliers (one vote each: starts are compared by their
    /// counts) going on to rounds of the model's own window.
    pub(super) fn register_far(
        &self,
        reference: &[[f32; 4]],
        target: &Projected,
        tgt_features: &M::Features,
        starts: &[Matrix4<f64>],
    ) -> Result<Matched> {
        let mut best: Option<(Matched, Matrix4<f64>)> = None;
        for start in starts {
            let moved = self.project(&moved_cloud(reference, start))?;
            let encoded = self.matcher.encode(&moved.image)?;
            let flow = self
                .matcher
                .wide_flow(&encoded, tgt_features, &target.image)?;
            let pair = self.match_flow(
                &moved.range,
                &target.range,
                &flow,
                &moved.points,
                None,
                false,
            )?;
            if best
                .as_ref()
                .is_none_or(|(kept, _)| pair.motion.num_inliers > kept.motion.num_inliers)
            {
                best = Some((pair, *start));
            }
        }
        let (pair, start) = best.ok_or_else(|| Error::Config("large_motion: no start".into()))?;
        let refined = self.rematch(
            reference,
            &(pair.transform * start),
            &target.range,
            tgt_features,
            2..=self.config.large_motion.max_rounds as usize,
            Some(pair.transform),
            false,
        )?;
        Ok(match refined {
            Some(refined) => refined,
            None => in_given_frames(pair, &start, 1),
        })
    }

    /// Rounds of matching the reference moved by the estimate so far (from `estimate`) against the
    /// target's features with the model's window, until a round — or the `last_correction` that led to
    /// `estimate` — corrects less than the configured steps (`large_motion.min_step`, `min_step_deg`).
    /// `None` when not one round kept `min_inliers` inliers.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn rematch(
        &self,
        reference: &[[f32; 4]],
        estimate: &Matrix4<f64>,
        tgt_range: &[f32],
        tgt_features: &M::Features,
        rounds: std::ops::RangeInclusive<usize>,
        last_correction: Option<Matrix4<f64>>,
        tilt_votes: bool,
    ) -> Result<Option<Matched>> {
        let large = &self.config.large_motion;
        let min_inliers = self.config.motion_model.min_inliers as usize;
        let mut estimate = *estimate;
        let mut result: Option<Matched> = None;
        let mut correction = last_correction;
        for round in rounds {
            if let Some(correction) = &correction {
                let (moved_m, turned_deg) = pose_difference(&Matrix4::identity(), correction);
                if moved_m < large.min_step && turned_deg < large.min_step_deg {
                    break;
                }
            }
            let moved = self.project(&moved_cloud(reference, &estimate))?;
            let encoded = self.matcher.encode(&moved.image)?;
            let flow = self.occupied_flow(&encoded, &moved.range, tgt_features)?;
            let pair = self.match_flow(
                &moved.range,
                tgt_range,
                &flow,
                &moved.points,
                None,
                tilt_votes,
            )?;
            if pair.motion.num_inliers < min_inliers {
                break;
            }
            correction = Some(pair.transform);
            let given = in_given_frames(pair, &estimate, round);
            estimate = given.transform;
            result = Some(given);
        }
        Ok(result)
    }
}

/// A pair matched with the reference moved by `start`, as the motion between the scans given: the
/// motion composed with `start`, the matches' reference points moved back.
pub(super) fn in_given_frames(mut pair: Matched, start: &Matrix4<f64>, rounds: usize) -> Matched {
    let back = rigid_inverse(start);
    let (rotation, translation) = (back.fixed_view::<3, 3>(0, 0), back.fixed_view::<3, 1>(0, 3));
    for p in &mut pair.motion.source {
        *p = Point3::from(rotation * p.coords + translation);
    }
    pair.transform *= start;
    pair.rounds = rounds;
    pair
}

/// The guesses `T_tgt_ref` of a target `ahead` metres along the reference's x axis, turned by `yaw`
/// (every yaw with every distance, yaw first).
pub(super) fn search_starts(ahead_m: &[f64], yaw_deg: &[f64]) -> Vec<Matrix4<f64>> {
    let mut starts = Vec::with_capacity(ahead_m.len() * yaw_deg.len());
    for yaw in yaw_deg {
        let (sin, cos) = yaw.to_radians().sin_cos();
        for &ahead in ahead_m {
            #[rustfmt::skip]
            let ref_tgt = Matrix4::new(
                cos, -sin, 0.0, ahead,
                sin, cos, 0.0, 0.0,
                0.0, 0.0, 1.0, 0.0,
                0.0, 0.0, 0.0, 1.0,
            );
            starts.push(rigid_inverse(&ref_tgt));
        }
    }
    starts
}

/// Where `motion` (`T_tgt_ref`) takes each cell's point of a point image (`H × W × 3`, NaN where empty),
/// as the cell's expected flow in pixels (Δrow, Δcol; across the azimuth's wrap the short way round):
/// NaN for empty cells and points moved onto the sensor.
pub(super) fn expected_flow(
    points: &[f32],
    cylinder: &CylinderConfig,
    motion: &Matrix4<f64>,
) -> Vec<[f32; 2]> {
    let width = cylinder.width;
    let rotation = motion.fixed_view::<3, 3>(0, 0).into_owned();
    let translation = motion.fixed_view::<3, 1>(0, 3).into_owned();
    // The azimuth is periodic whether or not the image spans a whole turn.
    let turn = cylinder.columns_per_turn();
    points
        .par_chunks_exact(3)
        .enumerate()
        .map(|(cell, point)| {
            let p = Point3::new(point[0] as f64, point[1] as f64, point[2] as f64);
            if !p.coords.iter().all(|v| v.is_finite()) {
                return [f32::NAN; 2];
            }
            let Some((row, col)) =
                cylinder.locate(&Point3::from(rotation * p.coords + translation))
            else {
                return [f32::NAN; 2];
            };
            let d_row = row - (cell / width) as f64;
            let mut d_col = col - (cell % width) as f64;
            d_col -= turn * (d_col / turn).round();
            [d_row as f32, d_col as f32]
        })
        .collect()
}

/// A scan with its points moved by `transform`, in float32 as the points are stored.
pub(super) fn moved_cloud(cloud: &[[f32; 4]], transform: &Matrix4<f64>) -> Vec<[f32; 4]> {
    if *transform == Matrix4::identity() {
        return cloud.to_vec();
    }
    let t: Matrix4<f32> = transform.cast();
    cloud
        .iter()
        .map(|&[x, y, z, reflectance]| {
            let row = |i: usize| x * t[(i, 0)] + y * t[(i, 1)] + z * t[(i, 2)] + t[(i, 3)];
            [row(0), row(1), row(2), reflectance]
        })
        .collect()
}
