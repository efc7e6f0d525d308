#![forbid(unsafe_code)]
//! The constant-velocity motion model (§III-D-c) and the judgement of a pair's motion against it.
//!
//! The paper falls back on the previous frame's motion when too few matches agree. Beyond the paper, a
//! motion resting on the road alone (its inliers' tilt votes say so) or lying further from the
//! prediction than a car's change of speed allows is not chained into the trajectory either: the
//! matches that agree with the prediction are solved instead when they are a consensus of their own,
//! otherwise the prediction is taken. Transforms are 4×4 homogeneous matrices, `T_tgt_ref` for motions
//! and `T_world_lidar` for poses.

use nalgebra::{Matrix3, Matrix4, Point3, Vector3};

use crate::error::{Error, Result};
use crate::odometry::config::schema::Named;
use crate::ransac::Refit;

/// When a pair's motion gives way to the prediction: the config's `motion_model` settings and the
/// RANSAC settings its guided solve uses.
#[derive(Debug, Clone, PartialEq)]
pub struct MotionLimits {
    /// Fewer RANSAC inliers than this and the pair has no motion of its own (the paper's 10).
    pub min_inliers: usize,
    /// With tilt votes: the inliers' votes above the floor must reach this (a match on a wall adds
    /// about 1, on the road about 0), or the consensus cannot tell where the car went horizontally.
    pub min_inlier_votes: f64,
    /// A motion further than this from the prediction (m per frame) is a wrong consensus; may be
    /// infinite (no limit).
    pub max_deviation: f64,
    /// The same for the rotation (° per frame).
    pub max_deviation_deg: f64,
    /// The matches agreeing with the prediction form a consensus of their own when they are at least
    /// this share of RANSAC's inliers (and `min_inliers`).
    pub guided_fraction: f64,
    /// Across more frames than this the prediction is a guess: no motion is implausible against it.
    pub prediction_horizon: usize,
    /// RANSAC's inlier threshold (m); the matches within twice it of the prediction agree with it.
    pub threshold: f64,
    /// How the agreeing matches are solved (as RANSAC's refits are).
    pub refit: Refit,
}

impl Default for MotionLimits {
    /// The odometry config's defaults (`odometry::config`, where every setting is declared), with the
    /// refit point-to-point.
    fn default() -> Self {
        MotionLimits {
            refit: Refit::PointToPoint,
            ..crate::odometry::config::OdometryConfig::default().motion_limits()
        }
    }
}

impl MotionLimits {
    /// Names the first setting out of its range.
    pub fn validate(&self) -> Result<()> {
        if self.min_inliers < 3 {
            return Err(Error::invalid(
                "min_inliers",
                format!(
                    "a rigid motion needs at least 3 matches, got {}",
                    self.min_inliers
                ),
            ));
        }
        let non_negative = [
            ("min_inlier_votes", self.min_inlier_votes),
            ("max_deviation", self.max_deviation),
            ("max_deviation_deg", self.max_deviation_deg),
        ];
        for (name, value) in non_negative {
            if value.is_nan() || value < 0.0 {
                return Err(Error::invalid(name, format!("must be ≥ 0, got {value}")));
            }
        }
        if !(0.0..=1.0).contains(&self.guided_fraction) {
            return Err(Error::invalid(
                "guided_fraction",
                format!("must lie in [0, 1], got {}", self.guided_fraction),
            ));
        }
        if self.prediction_horizon < 1 {
            return Err(Error::invalid(
                "prediction_horizon",
                "must be at least 1 frame",
            ));
        }
        if !(self.threshold.is_finite() && self.threshold > 0.0) {
            return Err(Error::invalid(
                "threshold",
                format!("must be a finite number > 0, got {}", self.threshold),
            ));
        }
        Ok(())
    }
}

/// Why a frame's motion is not its pair's own (the frame diagnostics' `fallback`). The motion model's
/// judgement of a pair ([`MotionModel::judge`]) gives the first four; the odometry's loop the others.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fallback {
    /// Too few inliers: the prediction was taken (the paper's motion model).
    ConstantVelocity,
    /// The inliers rest on too few upright surfaces to tell the horizontal motion: the prediction.
    DegenerateScene,
    /// The motion was implausible; the matches agreeing with the prediction were solved.
    GuidedConsensus,
    /// The motion was implausible and too few matches agreed with the prediction: the prediction.
    ImplausibleMotion,
    /// An ambiguous first pair drove backwards; a start's forward motion was taken.
    ForwardStart,
    /// The pair matched again from the prediction gave the motion.
    RematchedFromPrediction,
    /// The scan had too few points to match: the prediction.
    TooFewPoints,
    /// The scan could not be read: the prediction.
    UnreadableScan,
}

