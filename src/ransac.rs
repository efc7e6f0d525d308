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
mod config;
mod consensus;
#[cfg(test)]
mod tests;

use nalgebra::{Isometry3, Point3};
use rand::distr::weighted::WeightedIndex;
use rand::distr::Distribution;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

pub use config::{RansacConfig, RansacResult, Refit};
use consensus::{is_better, Matches, Score};

use crate::error::{Error, Result};
use crate::ray_noise::check_rays;
use crate::rigid::{check_pairs, Svd3};

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
