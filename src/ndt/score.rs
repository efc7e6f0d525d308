#![forbid(unsafe_code)]
//! The point-to-distribution NDT score with its analytic gradient and Hessian (Magnusson 2009, §6.2).
//!
//! Each transformed source point `x` near a map distribution `N(μ, Σ)` costs `d1·exp(−d2/2·qᵀΣ⁻¹q)` with
//! `q = x − μ`: the Gaussian approximation of the negative log-likelihood of a Gaussian-plus-uniform
//! mixture (outlier ratio, voxel size → `d1 < 0`, `d2 > 0`, Eq. 6.8). The cost is summed over the points
//! and their neighbouring voxels and minimised.
//!
//! Pose increments are 6-vectors `δ = (v, ω)` in the chart `R ← exp([ω]×)·R₀`, `t ← t₀ + v`: the source
//! rotates about its own (current) origin, which keeps the problem well conditioned however far the map
//! lies from the world origin. With `y = R₀·p`, `x(δ) = exp([ω]×)·y + t₀ + v`, so at `δ = 0`:
//! `∂x/∂v = I`, `∂x/∂ω = −[y]×` and `∂²x/∂ωᵢ∂ωⱼ = ½(eᵢyⱼ + eⱼyᵢ) − y·δᵢⱼ` (the Hessian is exact for this
//! chart; Magnusson's Euler-angle derivatives are replaced by the second-order term of the exponential).

use nalgebra::{Isometry3, Matrix3, Matrix3x6, Matrix6, Point3, Vector3, Vector6};
use rayon::prelude::*;

use super::voxel::{Gaussian, VoxelKey, VoxelMap};

/// Points per chunk of the parallel reduction. Fixed, so the summation order (and with it every bit of
/// the result) does not depend on the number of threads.
const CHUNK: usize = 256;

/// A point further than this many "standard deviations" (`d2·qᵀΣ⁻¹q / 2`) contributes `< e⁻⁵⁰`: skip it.
const NEGLIGIBLE_EXPONENT: f64 = 50.0;

/// The constants `d1`, `d2` of the Gaussian approximation of the mixture log-likelihood (Eq. 6.8).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScoreConstants {
    pub d1: f64,
    pub d2: f64,
}

impl ScoreConstants {
    /// From the expected outlier ratio and the voxel size (the uniform part's support is one voxel).
    pub fn new(outlier_ratio: f64, voxel_size: f64) -> Self {
        let c1 = 10.0 * (1.0 - outlier_ratio);
        let c2 = outlier_ratio / voxel_size.powi(3);
        let d3 = -c2.ln();
        let d1 = -(c1 + c2).ln() - d3;
        let d2 = -2.0 * ((-(c1 * (-0.5f64).exp() + c2).ln() - d3) / d1).ln();
        ScoreConstants { d1, d2 }
    }
}

/// Which map voxels a point is scored against.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum NeighbourSearch {
    /// Only the voxel containing the point (fastest, narrowest basin).
    Containing,
    /// The containing voxel and its 6 face neighbours (PCL's `DIRECT7`).
    #[default]
    Direct7,
    /// The full 3×3×3 block around the containing voxel.
    Direct27,
}

impl NeighbourSearch {
    /// Voxel offsets searched, the containing voxel first.
    pub fn offsets(self) -> &'static [[i32; 3]] {
        const DIRECT7: [[i32; 3]; 7] = [
            [0, 0, 0],
            [-1, 0, 0],
            [1, 0, 0],
            [0, -1, 0],
            [0, 1, 0],
            [0, 0, -1],
            [0, 0, 1],
        ];
        const DIRECT27: [[i32; 3]; 27] = {
            let mut offsets = [[0i32; 3]; 27];
            offsets[0] = [0, 0, 0];
            let mut next = 1;
            let mut i: i32 = 0;
            while i < 27 {
                let offset = [i / 9 - 1, (i / 3) % 3 - 1, i % 3 - 1];
                if !(offset[0] == 0 && offset[1] == 0 && offset[2] == 0) {
                    offsets[next] = offset;
                    next += 1;
                }
                i += 1;
            }
            offsets
        };
        match self {
            NeighbourSearch::Containing => &DIRECT7[..1],
            NeighbourSearch::Direct7 => &DIRECT7,
            NeighbourSearch::Direct27 => &DIRECT27,
        }
    }
}