impl Named for Fallback {
    const NAMES: &'static [(Self, &'static str)] = &[
        (Fallback::ConstantVelocity, "constant_velocity"),
        (Fallback::DegenerateScene, "degenerate_scene"),
        (Fallback::GuidedConsensus, "guided_consensus"),
        (Fallback::ImplausibleMotion, "implausible_motion"),
        (Fallback::ForwardStart, "forward_start"),
        (
            Fallback::RematchedFromPrediction,
            "rematched_from_prediction",
        ),
        (Fallback::TooFewPoints, "too_few_points"),
        (Fallback::UnreadableScan, "unreadable_scan"),
    ];
}

impl serde::Serialize for Fallback {
    fn serialize<S: serde::Serializer>(
        &self,
        serializer: S,
    ) -> std::result::Result<S::Ok, S::Error> {
        serializer.serialize_str(self.name())
    }
}

/// What a pair's matching found: its RANSAC motion and the matches it rests on.
#[derive(Debug, Clone, Copy)]
pub struct PairEvidence<'a> {
    /// RANSAC's `T_tgt_ref`.
    pub transform: Matrix4<f64>,
    /// RANSAC's inliers.
    pub num_inliers: usize,
    /// With tilt votes: the inliers' votes above the floor; `None` without them.
    pub inlier_votes: Option<f64>,
    /// The matches' reference points.
    pub source: &'a [Point3<f64>],
    /// The matches' target points.
    pub target: &'a [Point3<f64>],
}

impl<'a> PairEvidence<'a> {
    /// The evidence of one pair.
    pub fn new(
        transform: Matrix4<f64>,
        num_inliers: usize,
        inlier_votes: Option<f64>,
        source: &'a [Point3<f64>],
        target: &'a [Point3<f64>],
    ) -> Self {
        PairEvidence {
            transform,
            num_inliers,
            inlier_votes,
            source,
            target,
        }
    }
}

/// The motion a frame takes and why, when it is not the pair's own.
#[derive(Debug, Clone, PartialEq)]
pub struct Judgement {
    /// `T_tgt_ref`.
    pub motion: Matrix4<f64>,
    /// `None`: the pair's own motion.
    pub fallback: Option<Fallback>,
}

/// The constant-velocity motion model: the last measured per-frame motion, and whether the previous
/// judged frame's motion was replaced as implausible.
#[derive(Debug, Clone, PartialEq)]
pub struct MotionModel {
    limits: MotionLimits,
    velocity: Matrix4<f64>,
    measured: bool,
    gated_last: bool,
}

impl MotionModel {
    /// A model that has measured nothing: it predicts standing still.
    pub fn new(limits: MotionLimits) -> Self {
        MotionModel {
            limits,
            velocity: Matrix4::identity(),
            measured: false,
            gated_last: false,
        }
    }

    /// Its settings.
    pub fn limits(&self) -> &MotionLimits {
        &self.limits
    }

    /// The per-frame motion `T_tgt_ref` last measured (the identity before any).
    pub fn velocity(&self) -> &Matrix4<f64> {
        &self.velocity
    }

    /// Whether a velocity was measured; until then the prediction is "standing still", a guess.
    pub fn is_measured(&self) -> bool {
        self.measured
    }

    /// Whether the last judged motion was replaced by the prediction as implausible.
    pub fn gated_last(&self) -> bool {
        self.gated_last
    }

    /// The constant-velocity motion `T_tgt_ref` across `frames` frames (the velocity to that power,
    /// multiplied in numpy's `matrix_power` order).
    pub fn predicted(&self, frames: usize) -> Matrix4<f64> {
        matrix_power(&self.velocity, frames)
    }

    /// Measures the velocity from two rigid poses `T_world_lidar` `frames` frames apart. Across a gap left by
    /// missing scans the motion spans several frames, and the velocity measured before it stays the
    /// better per-frame estimate: only consecutive frames measure.
    pub fn update(&mut self, reference_pose: &Matrix4<f64>, pose: &Matrix4<f64>, frames: usize) {
        if frames == 1 {
            self.velocity = rigid_inverse(pose) * reference_pose;
            self.measured = true;
        }
    }

