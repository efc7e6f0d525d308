#![forbid(unsafe_code)]
//! RANSAC's settings ([`RansacConfig`], with the solve of its refits, [`Refit`]) and its answer
//! ([`RansacResult`]).

use nalgebra::{Isometry3, Point3};

use crate::error::{Error, Result};
use crate::ray_noise::{ray_noise_refit, RayNoise};
use crate::rigid::rigid_transform;

/// RANSAC settings; `Default` is the paper's (0.1 m threshold) with 0.999 confidence.
#[derive(Debug, Clone, PartialEq)]
pub struct RansacConfig {
    /// A match is an inlier when `‖dst − T·src‖ < threshold` (metres).
    pub threshold: f64,
    /// Stop once a better hypothesis would have been found with this probability (0 < c < 1).
    pub confidence: f64,
    /// Upper bound on the hypotheses drawn (≥ 1).
    pub max_iterations: usize,
    /// Seed of the sampler.
    pub seed: u64,
    /// Hypotheses drawn per parallel batch (≥ 1); changes speed only, never the result.
    pub batch_size: usize,
    /// Least-squares refits after the search, each on the inliers of the motion before it (the first on
    /// those of the best hypothesis), until the inlier set stops changing. A refit is kept even when its
    /// consensus is smaller: the inlier count picks the hypothesis, least squares the motion (on the
    /// odometry's bench drives this lowers the pair rotation error by 4–8 %, against keeping only refits
    /// that do not shrink the consensus). 0 returns the best minimal-sample hypothesis itself.
    pub refine_iterations: usize,
    /// The solve of each refit.
    pub refit: Refit,
}

/// How RANSAC's refits solve for the motion on the inliers.
#[derive(Debug, Clone, PartialEq, Default)]
pub enum Refit {
    /// The closed-form SVD solve (Eq. 12–14): isotropic noise, the paper's.
    #[default]
    PointToPoint,
    /// The SVD solve, then Gauss–Newton under ray noise ([`crate::ray_noise`]), with the refits' inliers
    /// chosen under the same model: within the threshold along the target's ray, and across it within
    /// the threshold or the width of `bearing_threshold_deg` at the match's range, whichever is larger
    /// (an ellipsoid around the target point). Every target point must lie in its sensor's frame, at
    /// least [`crate::ray_noise::MIN_RANGE`] from the origin.
    RayNoise {
        /// The noise model of the Gauss–Newton solve.
        noise: RayNoise,
        /// Bearing tolerance of a refit's inliers, degrees (≥ 0, < 90; 0: the threshold alone).
        bearing_threshold_deg: f64,
    },
}

impl Refit {
    /// The motion (`dst ≈ T·src`) of pairs taken as inliers, solved as one of RANSAC's refits is: the
    /// closed-form SVD solve, then for [`Refit::RayNoise`] the Gauss–Newton refit started there.
    pub fn solve(&self, src: &[Point3<f64>], dst: &[Point3<f64>]) -> Result<Isometry3<f64>> {
        self.validate()?;
        let closed_form = rigid_transform(src, dst, None)?;
        match self {
            Refit::PointToPoint => Ok(closed_form),
            Refit::RayNoise { noise, .. } => {
                Ok(ray_noise_refit(src, dst, &closed_form, noise)?.transform)
            }
        }
    }

    pub(super) fn validate(&self) -> Result<()> {
        if let Refit::RayNoise {
            noise,
            bearing_threshold_deg,
        } = self
        {
            noise.validate()?;
            if !(bearing_threshold_deg.is_finite() && (0.0..90.0).contains(bearing_threshold_deg)) {
                return Err(Error::invalid(
                    "bearing_threshold_deg",
                    format!("must be in [0, 90) degrees, got {bearing_threshold_deg}"),
                ));
            }
        }
        Ok(())
    }
}

impl Default for RansacConfig {
    fn default() -> Self {
        RansacConfig {
            threshold: 0.1,
            confidence: 0.999,
            max_iterations: 1000,
            seed: 0,
            batch_size: 64,
            refine_iterations: 10,
            refit: Refit::PointToPoint,
        }
    }
}

/// What RANSAC found.
#[derive(Debug, Clone, PartialEq)]
pub struct RansacResult {
    /// The motion `T` with `dst ≈ T·src` (after refitting on the inliers).
    pub transform: Isometry3<f64>,
    /// Per match: true when it is an inlier of `transform`.
    pub inliers: Vec<bool>,
    /// Number of `true` in `inliers` (≥ 1: an answer without inliers is an error).
    pub num_inliers: usize,
    /// Hypotheses drawn (including degenerate samples).
    pub iterations: usize,
    /// Root mean square distance of the inliers under `transform`, metres.
    pub rmse: f64,
}
