#![forbid(unsafe_code)]
//! One pair's motion from the matcher's output (paper §III-D), the chain the odometry runs on every
//! pair: each cell's confidence weighted by the coherence of its flow ([`crate::coherence`]), the flow
//! decoded into 3D matches with NMS fused in (§III-D-a, [`crate::matches::select_matches`]), each
//! match's vote in RANSAC's consensus from the tilt of the surface under it ([`crate::surface`]) and
//! from how crowded its part of the scan is, and RANSAC around the SVD solve (§III-D-b,
//! [`crate::ransac`]).
//!
//! ```
//! use dmlo_rs::pair::{match_pair, PairConfig, PairImages};
//! use dmlo_rs::projection::CylinderConfig;
//!
//! # fn main() -> dmlo_rs::error::Result<()> {
//! let cylinder = CylinderConfig::kitti();
//! let cells = cylinder.height * cylinder.width;
//! // A wall 10 m ahead seen twice, nothing moved: zero flow, full confidence.
//! let range = vec![10.0f32; cells];
//! let (flow, confidence) = (vec![0.0f32; 2 * cells], vec![1.0f32; cells]);
//! let images = PairImages::new(&range, &range, &flow, &confidence);
//! let pair = match_pair(&images, &cylinder, &PairConfig::default(), true)?;
//! assert!(pair.transform.translation.vector.norm() < 1e-6);
//! # Ok(())
//! # }
//! ```

use std::collections::HashMap;

use nalgebra::{Isometry3, Point3};

use crate::coherence::{coherent_confidence, CoherenceConfig};
use crate::error::{Error, Result};
use crate::matches::{select_matches, DecodeConfig};
use crate::projection::CylinderConfig;
use crate::ransac::{ransac_rigid_voted, RansacConfig};
use crate::surface::horizontal_votes;

/// The settings of [`match_pair`]; `Default` is the odometry config's default (its `matching` and
/// `ransac` sections).
#[derive(Debug, Clone, PartialEq)]
pub struct PairConfig {
    /// A confidence `Q*` below this drops the cell before NMS.
    pub min_confidence: f32,
    /// NMS radius in cells (the paper's r = 1).
    pub nms_radius: usize,
    /// The top N matches kept after NMS.
    pub max_matches: usize,
    /// The confidence weighted by the coherence of each cell's flow with its neighbours'; `None`: the
    /// network's confidence as it is (the paper).
    pub coherence: Option<CoherenceConfig>,
    /// RANSAC and its refits.
    pub ransac: RansacConfig,
    /// With tilt votes: a match's vote for a horizontal motion is the horizontal part of the normal of
    /// the surface under its reference cell, at least this floor. The road's rings look alike from scan
    /// to scan, so at speed its matches agree on no motion at all; counted one each they outvote the
    /// few matches on posts and walls that see the car move. `None`: one vote each.
    pub tilt_vote_floor: Option<f64>,
    /// With tilt votes: each vote divided by the square root of how many matches share its cube of
    /// this many metres in the reference scan (a nearby car fills much of the image and holds hundreds
    /// of matches). `None`: no such division.
    pub vote_voxel: Option<f64>,
}

impl Default for PairConfig {
    /// The odometry config's defaults (`odometry::config`, where every setting is declared).
    fn default() -> Self {
        crate::odometry::config::OdometryConfig::default().pair_config()
    }
}

/// The images a pair is matched from, each row-major over the cylinder's `height × width` cells.
#[derive(Debug, Clone, Copy)]
pub struct PairImages<'a> {
    /// The reference scan's range image (metres, 0 where empty).
    pub ref_range: &'a [f32],
    /// The target scan's range image.
    pub tgt_range: &'a [f32],
    /// The flow of every reference cell into the target, `2 × H × W` (Δrow, then Δcol, pixels).
    pub flow: &'a [f32],
    /// The matcher's confidence of every reference cell.
    pub confidence: &'a [f32],
    /// The reference's point image, `H × W × 3` (each cell's kept point, NaN where empty), for the
    /// surfaces under the matches; `None`: the virtual points at the cells' centres.
    pub ref_points: Option<&'a [f32]>,
    /// Reference cells left out of the matches (a moving object's), `H × W`.
    pub leave_out: Option<&'a [bool]>,
}

impl<'a> PairImages<'a> {
    /// The four images every pair has; no point image, no cells left out.
    pub fn new(
        ref_range: &'a [f32],
        tgt_range: &'a [f32],
        flow: &'a [f32],
        confidence: &'a [f32],
    ) -> Self {
        PairImages {
            ref_range,
            tgt_range,
            flow,
            confidence,
            ref_points: None,
            leave_out: None,
        }
    }
}

/// A pair's motion and the matches it rests on.
#[derive(Debug, Clone, PartialEq)]
pub struct PairMotion {
    /// `T_tgt_ref` (`p_t = T p_r`); the identity when RANSAC found no motion (fewer than three matches,
    /// or none that determine one).
    pub transform: Isometry3<f64>,
    /// The matches' reference points `p'_r` (reference frame).
    pub source: Vec<Point3<f64>>,
    /// The matches' target points `p̂_t` (target frame).
    pub target: Vec<Point3<f64>>,
    /// The reference cell `[row, col]` of each match.
    pub cells: Vec<[usize; 2]>,
    /// RANSAC's inliers among the matches.
    pub inliers: Vec<bool>,
    /// How many inliers.
    pub num_inliers: usize,
    /// With tilt votes: the inliers' summed votes above the floor, how much of the consensus stands on
    /// upright surfaces (a road match adds ≈ 0); `None` without them.
    pub inlier_votes: Option<f64>,
}