    /// Whether `motion` lies further from `predicted` than a car's change of speed over `gap` frames
    /// allows; never beyond the prediction's horizon, where the prediction is a guess.
    pub fn implausible(&self, motion: &Matrix4<f64>, predicted: &Matrix4<f64>, gap: usize) -> bool {
        if gap > self.limits.prediction_horizon {
            return false;
        }
        let (moved, turned) = pose_difference(motion, predicted);
        let frames = gap as f64;
        moved > self.limits.max_deviation * frames
            || turned > self.limits.max_deviation_deg * frames
    }

    /// The motion a frame `gap` frames after its reference takes from its pair (module docs). A motion
    /// is judged implausible only once a velocity was measured, and never twice in a row: then the
    /// prediction is the stale one (measured from a wrong pair before any velocity was known), and the
    /// matching is trusted again.
    pub fn judge(
        &mut self,
        pair: &PairEvidence<'_>,
        predicted: &Matrix4<f64>,
        gap: usize,
    ) -> Judgement {
        let prediction = |fallback| Judgement {
            motion: *predicted,
            fallback: Some(fallback),
        };
        if pair.num_inliers < self.limits.min_inliers {
            return prediction(Fallback::ConstantVelocity);
        }
        if pair
            .inlier_votes
            .is_some_and(|votes| votes < self.limits.min_inlier_votes)
        {
            return prediction(Fallback::DegenerateScene);
        }
        let gated_before = std::mem::replace(&mut self.gated_last, false);
        if self.measured && !gated_before && self.implausible(&pair.transform, predicted, gap) {
            // The static scene usually still agrees with the prediction: a larger wrong consensus (a
            // passing car, a repeated facade) outvoted it, and its own solve beats the prediction.
            if let Some(guided) = self.consensus_near(pair, predicted) {
                return Judgement {
                    motion: guided,
                    fallback: Some(Fallback::GuidedConsensus),
                };
            }
            self.gated_last = true;
            return prediction(Fallback::ImplausibleMotion);
        }
        Judgement {
            motion: pair.transform,
            fallback: None,
        }
    }

    /// The solve of the matches that agree with `predicted` (within twice the threshold: the prediction
    /// is itself a few centimetres off), solved once more on its own inliers at the threshold; `None`
    /// when they are no consensus of their own or do not determine a motion.
    pub fn consensus_near(
        &self,
        pair: &PairEvidence<'_>,
        predicted: &Matrix4<f64>,
    ) -> Option<Matrix4<f64>> {
        let limits = &self.limits;
        let needed =
            (limits.min_inliers as f64).max(limits.guided_fraction * pair.num_inliers as f64);
        let near = agreeing(pair, predicted, 2.0 * limits.threshold);
        if (near.len() as f64) < needed {
            return None;
        }
        let transform = self.refit(pair, &near)?;
        let inliers = agreeing(pair, &transform, limits.threshold);
        if (inliers.len() as f64) < needed {
            return None;
        }
        self.refit(pair, &inliers)
    }

    fn refit(&self, pair: &PairEvidence<'_>, chosen: &[usize]) -> Option<Matrix4<f64>> {
        let source: Vec<_> = chosen.iter().map(|&i| pair.source[i]).collect();
        let target: Vec<_> = chosen.iter().map(|&i| pair.target[i]).collect();
        // Degenerate agreeing matches (collinear, coincident) are no consensus.
        let solved = self.limits.refit.solve(&source, &target).ok()?;
        Some(solved.to_homogeneous())
    }
}

/// The matches whose source, moved by `transform`, lies within `radius` of its target.
fn agreeing(pair: &PairEvidence<'_>, transform: &Matrix4<f64>, radius: f64) -> Vec<usize> {
    let rotation = transform.fixed_view::<3, 3>(0, 0);
    let translation: Vector3<f64> = transform.fixed_view::<3, 1>(0, 3).into_owned();
    pair.source
        .iter()
        .zip(pair.target)
        .enumerate()
        .filter(|(_, (source, target))| {
            (rotation * source.coords + translation - target.coords).norm() < radius
        })
        .map(|(i, _)| i)
        .collect()
}

