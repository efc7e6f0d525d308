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

use nalgebra::{Isometry3, Matrix3, Matrix6, Point3, Vector3, Vector6};
use rayon::prelude::*;

use super::voxel::{Distributions, VoxelKey};

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
    pub gaussians: &'a Distributions,
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
    Scorer::new(context, source).evaluate(pose)
}

/// Repeated evaluations of one source against one map, as Newton's method and its line search make them.
/// Each point remembers the voxel it fell in last time and the distributions around it: between nearby
/// poses most points stay in their voxel and skip the 7 (or 27) hash lookups, which were most of an
/// evaluation's time. The results are those of [`evaluate`], bit for bit.
pub struct Scorer<'a> {
    context: &'a ScoreContext<'a>,
    source: &'a [Point3<f64>],
    /// Per point: the voxel it was last found in (`None`: not yet, or outside the key range) …
    keys: Vec<Option<VoxelKey>>,
    /// … how many of that voxel's neighbourhood hold a distribution …
    counts: Vec<u8>,
    /// … and their slots in the map, `neighbours.offsets().len()` per point, in offset order.
    slots: Vec<u32>,
}

impl<'a> Scorer<'a> {
    pub fn new(context: &'a ScoreContext<'a>, source: &'a [Point3<f64>]) -> Self {
        let stride = context.neighbours.offsets().len();
        Scorer {
            context,
            source,
            keys: vec![None; source.len()],
            counts: vec![0; source.len()],
            slots: vec![0; source.len() * stride],
        }
    }

    /// The cost and its derivatives with the source placed by `pose`.
    pub fn evaluate(&mut self, pose: &Isometry3<f64>) -> Evaluation {
        let context = self.context;
        let stride = context.neighbours.offsets().len();
        let partial: Vec<Evaluation> = self
            .source
            .par_chunks(CHUNK)
            .zip(self.keys.par_chunks_mut(CHUNK))
            .zip(self.counts.par_chunks_mut(CHUNK))
            .zip(self.slots.par_chunks_mut(CHUNK * stride))
            .map(|(((points, keys), counts), slots)| {
                let mut cache = NeighbourCache {
                    keys,
                    counts,
                    slots,
                    stride,
                };
                evaluate_chunk(context, points, pose, &mut cache)
            })
            .collect();
        let mut total = Evaluation::zero();
        for part in &partial {
            total.add(part);
        }
        total
    }
}

/// One chunk's share of a [`Scorer`]'s memory.
struct NeighbourCache<'c> {
    keys: &'c mut [Option<VoxelKey>],
    counts: &'c mut [u8],
    slots: &'c mut [u32],
    stride: usize,
}

impl NeighbourCache<'_> {
    /// The map slots of the distributions around voxel `key`, for point `index` of the chunk.
    fn neighbours(&mut self, index: usize, key: VoxelKey, context: &ScoreContext<'_>) -> &[u32] {
        let slots = &mut self.slots[index * self.stride..(index + 1) * self.stride];
        if self.keys[index] != Some(key) {
            let mut count = 0;
            for offset in context.neighbours.offsets() {
                if let Some(slot) = context.gaussians.slot(&key.offset(*offset)) {
                    slots[count] = slot;
                    count += 1;
                }
            }
            self.keys[index] = Some(key);
            self.counts[index] = count as u8;
        }
        &slots[..usize::from(self.counts[index])]
    }
}