/// The cost and its derivatives at one pose, summed over the source points.
#[derive(Clone, Debug, PartialEq)]
pub struct Evaluation {
    /// `Σ d1·exp(…)` over all point–distribution pairs (negative; lower is better).
    pub cost: f64,
    /// `Σ exp(…)`: the unscaled likelihood, reported per point as the result's score.
    pub likelihood: f64,
    pub gradient: Vector6<f64>,
    pub hessian: Matrix6<f64>,
    /// `Σ −d1·d2·e·JᵀΣ⁻¹J`: the Hessian without its curvature terms, positive semi-definite everywhere
    /// (the Gauss-Newton-like fallback where the full Hessian is indefinite, far from the optimum).
    pub hessian_psd: Matrix6<f64>,
    /// Source points with at least one distribution in their neighbourhood.
    pub num_correspondences: usize,
}

impl Evaluation {
    fn zero() -> Self {
        Evaluation {
            cost: 0.0,
            likelihood: 0.0,
            gradient: Vector6::zeros(),
            hessian: Matrix6::zeros(),
            hessian_psd: Matrix6::zeros(),
            num_correspondences: 0,
        }
    }

    fn add(&mut self, other: &Evaluation) {
        self.cost += other.cost;
        self.likelihood += other.likelihood;
        self.gradient += other.gradient;
        self.hessian += other.hessian;
        self.hessian_psd += other.hessian_psd;
        self.num_correspondences += other.num_correspondences;
    }
}

/// What [`evaluate`] reads: the map's distributions and how to look them up.
pub struct ScoreContext<'a> {
    pub gaussians: &'a VoxelMap<Gaussian>,
    pub voxel_size: f64,
    pub neighbours: NeighbourSearch,
    pub constants: ScoreConstants,
}

/// The NDT cost, gradient and Hessian of `source` (sensor frame) placed by `pose`, over the increment
/// `δ = (v, ω)` described in the module docs. Parallel over chunks of points; deterministic.
pub fn evaluate(
    context: &ScoreContext<'_>,
    source: &[Point3<f64>],
    pose: &Isometry3<f64>,
) -> Evaluation {
    let partial: Vec<Evaluation> = source
        .par_chunks(CHUNK)
        .map(|chunk| evaluate_chunk(context, chunk, pose))
        .collect();
    let mut total = Evaluation::zero();
    for part in &partial {
        total.add(part);
    }
    total
}

fn evaluate_chunk(
    context: &ScoreContext<'_>,
    chunk: &[Point3<f64>],
    pose: &Isometry3<f64>,
) -> Evaluation {
    let ScoreConstants { d1, d2 } = context.constants;
    let inverse_voxel_size = 1.0 / context.voxel_size;
    let rotation = pose.rotation.to_rotation_matrix();
    let translation = pose.translation.vector;
    let mut sum = Evaluation::zero();
    for point in chunk {
        let rotated = rotation * point.coords;
        let placed = Point3::from(rotated + translation);
        let Some(key) = VoxelKey::containing(&placed, inverse_voxel_size) else {
            continue;
        };
        // ∂x/∂δ = [I | −[y]×]
        let mut jacobian = Matrix3x6::zeros();
        jacobian
            .fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&Matrix3::identity());
        jacobian
            .fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&-rotated.cross_matrix());
        let mut found = false;
        for offset in context.neighbours.offsets() {
            let Some(gaussian) = context.gaussians.get(&key.offset(*offset)) else {
                continue;
            };
            found = true;
            let q = placed - gaussian.mean;
            let a = gaussian.inverse_covariance * q;
            let exponent = 0.5 * d2 * q.dot(&a);
            if exponent > NEGLIGIBLE_EXPONENT {
                continue;
            }
            let e = (-exponent).exp();
            sum.cost += d1 * e;
            sum.likelihood += e;
            // ∂cost/∂δ = −d1·d2·e·g with g = Jᵀ Σ⁻¹ q
            let weight = -d1 * d2 * e;
            let g = jacobian.transpose() * a;
            sum.gradient += g * weight;
            let first_order = jacobian.transpose() * (gaussian.inverse_covariance * jacobian);
            sum.hessian_psd += first_order * weight;
            let mut hessian = first_order - g * g.transpose() * d2;
            // qᵀΣ⁻¹ ∂²x/∂ωᵢ∂ωⱼ = ½(aᵢyⱼ + aⱼyᵢ) − (a·y)δᵢⱼ
            let second_order = (a * rotated.transpose() + rotated * a.transpose()) * 0.5
                - Matrix3::identity() * a.dot(&rotated);
            let mut block = hessian.fixed_view_mut::<3, 3>(3, 3);
            block += second_order;
            sum.hessian += hessian * weight;
        }
        if found {
            sum.num_correspondences += 1;
        }
    }
    sum
}