/// Distance (m) and angle (°) between two transforms: of the motion `a⁻¹·b`, the angle from
/// `atan2(sin θ, cos θ)` (accurate for small angles), as `dmlo.metrics.pose_difference`; both rigid.
pub fn pose_difference(a: &Matrix4<f64>, b: &Matrix4<f64>) -> (f64, f64) {
    let step = rigid_inverse(a) * b;
    let moved = step.fixed_view::<3, 1>(0, 3).norm();
    let skew = Vector3::new(
        step[(2, 1)] - step[(1, 2)],
        step[(0, 2)] - step[(2, 0)],
        step[(1, 0)] - step[(0, 1)],
    );
    let sine = 0.5 * skew.norm();
    let cosine = 0.5 * (step[(0, 0)] + step[(1, 1)] + step[(2, 2)] - 1.0);
    (moved, sine.atan2(cosine).to_degrees())
}

/// The rigid motion halfway between two: the rotation the projection of `R_a + R_b` onto SO(3) (for two
/// rotations their geodesic midpoint), the translation the mean; as `dmlo.poses.midpoint_motion`.
pub fn midpoint_motion(a: &Matrix4<f64>, b: &Matrix4<f64>) -> Matrix4<f64> {
    let sum: Matrix3<f64> = a.fixed_view::<3, 3>(0, 0) + b.fixed_view::<3, 3>(0, 0);
    let mut middle = Matrix4::identity();
    middle
        .fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&nearest_rotation(&sum));
    let translation = (a.fixed_view::<3, 1>(0, 3) + b.fixed_view::<3, 1>(0, 3)) / 2.0;
    middle.fixed_view_mut::<3, 1>(0, 3).copy_from(&translation);
    middle
}

/// The rotation nearest to `matrix` in the Frobenius norm (SVD, its reflection fixed).
fn nearest_rotation(matrix: &Matrix3<f64>) -> Matrix3<f64> {
    let svd = matrix.svd(true, true);
    let (u, v_t) = (svd.u.expect("asked for"), svd.v_t.expect("asked for"));
    let fix = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, (u * v_t).determinant().signum()));
    u * fix * v_t
}

/// `transform` with its rotation block made the nearest rotation and its last row exact. A pose chained
/// from motions that were themselves composed from the velocity (pairs matched from the prediction)
/// feeds its round-off back through the next velocity, and [`rigid_inverse`] of a matrix slightly off
/// the rotations is not its inverse: left alone, the chain's departure from a rotation grows by a
/// constant factor every frame until the poses overflow. Each pose is made rigid before it is kept.
pub fn nearest_rigid(transform: &Matrix4<f64>) -> Matrix4<f64> {
    let mut rigid = Matrix4::identity();
    rigid
        .fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&nearest_rotation(
            &transform.fixed_view::<3, 3>(0, 0).into(),
        ));
    rigid
        .fixed_view_mut::<3, 1>(0, 3)
        .copy_from(&transform.fixed_view::<3, 1>(0, 3));
    rigid
}

/// The inverse of a rigid transform `[R t; 0 1]`: `[Rᵀ −Rᵀt; 0 1]`, its last row exact (a general inverse
/// leaves round-off there, which poses chained from it would carry).
pub fn rigid_inverse(transform: &Matrix4<f64>) -> Matrix4<f64> {
    let rotation = transform.fixed_view::<3, 3>(0, 0).transpose();
    let translation = -(rotation * transform.fixed_view::<3, 1>(0, 3));
    let mut inverse = Matrix4::identity();
    inverse.fixed_view_mut::<3, 3>(0, 0).copy_from(&rotation);
    inverse.fixed_view_mut::<3, 1>(0, 3).copy_from(&translation);
    inverse
}

/// `matrix^n`, multiplied in the order numpy's `matrix_power` uses (the small powers written out, then
/// binary decomposition).
pub fn matrix_power(matrix: &Matrix4<f64>, n: usize) -> Matrix4<f64> {
    match n {
        0 => Matrix4::identity(),
        1 => *matrix,
        2 => matrix * matrix,
        3 => (matrix * matrix) * matrix,
        _ => {
            let (mut z, mut result): (Option<Matrix4<f64>>, Option<Matrix4<f64>>) = (None, None);
            let mut n = n;
            while n > 0 {
                let square = match z {
                    None => *matrix,
                    Some(previous) => previous * previous,
                };
                z = Some(square);
                if n % 2 == 1 {
                    result = Some(match result {
                        None => square,
                        Some(partial) => partial * square,
                    });
                }
                n /= 2;
            }
            result.unwrap_or_else(Matrix4::identity)
        }
    }
}