fn evaluate_chunk(
    context: &ScoreContext<'_>,
    chunk: &[Point3<f64>],
    pose: &Isometry3<f64>,
    cache: &mut NeighbourCache<'_>,
) -> Evaluation {
    let ScoreConstants { d1, d2 } = context.constants;
    let inverse_voxel_size = 1.0 / context.voxel_size;
    let rotation = pose.rotation.to_rotation_matrix();
    let translation = pose.translation.vector;
    let mut sum = Evaluation::zero();
    // The Hessian is assembled once per chunk from three sums, Σw·JᵀΣ⁻¹J − d2·Σw·ggᵀ + Σw·(rotation
    // curvature), instead of building a 6×6 matrix for every point–distribution pair.
    let mut outer_gradients = Matrix6::zeros();
    let mut curvature = Matrix3::zeros();
    for (index, point) in chunk.iter().enumerate() {
        let y = rotation * point.coords;
        let placed = Point3::from(y + translation);
        let Some(key) = VoxelKey::containing(&placed, inverse_voxel_size) else {
            continue;
        };
        let slots = cache.neighbours(index, key, context);
        let found = !slots.is_empty();
        for &slot in slots {
            let gaussian = context.gaussians.by_slot(slot);
            let q = placed - gaussian.mean;
            let inverse_covariance = &gaussian.inverse_covariance;
            let a = inverse_covariance * q;
            let exponent = 0.5 * d2 * q.dot(&a);
            if exponent > NEGLIGIBLE_EXPONENT {
                continue;
            }
            let e = (-exponent).exp();
            sum.cost += d1 * e;
            sum.likelihood += e;
            // With J = ∂x/∂δ = [I | −[y]×]: g = JᵀΣ⁻¹q = (a, y × a), and ∂cost/∂δ = −d1·d2·e·g.
            let weight = -d1 * d2 * e;
            let rotation_gradient = y.cross(&a);
            let g = Vector6::new(
                a.x,
                a.y,
                a.z,
                rotation_gradient.x,
                rotation_gradient.y,
                rotation_gradient.z,
            );
            sum.gradient += g * weight;
            // JᵀΣ⁻¹J by blocks: Σ⁻¹ (translation), Σ⁻¹·(−[y]×) (coupling, whose row i is (y × sᵢ)ᵀ for the
            // rows sᵢ of the symmetric Σ⁻¹) and [y]×·Σ⁻¹·(−[y]×) (rotation, column j = y × coupling column j).
            let coupling = Matrix3::from_rows(&[
                y.cross(&inverse_covariance.column(0).into_owned())
                    .transpose(),
                y.cross(&inverse_covariance.column(1).into_owned())
                    .transpose(),
                y.cross(&inverse_covariance.column(2).into_owned())
                    .transpose(),
            ]);
            let rotation_block = Matrix3::from_columns(&[
                y.cross(&coupling.column(0).into_owned()),
                y.cross(&coupling.column(1).into_owned()),
                y.cross(&coupling.column(2).into_owned()),
            ]);
            let mut first_order = sum.hessian_psd.fixed_view_mut::<3, 3>(0, 0);
            first_order += inverse_covariance * weight;
            let mut first_order = sum.hessian_psd.fixed_view_mut::<3, 3>(0, 3);
            first_order += coupling * weight;
            let mut first_order = sum.hessian_psd.fixed_view_mut::<3, 3>(3, 3);
            first_order += rotation_block * weight;
            outer_gradients += g * g.transpose() * (weight * d2);
            // qᵀΣ⁻¹ ∂²x/∂ωᵢ∂ωⱼ = ½(aᵢyⱼ + aⱼyᵢ) − (a·y)δᵢⱼ
            curvature += ((a * y.transpose() + y * a.transpose()) * 0.5
                - Matrix3::identity() * a.dot(&y))
                * weight;
        }
        if found {
            sum.num_correspondences += 1;
        }
    }
    // The lower-left coupling block is the transpose of the upper-right one.
    let upper_right = sum.hessian_psd.fixed_view::<3, 3>(0, 3).transpose();
    sum.hessian_psd
        .fixed_view_mut::<3, 3>(3, 0)
        .copy_from(&upper_right);
    sum.hessian = sum.hessian_psd - outer_gradients;
    let mut rotation_block = sum.hessian.fixed_view_mut::<3, 3>(3, 3);
    rotation_block += curvature;
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

    fn small_map() -> (Distributions, Vec<Point3<f64>>) {
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
        let mut gaussians = Distributions::default();
        for (key, stats) in voxel_statistics(&points, 1.0) {
            if let Some(g) = stats.gaussian(&key.corner(1.0), 5, 0.01) {
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
    fn a_scorer_remembering_neighbours_gives_the_uncached_evaluation_bit_for_bit() {
        let (gaussians, source) = small_map();
        for neighbours in [
            NeighbourSearch::Containing,
            NeighbourSearch::Direct7,
            NeighbourSearch::Direct27,
        ] {
            let context = ScoreContext {
                gaussians: &gaussians,
                voxel_size: 1.0,
                neighbours,
                constants: ScoreConstants::new(0.55, 1.0),
            };
            let mut scorer = Scorer::new(&context, &source);
            // Small steps keep most points in their voxel (cache hits), the large ones move many (misses),
            // and the return to a pose seen before re-uses entries written at other poses.
            let poses = [
                (0.0, 0.0),
                (0.01, 0.001),
                (0.02, 0.002),
                (0.6, 0.05),
                (0.61, 0.05),
                (0.0, 0.0),
            ];
            let mut hits = 0;
            for (shift, turn) in poses {
                let pose = Isometry3::new(
                    Vector3::new(shift, -0.5 * shift, 0.2 * shift),
                    Vector3::new(0.3 * turn, -0.2 * turn, turn),
                );
                let cached = scorer.evaluate(&pose);
                assert_eq!(cached, evaluate(&context, &source, &pose), "{neighbours:?}");
                hits += cached.num_correspondences;
            }
            assert!(hits > 0);
        }
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