/// Applies the increment `δ = (v, ω)` of the module's chart to `pose`.
pub fn apply_increment(pose: &Isometry3<f64>, increment: &Vector6<f64>) -> Isometry3<f64> {
    let v = Vector3::new(increment[0], increment[1], increment[2]);
    let omega = Vector3::new(increment[3], increment[4], increment[5]);
    let rotation = nalgebra::UnitQuaternion::from_scaled_axis(omega) * pose.rotation;
    Isometry3::from_parts((pose.translation.vector + v).into(), rotation)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ndt::voxel::voxel_statistics;

    fn small_map() -> (VoxelMap<Gaussian>, Vec<Point3<f64>>) {
        // Three tilted planes crossing a few voxels, sampled on a jittered grid.
        let mut points = Vec::new();
        for i in 0..40 {
            for j in 0..40 {
                let (u, v) = (i as f64 * 0.1, j as f64 * 0.1);
                let jitter = ((i * 7 + j * 13) % 11) as f64 * 0.003;
                points.push(Point3::new(u, v, 0.2 * u + jitter));
                points.push(Point3::new(u, 0.1 * v + jitter, v));
                points.push(Point3::new(0.3 * v + jitter, u, v));
            }
        }
        let (order, stats) = voxel_statistics(&points, 1.0);
        let mut gaussians = VoxelMap::default();
        for key in order {
            if let Some(g) = stats[&key].gaussian(&key.corner(1.0), 5, 0.01) {
                gaussians.insert(key, g);
            }
        }
        let source = points.iter().step_by(7).copied().collect();
        (gaussians, source)
    }

    #[test]
    fn constants_match_magnusson_for_unit_voxels() {
        let c = ScoreConstants::new(0.55, 1.0);
        assert!((c.d1 + 2.2166).abs() < 1e-3, "{c:?}");
        assert!((c.d2 - 0.4326).abs() < 1e-3, "{c:?}");
    }

    #[test]
    fn direct27_offsets_are_distinct() {
        let mut offsets = NeighbourSearch::Direct27.offsets().to_vec();
        assert_eq!(offsets[0], [0, 0, 0]);
        offsets.sort();
        offsets.dedup();
        assert_eq!(offsets.len(), 27);
    }

    #[test]
    fn gradient_and_hessian_match_finite_differences() {
        let (gaussians, source) = small_map();
        let context = ScoreContext {
            gaussians: &gaussians,
            voxel_size: 1.0,
            neighbours: NeighbourSearch::Direct7,
            constants: ScoreConstants::new(0.55, 1.0),
        };
        let pose = Isometry3::new(
            Vector3::new(0.05, -0.03, 0.04),
            Vector3::new(0.02, -0.01, 0.03),
        );
        // Points close to a voxel face would switch neighbours within the finite-difference steps (the
        // cost jumps there); keep those at least 1 cm inside their voxel.
        let source: Vec<Point3<f64>> = source
            .into_iter()
            .filter(|p| {
                (pose * p)
                    .coords
                    .iter()
                    .all(|v| (v - v.round()).abs() > 0.01)
            })
            .collect();
        let at = evaluate(&context, &source, &pose);
        let cost =
            |delta: Vector6<f64>| evaluate(&context, &source, &apply_increment(&pose, &delta)).cost;
        let unit = |i: usize| {
            let mut e = Vector6::zeros();
            e[i] = 1.0;
            e
        };
        let h = 1e-4;
        for i in 0..6 {
            let numeric_gradient = (cost(unit(i) * h) - cost(-unit(i) * h)) / (2.0 * h);
            let tolerance = 1e-5 * (1.0 + at.gradient[i].abs());
            assert!(
                (numeric_gradient - at.gradient[i]).abs() < tolerance,
                "gradient {i}"
            );
            for j in 0..6 {
                let (ei, ej) = (unit(i) * h, unit(j) * h);
                let numeric = (cost(ei + ej) - cost(ei - ej) - cost(ej - ei) + cost(-ei - ej))
                    / (4.0 * h * h);
                let analytic = at.hessian[(i, j)];
                assert!(
                    (numeric - analytic).abs() < 1e-3 * (1.0 + analytic.abs()),
                    "hessian ({i}, {j}): {numeric} vs {analytic}"
                );
            }
        }
    }
}
