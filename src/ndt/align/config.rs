#![forbid(unsafe_code)]
//! Settings of the alignment ([`NdtAlignConfig`]) and its outcome ([`NdtResult`]).

use nalgebra::Isometry3;

use super::super::score::NeighbourSearch;
use crate::{Error, Result};

/// Default [`NdtAlignConfig::degeneracy_threshold`]: a translation with under 5 % of the information of
/// the best-constrained one. Along a corridor the in-plane information of planar distributions is about
/// the map's `min_eigenvalue_ratio` of their normal information, times the share of points on them: below
/// this; a street's weakest translation lies well above it (docs/measurements.md).
pub const DEFAULT_DEGENERACY_THRESHOLD: f64 = 0.05;
/// Default [`NdtAlignConfig::rotation_degeneracy_threshold`]: below the weakest rotation (roll) of a street
/// or a corridor (docs/measurements.md).
pub const DEFAULT_ROTATION_DEGENERACY_THRESHOLD: f64 = 0.01;

/// Settings of [`NdtMap::align`](crate::ndt::NdtMap::align).
#[derive(Clone, Debug, PartialEq)]
pub struct NdtAlignConfig {
    /// Newton steps at most.
    pub max_iterations: usize,
    /// Converged when a step moves the source by less than this, metres …
    pub translation_epsilon: f64,
    /// … and rotates it by less than this, degrees.
    pub rotation_epsilon_deg: f64,
    /// Expected fraction of source points with no counterpart in the map (sets `d1`, `d2`).
    pub outlier_ratio: f64,
    /// The source is thinned by a voxel-grid filter of this size first, metres (0 keeps every point) …
    pub source_voxel_size: f64,
    /// … but its points farther than this from the sensor (the source frame's origin), metres, by one of
    /// `source_far_voxel_size` (infinite: every point by `source_voxel_size`).
    pub source_far_range: f64,
    /// The far points' voxel, metres (0 keeps every far point).
    pub source_far_voxel_size: f64,
    /// Which map voxels each point is scored against.
    pub neighbours: NeighbourSearch,
    /// A Newton step is shortened so that it translates by at most this, metres …
    pub max_step_translation: f64,
    /// … and rotates by at most this, degrees.
    pub max_step_rotation_deg: f64,
    /// Fewer source points with a map distribution nearby than this is an error.
    pub min_correspondences: usize,
    /// A translation direction whose information (eigenvalue of the first-order Hessian at the initial
    /// pose, rotation marginalised) is below this fraction of the best-constrained translation's is
    /// degenerate: the solve keeps the initial estimate along it (see the module docs). In [0, 1); 0 off.
    pub degeneracy_threshold: f64,
    /// The same for rotation directions (translation marginalised). Lower than the translation's: the
    /// rotation information grows with the squared lever arm, so on a long narrow street roll has a small
    /// fraction of yaw's although the ground pins it well.
    pub rotation_degeneracy_threshold: f64,
}

impl Default for NdtAlignConfig {
    fn default() -> Self {
        NdtAlignConfig {
            max_iterations: 30,
            translation_epsilon: 1e-4,
            rotation_epsilon_deg: 1e-3,
            outlier_ratio: 0.55,
            source_voxel_size: 0.5,
            source_far_range: f64::INFINITY,
            source_far_voxel_size: 0.5,
            neighbours: NeighbourSearch::Direct7,
            max_step_translation: 0.5,
            max_step_rotation_deg: 5.0,
            min_correspondences: 20,
            degeneracy_threshold: DEFAULT_DEGENERACY_THRESHOLD,
            rotation_degeneracy_threshold: DEFAULT_ROTATION_DEGENERACY_THRESHOLD,
        }
    }
}

impl NdtAlignConfig {
    /// Checks every field, naming the first that is out of range.
    pub fn validate(&self) -> Result<()> {
        let positive = |value: f64, name: &'static str| {
            if value.is_finite() && value > 0.0 {
                Ok(())
            } else {
                Err(Error::invalid(
                    name,
                    format!("must be finite and > 0, got {value}"),
                ))
            }
        };
        if self.max_iterations == 0 {
            return Err(Error::invalid("max_iterations", "must be at least 1"));
        }
        positive(self.translation_epsilon, "translation_epsilon")?;
        positive(self.rotation_epsilon_deg, "rotation_epsilon_deg")?;
        if !(self.outlier_ratio > 0.0 && self.outlier_ratio < 1.0) {
            return Err(Error::invalid(
                "outlier_ratio",
                format!("must lie in (0, 1), got {}", self.outlier_ratio),
            ));
        }
        for (value, name) in [
            (self.source_voxel_size, "source_voxel_size"),
            (self.source_far_voxel_size, "source_far_voxel_size"),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return Err(Error::invalid(
                    name,
                    format!("must be finite and >= 0, got {value}"),
                ));
            }
        }
        // NaN fails as well as a negative range: infinity (every point near) is allowed.
        if self.source_far_range.is_nan() || self.source_far_range < 0.0 {
            return Err(Error::invalid(
                "source_far_range",
                format!("must be >= 0, got {}", self.source_far_range),
            ));
        }
        positive(self.max_step_translation, "max_step_translation")?;
        positive(self.max_step_rotation_deg, "max_step_rotation_deg")?;
        if self.min_correspondences == 0 {
            return Err(Error::invalid("min_correspondences", "must be at least 1"));
        }
        for (value, name) in [
            (self.degeneracy_threshold, "degeneracy_threshold"),
            (
                self.rotation_degeneracy_threshold,
                "rotation_degeneracy_threshold",
            ),
        ] {
            if !(0.0..1.0).contains(&value) {
                return Err(Error::invalid(
                    name,
                    format!("must lie in [0, 1), got {value}"),
                ));
            }
        }
        Ok(())
    }
}

/// The outcome of [`NdtMap::align`](crate::ndt::NdtMap::align).
#[derive(Clone, Debug, PartialEq)]
pub struct NdtResult {
    /// `T_map_source`: maps source (sensor-frame) points into the map.
    pub transform: Isometry3<f64>,
    /// The last step was below both epsilons (false: iteration limit, or no decrease along the step).
    pub converged: bool,
    /// Newton steps taken.
    pub iterations: usize,
    /// Source points (after thinning) with a map distribution in their neighbourhood at `transform`, or
    /// where the last step started when that step was below both epsilons (it is taken unchecked).
    pub num_correspondences: usize,
    /// Mean over the thinned source points of `Σ exp(−d2/2·qᵀΣ⁻¹q)` over their neighbouring distributions:
    /// each distribution adds up to 1 (a point on its mean), 0 far from every distribution; with neighbour
    /// search the sum can exceed 1. Higher is better; comparable only between runs with the same settings.
    /// Taken where `num_correspondences` is.
    pub score: f64,
    /// Directions of the pose held at the initial estimate because the map does not constrain them.
    pub degenerate_directions: usize,
    /// Eigenvalues of the information about the translation (rotation marginalised; first-order Hessian
    /// at the initial pose), ascending, divided by the largest (all 0 without any information); those
    /// below `degeneracy_threshold` are degenerate directions.
    pub translation_eigenvalues: [f64; 3],
    /// The same for the rotation (translation marginalised), against `rotation_degeneracy_threshold`.
    pub rotation_eigenvalues: [f64; 3],
}
