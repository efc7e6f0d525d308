#![forbid(unsafe_code)]
//! RANSAC around the closed-form rigid solve (paper §III-D-b): minimal samples of 3 matches,
//! inliers within a distance threshold, an adaptive number of hypotheses for a target confidence, and
//! a final refit on all inliers.
//!
//! With a vote per match ([`ransac_rigid_voted`]) a hypothesis's consensus is the sum of its inliers'
//! votes and samples draw each match as often as it votes.
//!
//! Determinism: samples are drawn serially from a ChaCha8 generator seeded by
//! [`RansacConfig::seed`], in batches; each batch's hypotheses are solved and scored in parallel
//! (rayon, in the caller's pool), then walked in order exactly as a serial loop would, with the best
//! chosen by (more inliers, then lower summed squared inlier error, then earlier hypothesis). The
//! result is therefore identical for any number of threads.

use std::cmp::Ordering;

use nalgebra::{Isometry3, Matrix3, Point3, Vector3};
use rand::distr::weighted::WeightedIndex;
use rand::distr::Distribution;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::ray_noise::{check_rays, ray_noise_refit, RayNoise};
use crate::rigid::{check_pairs, isometry_from_parts, rigid_transform, Svd3};

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

    fn validate(&self) -> Result<()> {
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

/// Matches in structure-of-arrays form. Hypotheses are scored in `f32` in independent lanes, so the
/// loop vectorises; the minimal solves, the final refit and the RMSE use the `f64` points.
///
/// The `f32` columns hold each point relative to a reference point of its own set (`src_origin`,
/// `dst_origin`), and hypotheses are moved into that frame before scoring: `f32` rounds coordinates
/// in the millions of metres (georeferenced clouds, UTM) to whole metres, far above the threshold,
/// while the spread of the matches around their reference point stays small.
struct Matches {
    src: [Vec<f32>; 3],
    dst: [Vec<f32>; 3],
    src_origin: Vector3<f64>,
    dst_origin: Vector3<f64>,
    src64: Vec<Vector3<f64>>,
    dst64: Vec<Vector3<f64>>,
    /// Each match's vote in a hypothesis's score; `None`: one each.
    votes: Option<Vec<f32>>,
}

/// The per-axis median of `points`: a reference point inside the bulk of the cloud that a few far
/// outliers do not drag away, as a mean would. `points` is not empty.
fn median_point(points: &[Point3<f64>]) -> Vector3<f64> {
    let middle = points.len() / 2;
    Vector3::from_fn(|k, _| {
        let mut values: Vec<f64> = points.iter().map(|p| p[k]).collect();
        *values.select_nth_unstable_by(middle, f64::total_cmp).1
    })
}

/// Lanes of the scoring loop.
const LANES: usize = 8;

/// A hypothesis as the scoring loop uses it: row-major rotation, then translation.
struct Hypothesis32 {
    r: [f32; 9],
    t: [f32; 3],
}

impl Hypothesis32 {
    /// `transform` (`dst ≈ T·src`) in the frame where source points are taken relative to
    /// `src_origin` and target points relative to `dst_origin`: the same rotation, the translation
    /// `R·src_origin + t − dst_origin` (formed in `f64`, so it is small and exact enough for `f32`).
    fn new(
        transform: &Isometry3<f64>,
        src_origin: &Vector3<f64>,
        dst_origin: &Vector3<f64>,
    ) -> Self {
        let r = transform.rotation.to_rotation_matrix().into_inner();
        let t = r * src_origin + transform.translation.vector - dst_origin;
        Hypothesis32 {
            r: [0, 1, 2, 3, 4, 5, 6, 7, 8].map(|k| r[(k / 3, k % 3)] as f32),
            t: [t.x as f32, t.y as f32, t.z as f32],
        }
    }

    #[inline(always)]
    fn distance_sq(&self, s: [f32; 3], d: [f32; 3]) -> f32 {
        let r = &self.r;
        let ex = r[0] * s[0] + r[1] * s[1] + r[2] * s[2] + self.t[0] - d[0];
        let ey = r[3] * s[0] + r[4] * s[1] + r[5] * s[2] + self.t[1] - d[1];
        let ez = r[6] * s[0] + r[7] * s[1] + r[8] * s[2] + self.t[2] - d[2];
        ex * ex + ey * ey + ez * ez
    }
}

impl Matches {
    /// `src` and `dst` are not empty.
    fn new(src: &[Point3<f64>], dst: &[Point3<f64>], votes: Option<&[f64]>) -> Self {
        let (src_origin, dst_origin) = (median_point(src), median_point(dst));
        let column = |points: &[Point3<f64>], origin: &Vector3<f64>, k: usize| {
            points
                .iter()
                .map(|p| (p[k] - origin[k]) as f32)
                .collect::<Vec<f32>>()
        };
        Matches {
            src: [0, 1, 2].map(|k| column(src, &src_origin, k)),
            dst: [0, 1, 2].map(|k| column(dst, &dst_origin, k)),
            src_origin,
            dst_origin,
            src64: src.iter().map(|p| p.coords).collect(),
            dst64: dst.iter().map(|p| p.coords).collect(),
            votes: votes.map(|v| v.iter().map(|&w| w as f32).collect()),
        }
    }

    fn hypothesis32(&self, transform: &Isometry3<f64>) -> Hypothesis32 {
        Hypothesis32::new(transform, &self.src_origin, &self.dst_origin)
    }

    fn at(&self, i: usize) -> ([f32; 3], [f32; 3]) {
        (
            [self.src[0][i], self.src[1][i], self.src[2][i]],
            [self.dst[0][i], self.dst[1][i], self.dst[2][i]],
        )
    }

    /// (summed votes of the inliers, their count, their summed squared distance).
    fn score(&self, transform: &Isometry3<f64>, threshold_sq: f64) -> Score {
        let h = self.hypothesis32(transform);
        let threshold_sq = threshold_sq as f32;
        let n = self.src[0].len();
        let full = n - n % LANES;
        let mut counts = [0u32; LANES];
        let mut sums = [0.0f32; LANES];
        let mut errors = [0.0f32; LANES];
        let [sx, sy, sz] = &self.src;
        let [dx, dy, dz] = &self.dst;
        let no_votes = [1.0f32; LANES];
        for base in (0..full).step_by(LANES) {
            let (sx, sy, sz) = (
                &sx[base..base + LANES],
                &sy[base..base + LANES],
                &sz[base..base + LANES],
            );
            let (dx, dy, dz) = (
                &dx[base..base + LANES],
                &dy[base..base + LANES],
                &dz[base..base + LANES],
            );
            let votes = self
                .votes
                .as_ref()
                .map_or(&no_votes[..], |v| &v[base..base + LANES]);
            for l in 0..LANES {
                let d = h.distance_sq([sx[l], sy[l], sz[l]], [dx[l], dy[l], dz[l]]);
                let inlier = d < threshold_sq;
                counts[l] += inlier as u32;
                sums[l] += if inlier { votes[l] } else { 0.0 };
                errors[l] += if inlier { d } else { 0.0 };
            }
        }
        let mut count = counts.iter().map(|&c| c as usize).sum::<usize>();
        let mut votes = sums.iter().map(|&v| v as f64).sum::<f64>();
        let mut error = errors.iter().map(|&e| e as f64).sum::<f64>();
        for i in full..n {
            let (s, d) = self.at(i);
            let d = h.distance_sq(s, d);
            if d < threshold_sq {
                count += 1;
                votes += self.votes.as_ref().map_or(1.0, |v| v[i] as f64);
                error += d as f64;
            }
        }
        Score {
            votes,
            count,
            error,
        }
    }

    /// The inlier mask, decided exactly as [`Matches::score`] counts.
    fn inlier_mask(&self, transform: &Isometry3<f64>, threshold_sq: f64) -> Vec<bool> {
        let h = self.hypothesis32(transform);
        (0..self.src[0].len())
            .map(|i| {
                let (s, d) = self.at(i);
                h.distance_sq(s, d) < threshold_sq as f32
            })
            .collect()
    }

    /// The inlier mask of [`Refit::RayNoise`]: `(a/τ)² + (c/τ_c)² < 1` for the error's components `a`
    /// along the target's ray and `c` across it, `τ = threshold`, `τ_c = max(τ, r·bearing_tan)`.
    fn ray_inlier_mask(
        &self,
        transform: &Isometry3<f64>,
        threshold: f64,
        bearing_tan: f64,
    ) -> Vec<bool> {
        self.src64
            .iter()
            .zip(&self.dst64)
            .map(|(p, q)| {
                let error = (transform * Point3::from(*p)).coords - q;
                let range = q.norm();
                let along = error.dot(q) / range;
                let across_sq = (error.norm_squared() - along * along).max(0.0);
                let across_threshold = threshold.max(range * bearing_tan);
                (along / threshold).powi(2) + across_sq / (across_threshold * across_threshold)
                    < 1.0
            })
            .collect()
    }

    fn point(&self, i: usize) -> (Vector3<f64>, Vector3<f64>) {
        (self.src64[i], self.dst64[i])
    }

    /// The rigid solve on three matches; `None` when they are (nearly) collinear.
    fn minimal_solve(&self, sample: [usize; 3], svd: &mut Svd3) -> Option<Isometry3<f64>> {
        let pairs = sample.map(|i| self.point(i));
        let p_mean = (pairs[0].0 + pairs[1].0 + pairs[2].0) / 3.0;
        let q_mean = (pairs[0].1 + pairs[1].1 + pairs[2].1) / 3.0;
        let mut h = Matrix3::zeros();
        for (p, q) in &pairs {
            h += (p - p_mean) * (q - q_mean).transpose();
        }
        let rotation = svd.rotation_from_cross_covariance(&h)?;
        Some(isometry_from_parts(
            &rotation,
            &(q_mean - rotation * p_mean),
        ))
    }
}

/// Votes are finite, ≥ 0, not all 0, one per match.
fn check_votes(votes: &[f64], n: usize) -> Result<()> {
    if votes.len() != n {
        return Err(Error::invalid(
            "votes",
            format!("has {} entries for {n} matches", votes.len()),
        ));
    }
    if let Some(i) = votes.iter().position(|v| !(v.is_finite() && *v >= 0.0)) {
        return Err(Error::invalid(
            "votes",
            format!("entry {i} is {} (votes must be finite and >= 0)", votes[i]),
        ));
    }
    if votes.iter().all(|&v| v == 0.0) {
        return Err(Error::invalid(
            "votes",
            "are all 0: no hypothesis could win",
        ));
    }
    Ok(())
}

/// Hypotheses needed to draw an all-inlier sample of 3 with probability `confidence` when a fraction
/// `inlier_ratio` of the matches are inliers.
fn required_iterations(inlier_ratio: f64, confidence: f64, max_iterations: usize) -> usize {
    let all_inliers = inlier_ratio.powi(3);
    if all_inliers >= 1.0 {
        return 1;
    }
    if all_inliers <= 0.0 {
        return max_iterations;
    }
    let needed = (1.0 - confidence).ln() / (1.0 - all_inliers).ln();
    if needed.is_finite() {
        (needed.ceil().max(1.0) as usize).min(max_iterations)
    } else {
        max_iterations
    }
}

/// A hypothesis's consensus: the summed votes of its inliers (their count when matches carry no votes),
/// how many they are, and their summed squared distance.
#[derive(Debug, Clone, Copy)]
struct Score {
    votes: f64,
    count: usize,
    error: f64,
}

/// (score, hypothesis index): `a` better than `b`? More votes, then a lower error, then the earlier.
fn is_better(a: (Score, usize), b: (Score, usize)) -> bool {
    match a.0.votes.total_cmp(&b.0.votes) {
        Ordering::Greater => true,
        Ordering::Less => false,
        Ordering::Equal => match a.0.error.total_cmp(&b.0.error) {
            Ordering::Less => true,
            Ordering::Greater => false,
            Ordering::Equal => a.1 < b.1,
        },
    }
}

/// Estimates `T` with `dst ≈ T·src` from putative matches `src[i] ↔ dst[i]`, robust to outliers.
///
/// Errors: [`Error::TooFewPoints`] for fewer than 3 matches; [`Error::InvalidArgument`] for bad
/// settings, mismatched lengths or non-finite points; [`Error::Degenerate`] when every sample drawn was
/// collinear, or when the answer has no inlier at all (no match within `threshold`). With no consistent
/// motion (all outliers) the result is otherwise the best hypothesis found, with a few chance inliers:
/// callers judge `num_inliers`, which is at least 1.
pub fn ransac_rigid(
    src: &[Point3<f64>],
    dst: &[Point3<f64>],
    config: &RansacConfig,
) -> Result<RansacResult> {
    ransac_rigid_voted(src, dst, None, config)
}

/// [`ransac_rigid`] with a vote per match: a hypothesis's consensus is the sum of its inliers' votes
/// instead of their count, and minimal samples draw each match with a probability in proportion to its
/// vote, so that matches which cannot tell motions apart (e.g. the road's, whose vote
/// [`crate::surface::horizontal_votes`] lowers) neither outvote nor crowd out the few that can. The
/// refits are unchanged: they solve on every inlier of the winning hypothesis. `votes` (≥ 0, finite,
/// not all 0) has one entry per match; with fewer than 3 non-zero votes samples are drawn uniformly.
pub fn ransac_rigid_voted(
    src: &[Point3<f64>],
    dst: &[Point3<f64>],
    votes: Option<&[f64]>,
    config: &RansacConfig,
) -> Result<RansacResult> {
    if !(config.threshold.is_finite() && config.threshold > 0.0) {
        return Err(Error::invalid(
            "threshold",
            format!("must be finite and > 0, got {}", config.threshold),
        ));
    }
    if !(config.confidence > 0.0 && config.confidence < 1.0) {
        return Err(Error::invalid(
            "confidence",
            format!("must be in (0, 1), got {}", config.confidence),
        ));
    }
    if config.max_iterations == 0 {
        return Err(Error::invalid("max_iterations", "must be >= 1"));
    }
    if config.batch_size == 0 {
        return Err(Error::invalid("batch_size", "must be >= 1"));
    }
    check_pairs(src, dst)?;
    config.refit.validate()?;
    if let Refit::RayNoise { .. } = &config.refit {
        check_rays(dst)?;
    }
    let n = src.len();
    if n < 3 {
        return Err(Error::TooFewPoints { needed: 3, got: n });
    }
    if let Some(votes) = votes {
        check_votes(votes, n)?;
    }
    let matches = Matches::new(src, dst, votes);
    let threshold_sq = config.threshold * config.threshold;
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    // With votes, a match is drawn as often as it votes: a sample of the matches that can tell
    // motions apart, rather than of the road's many that cannot.
    let weighted = votes
        .filter(|v| v.iter().filter(|&&w| w > 0.0).count() >= 3)
        .map(|v| WeightedIndex::new(v).expect("votes checked: finite, >= 0, not all 0"));
    let mut draw = || -> [usize; 3] {
        if let Some(weighted) = &weighted {
            let a = weighted.sample(&mut rng);
            let mut b = weighted.sample(&mut rng);
            while b == a {
                b = weighted.sample(&mut rng);
            }
            let mut c = weighted.sample(&mut rng);
            while c == a || c == b {
                c = weighted.sample(&mut rng);
            }
            return [a, b, c];
        }
        let a = rng.random_range(0..n);
        let mut b = rng.random_range(0..n - 1);
        if b >= a {
            b += 1;
        }
        let (lo, hi) = if a < b { (a, b) } else { (b, a) };
        let mut c = rng.random_range(0..n - 2);
        if c >= lo {
            c += 1;
        }
        if c >= hi {
            c += 1;
        }
        [a, b, c]
    };
    let total_votes = votes.map_or(n as f64, |v| v.iter().sum());

    let mut best: Option<(Score, usize, Isometry3<f64>)> = None;
    let mut required = config.max_iterations;
    let mut iterations = 0;
    while iterations < required {
        let batch = config.batch_size.min(config.max_iterations - iterations);
        let samples: Vec<[usize; 3]> = (0..batch).map(|_| draw()).collect();
        let scored: Vec<Option<(Score, Isometry3<f64>)>> = samples
            .par_iter()
            .map_init(Svd3::new, |svd, &sample| {
                let hypothesis = matches.minimal_solve(sample, svd)?;
                Some((matches.score(&hypothesis, threshold_sq), hypothesis))
            })
            .collect();
        let start = iterations;
        for (k, outcome) in scored.into_iter().enumerate() {
            let index = start + k;
            iterations = index + 1;
            if let Some((score, hypothesis)) = outcome {
                let improves = best
                    .as_ref()
                    .is_none_or(|b| is_better((score, index), (b.0, b.1)));
                if improves {
                    best = Some((score, index, hypothesis));
                    // The chance of an all-inlier sample: the winner's share of the votes (of the
                    // matches, without votes), as samples are drawn.
                    let share = if weighted.is_some() {
                        score.votes / total_votes
                    } else {
                        score.count as f64 / n as f64
                    };
                    required = required_iterations(share, config.confidence, config.max_iterations);
                }
            }
            if iterations >= required {
                break;
            }
        }
    }
    let Some((Score { mut count, .. }, _, mut transform)) = best else {
        return Err(Error::Degenerate(format!(
            "all {iterations} samples were collinear"
        )));
    };

    // The least-squares refit on all inliers of the best hypothesis is the answer (a 3-match sample
    // carries its noise); further refits on the new inlier set follow until it is stable.
    let mut inliers = matches.inlier_mask(&transform, threshold_sq);
    for _ in 0..config.refine_iterations {
        let (inlier_src, inlier_dst): (Vec<Point3<f64>>, Vec<Point3<f64>>) = inliers
            .iter()
            .enumerate()
            .filter(|(_, &inlier)| inlier)
            .map(|(i, _)| (src[i], dst[i]))
            .unzip();
        let Ok(refit) = config.refit.solve(&inlier_src, &inlier_dst) else {
            break;
        };
        let refit_inliers = match &config.refit {
            Refit::PointToPoint => matches.inlier_mask(&refit, threshold_sq),
            Refit::RayNoise {
                bearing_threshold_deg,
                ..
            } => matches.ray_inlier_mask(
                &refit,
                config.threshold,
                bearing_threshold_deg.to_radians().tan(),
            ),
        };
        let stable = refit_inliers == inliers;
        count = refit_inliers.iter().filter(|&&inlier| inlier).count();
        (transform, inliers) = (refit, refit_inliers);
        if stable {
            break;
        }
    }
    if count == 0 {
        // No motion is supported by any match (every residual is above the threshold): report it
        // rather than a transform with an empty consensus and an RMSE of nothing.
        return Err(Error::Degenerate(format!(
            "no match lies within the threshold ({} m) of any motion tried",
            config.threshold
        )));
    }
    let squared: f64 = inliers
        .iter()
        .enumerate()
        .filter(|(_, &inlier)| inlier)
        .map(|(i, _)| {
            (transform * Point3::from(matches.src64[i]) - Point3::from(matches.dst64[i]))
                .norm_squared()
        })
        .sum();
    let rmse = (squared / count as f64).sqrt();
    Ok(RansacResult {
        transform,
        num_inliers: count,
        inliers,
        iterations,
        rmse,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[allow(clippy::type_complexity)]
    fn scene(
        seed: u64,
        n: usize,
        outlier_ratio: f64,
        noise: f64,
    ) -> (
        Vec<Point3<f64>>,
        Vec<Point3<f64>>,
        Isometry3<f64>,
        Vec<bool>,
    ) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let truth = Isometry3::new(
            Vector3::new(0.9, -0.05, 0.02),
            Vector3::new(0.003, -0.002, 0.04),
        );
        let mut src = Vec::new();
        let mut dst = Vec::new();
        let mut is_inlier = Vec::new();
        for i in 0..n {
            let p = Point3::new(
                rng.random_range(-40.0..40.0),
                rng.random_range(-40.0..40.0),
                rng.random_range(-2.0..3.0),
            );
            let outlier = (i as f64) < outlier_ratio * n as f64;
            let q = if outlier {
                Point3::new(
                    rng.random_range(-40.0..40.0),
                    rng.random_range(-40.0..40.0),
                    rng.random_range(-2.0..3.0),
                )
            } else {
                truth * p
                    + Vector3::new(
                        rng.random_range(-1.0..1.0),
                        rng.random_range(-1.0..1.0),
                        rng.random_range(-1.0..1.0),
                    ) * noise
            };
            src.push(p);
            dst.push(q);
            is_inlier.push(!outlier);
        }
        (src, dst, truth, is_inlier)
    }

    /// The (src, dst) pairs `result` marks as inliers.
    fn inlier_pairs(
        src: &[Point3<f64>],
        dst: &[Point3<f64>],
        result: &RansacResult,
    ) -> (Vec<Point3<f64>>, Vec<Point3<f64>>) {
        (0..src.len())
            .filter(|&i| result.inliers[i])
            .map(|i| (src[i], dst[i]))
            .unzip()
    }

    /// `work` run in a rayon pool of `threads` threads.
    fn in_pool<T: Send>(threads: usize, work: impl FnOnce() -> T + Send) -> T {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(work)
    }

    #[test]
    fn recovers_a_known_motion_with_80_percent_outliers() {
        let (src, dst, truth, is_inlier) = scene(21, 1000, 0.8, 0.02);
        let result = ransac_rigid(&src, &dst, &RansacConfig::default()).unwrap();
        let rotation_error = (result.transform.rotation.inverse() * truth.rotation)
            .angle()
            .to_degrees();
        let translation_error =
            (result.transform.translation.vector - truth.translation.vector).norm();
        assert!(rotation_error < 0.05, "rotation error {rotation_error}°");
        assert!(
            translation_error < 0.02,
            "translation error {translation_error} m"
        );
        let wrong = result
            .inliers
            .iter()
            .zip(&is_inlier)
            .filter(|(a, b)| a != b)
            .count();
        assert!(wrong <= 3, "{wrong} matches misclassified");
        assert_eq!(
            result.num_inliers,
            result.inliers.iter().filter(|&&v| v).count()
        );
        // The answer is the least-squares fit on its inliers, not a noisy 3-match sample.
        let (inlier_src, inlier_dst) = inlier_pairs(&src, &dst, &result);
        let refit = rigid_transform(&inlier_src, &inlier_dst, None).unwrap();
        assert!(
            (refit.to_homogeneous() - result.transform.to_homogeneous())
                .abs()
                .max()
                < 1e-9
        );
        assert!(result.iterations <= 1000 && result.iterations > 0);
    }

    #[test]
    fn answer_is_the_least_squares_fit_of_its_inliers_even_when_that_shrinks_the_consensus() {
        // Noise near the threshold: refits move matches in and out of the inlier set, and some
        // refit keeps fewer matches than the motion before it. The answer is still the fixed point
        // of "least squares on the inliers" (a refit is never rejected for its smaller consensus).
        for seed in 0..40 {
            let noise = [0.06, 0.08][(seed % 2) as usize];
            let (src, dst, _, _) = scene(100 + seed, 300, 0.4, noise);
            let config = RansacConfig {
                seed,
                ..Default::default()
            };
            let result = ransac_rigid(&src, &dst, &config).unwrap();
            let (inlier_src, inlier_dst) = inlier_pairs(&src, &dst, &result);
            let refit = rigid_transform(&inlier_src, &inlier_dst, None).unwrap();
            let gap = (refit.to_homogeneous() - result.transform.to_homogeneous())
                .abs()
                .max();
            assert!(
                gap < 1e-9,
                "seed {seed}: the answer is {gap} from the fit of its inliers"
            );
        }
    }

    #[test]
    fn with_the_ray_noise_refit_the_answer_is_that_refit_of_its_inliers() {
        let (src, dst, truth, _) = scene(25, 600, 0.5, 0.03);
        let noise = RayNoise {
            range_ratio: 2.0,
            ..Default::default()
        };
        let config = RansacConfig {
            refit: Refit::RayNoise {
                noise: noise.clone(),
                bearing_threshold_deg: 0.0,
            },
            ..Default::default()
        };
        let result = ransac_rigid(&src, &dst, &config).unwrap();
        let (inlier_src, inlier_dst) = inlier_pairs(&src, &dst, &result);
        let closed_form = rigid_transform(&inlier_src, &inlier_dst, None).unwrap();
        let refit = ray_noise_refit(&inlier_src, &inlier_dst, &closed_form, &noise).unwrap();
        assert_eq!(result.transform, refit.transform);
        assert_ne!(result.transform, closed_form);
        let rotation_error = (result.transform.rotation.inverse() * truth.rotation).angle();
        assert!(rotation_error.to_degrees() < 0.05);
        let threads = |n: usize| in_pool(n, || ransac_rigid(&src, &dst, &config).unwrap());
        assert_eq!(threads(1), threads(3));
        // A target point at the sensor's origin has no ray: refused by name, not skipped silently.
        let mut at_origin = dst.clone();
        at_origin[7] = Point3::origin();
        assert!(matches!(
            ransac_rigid(&src, &at_origin, &config),
            Err(Error::InvalidArgument {
                argument: "dst",
                ..
            })
        ));
        assert!(ransac_rigid(&src, &at_origin, &RansacConfig::default()).is_ok());
    }

    #[test]
    fn a_refit_solves_as_the_svd_solve_then_its_gauss_newton_refit() {
        let (src, dst, _, is_inlier) = scene(31, 300, 0.0, 0.03);
        assert!(is_inlier.iter().all(|&inlier| inlier));
        let closed_form = rigid_transform(&src, &dst, None).unwrap();
        assert_eq!(Refit::PointToPoint.solve(&src, &dst).unwrap(), closed_form);
        let noise = RayNoise {
            range_ratio: 2.0,
            ..Default::default()
        };
        let ray = Refit::RayNoise {
            noise: noise.clone(),
            bearing_threshold_deg: 0.2,
        };
        let refined = ray_noise_refit(&src, &dst, &closed_form, &noise).unwrap();
        assert_eq!(ray.solve(&src, &dst).unwrap(), refined.transform);
        assert_ne!(refined.transform, closed_form);
        // Its own settings are checked before anything is solved.
        let bad = Refit::RayNoise {
            noise: RayNoise {
                range_ratio: 0.0,
                ..Default::default()
            },
            bearing_threshold_deg: 0.2,
        };
        assert!(matches!(
            bad.solve(&src, &dst),
            Err(Error::InvalidArgument {
                argument: "range_ratio",
                ..
            })
        ));
    }

    #[test]
    fn ray_noise_inliers_lie_in_an_ellipsoid_stretched_across_the_ray_at_range() {
        let matches = Matches::new(
            &[Point3::new(60.0, 0.0, 0.0); 4],
            &[
                Point3::new(60.0, 0.15, 0.0), // 0.15 m across the ray at 60 m: within 0.2°
                Point3::new(60.0, 0.0, -0.25), // 0.25 m across: beyond 0.2° (0.209 m)
                Point3::new(60.15, 0.0, 0.0), // 0.15 m along the ray: beyond the 0.1 m threshold
                Point3::new(60.07, 0.1, 0.0), // (0.07/0.1)² + (0.1/0.209)² = 0.72
            ],
            None,
        );
        let tan = 0.2f64.to_radians().tan();
        let identity = Isometry3::identity();
        assert_eq!(
            matches.ray_inlier_mask(&identity, 0.1, tan),
            [true, false, false, true]
        );
        // Within the threshold's own radius the test is the Euclidean one.
        assert_eq!(
            matches.ray_inlier_mask(&identity, 0.1, 0.0),
            matches.inlier_mask(&identity, 0.01)
        );
        let near = Matches::new(
            &[Point3::new(5.0, 0.0, 0.0)],
            &[Point3::new(5.0, 0.09, 0.0)],
            None,
        );
        assert_eq!(near.ray_inlier_mask(&identity, 0.1, tan), [true]);
    }

    /// A highway pair: many road matches that agree on no motion at all (the rings locked) with a
    /// low vote, fewer matches on posts that agree on the true motion, and outliers.
    fn locked_rings(seed: u64) -> (Vec<Point3<f64>>, Vec<Point3<f64>>, Vec<f64>, Isometry3<f64>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let truth = Isometry3::new(Vector3::new(-1.0, 0.05, 0.0), Vector3::new(0.0, 0.0, 0.03));
        let (mut src, mut dst, mut votes) = (Vec::new(), Vec::new(), Vec::new());
        for i in 0..600 {
            let angle: f64 = rng.random_range(0.0..std::f64::consts::TAU);
            let range: f64 = rng.random_range(4.0..15.0);
            let road = Point3::new(range * angle.cos(), range * angle.sin(), -1.73);
            let post = Point3::new(
                rng.random_range(-30.0..30.0),
                rng.random_range(-12.0..12.0),
                rng.random_range(-1.0..3.0),
            );
            let (p, q, vote) = match i % 6 {
                0..=3 => (road, road, 0.05), // locked: the same point in both scans
                4 => (post, truth * post, 1.0),
                _ => {
                    let q = Point3::new(
                        rng.random_range(-30.0..30.0),
                        rng.random_range(-12.0..12.0),
                        rng.random_range(-1.0..3.0),
                    );
                    (post, q, rng.random_range(0.05..1.0))
                }
            };
            src.push(p);
            dst.push(q);
            votes.push(vote);
        }
        (src, dst, votes, truth)
    }

    #[test]
    fn votes_keep_locked_road_matches_from_outvoting_the_posts() {
        let (src, dst, votes, truth) = locked_rings(5);
        let config = RansacConfig::default();
        let counted = ransac_rigid(&src, &dst, &config).unwrap();
        assert!(
            counted.transform.translation.vector.norm() < 0.05,
            "the rings win a count"
        );
        let voted = ransac_rigid_voted(&src, &dst, Some(&votes), &config).unwrap();
        let error = voted.transform.inverse() * truth;
        assert!(error.translation.vector.norm() < 1e-6, "{error:?}");
        assert_eq!(voted.num_inliers, 100);
    }

    #[test]
    fn equal_votes_change_nothing_and_voting_is_thread_independent() {
        let (src, dst, _, _) = scene(23, 500, 0.5, 0.05);
        let config = RansacConfig::default();
        let counted = ransac_rigid(&src, &dst, &config).unwrap();
        let ones = vec![1.0; src.len()];
        assert_eq!(
            ransac_rigid_voted(&src, &dst, Some(&ones), &config)
                .unwrap()
                .transform,
            counted.transform
        );
        let (src, dst, votes, _) = locked_rings(6);
        let config = RansacConfig {
            batch_size: 16,
            ..Default::default()
        };
        let run = |threads: usize| {
            in_pool(threads, || {
                ransac_rigid_voted(&src, &dst, Some(&votes), &config).unwrap()
            })
        };
        assert_eq!(run(1), run(3));
    }

    #[test]
    fn bad_votes_are_named() {
        let (src, dst, _, _) = scene(24, 20, 0.0, 0.0);
        let config = RansacConfig::default();
        for votes in [
            vec![1.0; 19],
            vec![-1.0; 20],
            vec![f64::NAN; 20],
            vec![0.0; 20],
        ] {
            let err = ransac_rigid_voted(&src, &dst, Some(&votes), &config).unwrap_err();
            assert!(err.to_string().starts_with("votes:"), "{err}");
        }
        // Fewer than 3 matches with a vote: samples are drawn uniformly, never stuck.
        let mut two = vec![0.0; 20];
        two[0] = 1.0;
        two[1] = 1.0;
        ransac_rigid_voted(&src, &dst, Some(&two), &config).unwrap();
    }

    #[test]
    fn same_seed_same_result_with_1_or_4_threads() {
        let (src, dst, _, _) = scene(22, 2000, 0.7, 0.05);
        let config = RansacConfig {
            seed: 9,
            batch_size: 16,
            ..Default::default()
        };
        let run = |threads: usize| in_pool(threads, || ransac_rigid(&src, &dst, &config).unwrap());
        let one = run(1);
        let four = run(4);
        assert_eq!(one, four);
        // The batch size changes only speed.
        let other_batches = in_pool(2, || {
            ransac_rigid(
                &src,
                &dst,
                &RansacConfig {
                    batch_size: 100,
                    ..config.clone()
                },
            )
            .unwrap()
        });
        assert_eq!(one, other_batches);
        let different_seed =
            ransac_rigid(&src, &dst, &RansacConfig { seed: 10, ..config }).unwrap();
        assert!(
            different_seed.iterations != one.iterations
                || different_seed.transform != one.transform
        );
    }

    #[test]
    fn adaptive_iterations_stop_early_on_clean_data() {
        let (src, dst, truth, _) = scene(23, 500, 0.0, 0.0);
        let result = ransac_rigid(&src, &dst, &RansacConfig::default()).unwrap();
        assert_eq!(result.num_inliers, 500);
        assert!(result.iterations < 10, "{} iterations", result.iterations);
        assert!(
            (result.transform.to_homogeneous() - truth.to_homogeneous())
                .abs()
                .max()
                < 1e-9
        );
        assert!(result.rmse < 1e-9);
    }

    #[test]
    fn inliers_are_counted_exactly_far_from_the_origin() {
        // Georeferenced (UTM-like) coordinates: the same scene and motion moved millions of metres from
        // the origin must give the same consensus as near it.
        for (outlier_ratio, noise) in [(0.0, 0.0), (0.3, 0.02)] {
            let (src, dst, truth, is_inlier) = scene(26, 200, outlier_ratio, noise);
            let near = ransac_rigid(&src, &dst, &RansacConfig::default()).unwrap();
            assert_eq!(near.inliers, is_inlier);
            for offset in [1e6, 5e6, 1e7] {
                let shift = Isometry3::translation(offset, -0.7 * offset, 30.0);
                let (far_src, far_dst): (Vec<_>, Vec<_>) = src
                    .iter()
                    .zip(&dst)
                    .map(|(p, q)| (shift * p, shift * q))
                    .unzip();
                let far_truth = shift * truth * shift.inverse();
                let far = ransac_rigid(&far_src, &far_dst, &RansacConfig::default()).unwrap();
                assert_eq!(far.inliers, is_inlier, "offset {offset} m");
                assert_eq!(far.num_inliers, near.num_inliers, "offset {offset} m");
                assert!(
                    far.iterations <= near.iterations.max(10),
                    "offset {offset} m"
                );
                let rotation_error =
                    (far.transform.rotation.inverse() * far_truth.rotation).angle();
                assert!(rotation_error.to_degrees() < 0.05, "offset {offset} m");
                // The motion moves the scene's own points as the truth does, to well under the noise.
                let worst = far_src
                    .iter()
                    .map(|p| (far.transform * p - far_truth * p).norm())
                    .fold(0.0, f64::max);
                assert!(worst < 0.02 + noise, "offset {offset} m: {worst} m");
                assert!((far.rmse - near.rmse).abs() < 1e-6, "offset {offset} m");
                let threads = |n: usize| {
                    in_pool(n, || {
                        ransac_rigid(&far_src, &far_dst, &RansacConfig::default())
                    })
                };
                assert_eq!(threads(1), threads(3));
            }
        }
    }

    #[test]
    fn a_local_scan_is_registered_into_far_map_coordinates() {
        // Source near its sensor, target in map coordinates millions of metres away: each side is
        // scored relative to a point of its own, not one shared reference between them.
        let (src, local_dst, truth, is_inlier) = scene(27, 200, 0.3, 0.02);
        let to_map = Isometry3::new(
            Vector3::new(4.5e6, 5.4e6, 120.0),
            Vector3::new(0.0, 0.0, 2.0),
        );
        let dst: Vec<_> = local_dst.iter().map(|q| to_map * q).collect();
        let result = ransac_rigid(&src, &dst, &RansacConfig::default()).unwrap();
        assert_eq!(result.inliers, is_inlier);
        let rotation_error =
            (result.transform.rotation.inverse() * (to_map * truth).rotation).angle();
        assert!(rotation_error.to_degrees() < 0.05);
    }

    #[test]
    fn an_answer_without_any_inlier_is_an_error_not_an_empty_consensus() {
        // Only outliers and a threshold far below every residual: no motion has a single inlier.
        let (src, dst, _, _) = scene(28, 100, 1.0, 0.0);
        let config = RansacConfig {
            threshold: 1e-9,
            max_iterations: 50,
            ..Default::default()
        };
        assert!(matches!(
            ransac_rigid(&src, &dst, &config),
            Err(Error::Degenerate(_))
        ));
    }

    #[test]
    fn few_degenerate_and_outlier_only_inputs_do_not_panic_or_hang() {
        let p = |x: f64| Point3::new(x, 2.0 * x, -x);
        assert_eq!(
            ransac_rigid(
                &[p(0.0), p(1.0)],
                &[p(0.0), p(1.0)],
                &RansacConfig::default()
            ),
            Err(Error::TooFewPoints { needed: 3, got: 2 })
        );
        let line: Vec<_> = (0..50).map(|i| p(i as f64)).collect();
        assert!(matches!(
            ransac_rigid(&line, &line, &RansacConfig::default()),
            Err(Error::Degenerate(_))
        ));
        let (src, dst, _, _) = scene(24, 300, 1.0, 0.0);
        let result = ransac_rigid(&src, &dst, &RansacConfig::default()).unwrap();
        assert!(result.num_inliers < 10);
        assert_eq!(result.iterations, 1000);
        for bad in [
            RansacConfig {
                threshold: 0.0,
                ..Default::default()
            },
            RansacConfig {
                confidence: 1.0,
                ..Default::default()
            },
            RansacConfig {
                max_iterations: 0,
                ..Default::default()
            },
        ] {
            assert!(matches!(
                ransac_rigid(&src, &dst, &bad),
                Err(Error::InvalidArgument { .. })
            ));
        }
        let three = [
            Point3::new(0.0, 0.0, 0.0),
            Point3::new(1.0, 0.0, 0.0),
            Point3::new(0.0, 1.0, 0.0),
        ];
        assert_eq!(
            ransac_rigid(&three, &three, &RansacConfig::default())
                .unwrap()
                .num_inliers,
            3
        );
    }
}