/// The motion of a pair from the matcher's flow and confidence (module docs). `tilt_votes`: RANSAC
/// weighs the matches as `config` says (consecutive scans); false: one vote each (registration from
/// several starts, which compares them by their inlier counts). Errors name a wrong image size or
/// setting; a pair without a motion (too few matches, all collinear) is not an error but the identity
/// with no inliers.
pub fn match_pair(
    images: &PairImages<'_>,
    cylinder: &CylinderConfig,
    config: &PairConfig,
    tilt_votes: bool,
) -> Result<PairMotion> {
    check_config(config)?;
    let weighted;
    let confidence = match &config.coherence {
        Some(coherence) => {
            weighted = coherent_confidence(
                images.flow,
                images.confidence,
                images.ref_range,
                cylinder,
                coherence,
            )?;
            &weighted[..]
        }
        None => images.confidence,
    };
    let decode = DecodeConfig {
        min_confidence: config.min_confidence,
        ..Default::default()
    };
    let matches = select_matches(
        images.ref_range,
        images.tgt_range,
        images.flow,
        confidence,
        images.leave_out,
        cylinder,
        &decode,
        config.nms_radius,
        config.max_matches,
    )?;
    let mut motion = PairMotion {
        transform: Isometry3::identity(),
        inliers: vec![false; matches.len()],
        num_inliers: 0,
        inlier_votes: None,
        source: matches.source,
        target: matches.target,
        cells: matches.cells,
    };
    if motion.source.len() < 3 {
        return Ok(motion);
    }
    let tilt = match config.tilt_vote_floor {
        Some(floor) if tilt_votes => {
            let virtual_points;
            let points = match images.ref_points {
                Some(points) => points,
                None => {
                    virtual_points = cell_centre_points(images.ref_range, cylinder)?;
                    &virtual_points[..]
                }
            };
            Some(horizontal_votes(points, cylinder, &motion.cells, floor)?)
        }
        _ => None,
    };
    let votes = match config.vote_voxel {
        Some(voxel) if tilt_votes => {
            let crowding = voxel_crowding(&motion.source, voxel);
            Some(match &tilt {
                Some(tilt) => tilt
                    .iter()
                    .zip(&crowding)
                    .map(|(v, &n)| v / (n as f64).sqrt())
                    .collect(),
                None => crowding.iter().map(|&n| 1.0 / (n as f64).sqrt()).collect(),
            })
        }
        _ => tilt.clone(),
    };
    match ransac_rigid_voted(
        &motion.source,
        &motion.target,
        votes.as_deref(),
        &config.ransac,
    ) {
        Ok(ransac) => {
            if let (Some(tilt), Some(floor)) = (&tilt, config.tilt_vote_floor) {
                let above: f64 = tilt
                    .iter()
                    .zip(&ransac.inliers)
                    .filter(|(_, &inlier)| inlier)
                    .map(|(v, _)| v - floor)
                    .sum();
                motion.inlier_votes = Some(above);
            }
            motion.transform = ransac.transform;
            motion.inliers = ransac.inliers;
            motion.num_inliers = ransac.num_inliers;
        }
        // Matches that determine no motion: no motion from this pair, for the caller's fallbacks.
        Err(Error::TooFewPoints { .. } | Error::Degenerate(_)) => {}
        Err(error) => return Err(error),
    }
    Ok(motion)
}

fn check_config(config: &PairConfig) -> Result<()> {
    if config.max_matches < 3 {
        return Err(Error::invalid(
            "max_matches",
            format!(
                "must be at least 3 (a rigid motion's minimal sample), got {}",
                config.max_matches
            ),
        ));
    }
    if let Some(floor) = config.tilt_vote_floor {
        if !(floor > 0.0 && floor <= 1.0) {
            return Err(Error::invalid(
                "tilt_vote_floor",
                format!("must lie in (0, 1], got {floor}"),
            ));
        }
    }
    if let Some(voxel) = config.vote_voxel {
        if !(voxel.is_finite() && voxel > 0.0) {
            return Err(Error::invalid(
                "vote_voxel",
                format!("must be a positive length in metres, got {voxel}"),
            ));
        }
    }
    Ok(())
}

/// The point image of a range image alone: Φ⁻¹ at each cell's centre (Eq. 4), NaN where empty.
fn cell_centre_points(ranges: &[f32], cylinder: &CylinderConfig) -> Result<Vec<f32>> {
    let cells = cylinder.height * cylinder.width;
    if ranges.len() != cells {
        return Err(Error::invalid(
            "ref_range",
            format!(
                "has {} values, expected {} x {}",
                ranges.len(),
                cylinder.height,
                cylinder.width
            ),
        ));
    }
    let mut points = vec![f32::NAN; 3 * cells];
    for (cell, (&range, point)) in ranges.iter().zip(points.chunks_exact_mut(3)).enumerate() {
        if range > 0.0 {
            let (row, col) = (cell / cylinder.width, cell % cylinder.width);
            let p = cylinder.unproject(row as f64, col as f64, range as f64);
            point.copy_from_slice(&[p.x as f32, p.y as f32, p.z as f32]);
        }
    }
    Ok(points)
}

/// For each point, how many of `points` share its cube of `voxel` metres.
fn voxel_crowding(points: &[Point3<f64>], voxel: f64) -> Vec<usize> {
    let key = |p: &Point3<f64>| {
        [
            (p.x / voxel).floor() as i64,
            (p.y / voxel).floor() as i64,
            (p.z / voxel).floor() as i64,
        ]
    };
    let mut counts: HashMap<[i64; 3], usize> = HashMap::with_capacity(points.len());
    for point in points {
        *counts.entry(key(point)).or_insert(0) += 1;
    }
    points.iter().map(|point| counts[&key(point)]).collect()
}

#[cfg(test)]
mod tests;
