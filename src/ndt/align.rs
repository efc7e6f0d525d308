#![forbid(unsafe_code)]
//! Scan-to-map registration: Newton's method on the NDT score (Magnusson 2009, Alg. 2) with a step-length
//! limit and a backtracking (Armijo) line search. Where the full Hessian is indefinite (far from the
//! optimum) the step uses its positive semi-definite first-order part instead, a Gauss-Newton-like step.
//! Against a saddle-free (|λ|) Newton step on real KITTI scans (8 starts 0.3 m / 2° off) it took about as
//! many iterations (11–16 vs 9–15) in about half the time: its steps are rarely cut back by the line search.
//!
//! Degeneracy (Zhang, Kaess & Singh, ICRA 2016, "On degeneracy of optimization-based state estimation
//! problems"): in a corridor (ground and walls parallel to the road) the score has next to no information
//! about the motion along it, and what little it has comes from the in-plane shape of the distributions,
//! i.e. from how the map scans sampled the surfaces, not from geometry. The first-order Hessian at the
//! initial pose is eigen-analysed once; a direction whose eigenvalue is below a threshold × the largest of
//! its kind (`degeneracy_threshold` for translations, `rotation_degeneracy_threshold` for rotations) is
//! degenerate, and every Newton step is solved in the span of the constrained directions only,
//! so the result keeps the initial estimate along the degenerate ones (Zhang's solution remapping).
//! Metres and radians are not comparable, so translation and rotation are analysed separately, each with
//! the other marginalised (Schur complement: the translation information when the rotation may adjust
//! freely, and vice versa). This needs no length scale; scaling rotations by the source's RMS range
//! instead was tried and rejected: on simulated streets that range (≈ 42 m) is set by far points without
//! map neighbours and made the well-constrained roll look the weakest direction.

use nalgebra::{
    Isometry3, Matrix3, Matrix4, Matrix6, Point3, Rotation3, SymmetricEigen, Translation3,
    UnitQuaternion, Vector3, Vector6,
};

use super::map::NdtMap;
use super::score::{
    apply_increment, Evaluation, NeighbourSearch, ScoreConstants, ScoreContext, Scorer,
};
use super::voxel::voxel_downsample;
use crate::{Error, Result};

/// Halvings tried by the line search before giving up on a direction.
const MAX_LINE_SEARCH_HALVINGS: usize = 12;
/// Armijo's sufficient-decrease constant.
const ARMIJO: f64 = 1e-4;
/// Default [`NdtAlignConfig::degeneracy_threshold`]: a translation with under 5 % of the information of
/// the best-constrained one. A synthetic corridor's axis has ≈ 3 % (in-plane information of planar
/// distributions is about the map's `min_eigenvalue_ratio` = 1 % of their normal information, times the
/// share of points on them), the weakest translation on simulated streets 12–37 % (docs/measurements.md).
pub const DEFAULT_DEGENERACY_THRESHOLD: f64 = 0.05;
/// Default [`NdtAlignConfig::rotation_degeneracy_threshold`]: the weakest rotation (roll) on simulated
/// streets has 2–10 % of the strongest's, on the synthetic corridor 8 %.
pub const DEFAULT_ROTATION_DEGENERACY_THRESHOLD: f64 = 0.01;

/// Settings of [`NdtMap::align`].
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
    /// The source is thinned by a voxel-grid filter of this size first, metres (0 keeps every point).
    pub source_voxel_size: f64,
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
    /// rotation information grows with the squared lever arm, so on a long narrow street roll has only
    /// 2–10 % of yaw's although the ground pins it well.
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
        if !(self.source_voxel_size.is_finite() && self.source_voxel_size >= 0.0) {
            return Err(Error::invalid(
                "source_voxel_size",
                format!("must be finite and >= 0, got {}", self.source_voxel_size),
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

/// The outcome of [`NdtMap::align`].
#[derive(Clone, Debug, PartialEq)]
pub struct NdtResult {
    /// `T_map_source`: maps source (sensor-frame) points into the map.
    pub transform: Isometry3<f64>,
    /// The last step was below both epsilons (false: iteration limit, or no decrease along the step).
    pub converged: bool,
    /// Newton steps taken.
    pub iterations: usize,
    /// Source points (after thinning) with a map distribution in their neighbourhood at `transform`.
    pub num_correspondences: usize,
    /// Mean over the thinned source points of `Σ exp(−d2/2·qᵀΣ⁻¹q)` over their neighbouring distributions:
    /// each distribution adds up to 1 (a point on its mean), 0 far from every distribution; with neighbour
    /// search the sum can exceed 1. Higher is better; comparable only between runs with the same settings.
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

/// `T` from a 4×4 matrix, refusing anything that is not a rigid motion (within float32 round-off).
pub fn isometry_from_matrix4(
    matrix: &Matrix4<f64>,
    argument: &'static str,
) -> Result<Isometry3<f64>> {
    if matrix.iter().any(|v| !v.is_finite()) {
        return Err(Error::invalid(argument, "has a non-finite entry"));
    }
    let last_row = matrix.fixed_view::<1, 4>(3, 0);
    if (last_row - nalgebra::RowVector4::new(0.0, 0.0, 0.0, 1.0)).amax() > 1e-6 {
        return Err(Error::invalid(
            argument,
            format!("last row must be [0, 0, 0, 1], got {last_row}"),
        ));
    }
    let rotation = matrix.fixed_view::<3, 3>(0, 0).into_owned();
    let orthogonality = (rotation.transpose() * rotation - nalgebra::Matrix3::identity()).amax();
    if orthogonality > 1e-4 || rotation.determinant() <= 0.0 {
        return Err(Error::invalid(
            argument,
            format!(
                "is not a rigid transform: |RᵀR − I| = {orthogonality:.3e}, det R = {:.6}",
                rotation.determinant()
            ),
        ));
    }
    let rotation = Rotation3::from_matrix_eps(&rotation, 1e-12, 100, Rotation3::identity());
    let translation = Translation3::new(matrix[(0, 3)], matrix[(1, 3)], matrix[(2, 3)]);
    Ok(Isometry3::from_parts(
        translation,
        UnitQuaternion::from_rotation_matrix(&rotation),
    ))
}

impl NdtMap {
    /// Registers `points` (sensor frame) to the map, starting from `initial` = `T_map_source`.
    ///
    /// Fails on an empty map, empty or non-finite points, a bad configuration, or fewer than
    /// `min_correspondences` thinned source points near a map distribution at the initial pose.
    /// Parallel over points (rayon's current pool); the result is bit-identical for any thread count.
    pub fn align(
        &self,
        points: &[Point3<f64>],
        initial: &Isometry3<f64>,
        config: &NdtAlignConfig,
    ) -> Result<NdtResult> {
        config.validate()?;
        if self.is_empty() {
            return Err(Error::invalid(
                "map",
                "is empty: insert a scan before aligning",
            ));
        }
        if points.is_empty() {
            return Err(Error::invalid("points", "is empty"));
        }
        if let Some(row) = points
            .iter()
            .position(|p| !p.coords.iter().all(|v| v.is_finite()))
        {
            return Err(Error::invalid("points", format!("row {row} is not finite")));
        }
        if !(initial
            .translation
            .vector
            .iter()
            .chain(initial.rotation.coords.iter())
            .all(|v| v.is_finite()))
        {
            return Err(Error::invalid(
                "initial_transform",
                "has a non-finite entry",
            ));
        }
        let source = voxel_downsample(points, config.source_voxel_size);
        let voxel_size = self.config().voxel_size;
        let context = ScoreContext {
            gaussians: self.gaussians(),
            voxel_size,
            neighbours: config.neighbours,
            constants: ScoreConstants::new(config.outlier_ratio, voxel_size),
        };
        let mut pose = *initial;
        let mut scorer = Scorer::new(&context, &source);
        let mut current = scorer.evaluate(&pose);
        if current.num_correspondences < config.min_correspondences {
            return Err(Error::TooFewPoints {
                needed: config.min_correspondences,
                got: current.num_correspondences,
            });
        }
        let degeneracy = Degeneracy::analyse(
            &current,
            config.degeneracy_threshold,
            config.rotation_degeneracy_threshold,
        );
        let rotation_epsilon = config.rotation_epsilon_deg.to_radians();
        let mut converged = false;
        let mut iterations = 0;
        while iterations < config.max_iterations {
            if current.gradient.iter().all(|g| *g == 0.0) {
                // Already at a stationary point (or every point is far from every distribution).
                converged = true;
                break;
            }
            let Some(direction) = newton_direction(&current, config, &degeneracy) else {
                break;
            };
            iterations += 1;
            if is_small(&direction, config.translation_epsilon, rotation_epsilon) {
                // Below the tolerances the cost change is lost in round-off: take the step unchecked.
                pose = apply_increment(&pose, &direction);
                current = scorer.evaluate(&pose);
                converged = true;
                break;
            }
            let Some((next_pose, next, step)) =
                line_search(&mut scorer, &pose, &current, &direction)
            else {
                break;
            };
            pose = next_pose;
            current = next;
            if is_small(&step, config.translation_epsilon, rotation_epsilon) {
                converged = true;
                break;
            }
        }
        Ok(NdtResult {
            transform: pose,
            converged,
            iterations,
            num_correspondences: current.num_correspondences,
            score: current.likelihood / source.len() as f64,
            degenerate_directions: degeneracy.degenerate_directions,
            translation_eigenvalues: degeneracy.translation_eigenvalues,
            rotation_eigenvalues: degeneracy.rotation_eigenvalues,
        })
    }

    /// [`align`](Self::align) with the initial `T_map_source` as a 4×4 matrix (checked to be rigid).
    pub fn align_matrix(
        &self,
        points: &[Point3<f64>],
        initial: &Matrix4<f64>,
        config: &NdtAlignConfig,
    ) -> Result<NdtResult> {
        let initial = isometry_from_matrix4(initial, "initial_transform")?;
        self.align(points, &initial, config)
    }
}

/// Whether an increment `(v, ω)` moves by less than both tolerances (metres, radians).
fn is_small(step: &Vector6<f64>, translation_epsilon: f64, rotation_epsilon: f64) -> bool {
    Vector3::new(step[0], step[1], step[2]).norm() < translation_epsilon
        && Vector3::new(step[3], step[4], step[5]).norm() < rotation_epsilon
}

/// Which directions of the increment the map constrains, decided once at the initial pose.
struct Degeneracy {
    /// Orthogonal projector onto the constrained directions; `None` when every direction is constrained
    /// (or the test is off), which leaves the solve exactly as without the analysis.
    projector: Option<Matrix6<f64>>,
    degenerate_directions: usize,
    translation_eigenvalues: [f64; 3],
    rotation_eigenvalues: [f64; 3],
}

impl Degeneracy {
    /// Eigen-analysis of the first-order Hessian `Σ w·JᵀΣ⁻¹J` at the initial pose, the NDT counterpart of
    /// the information matrix `JᵀJ` Zhang et al. analyse (positive semi-definite everywhere, so its
    /// spectrum means something even where the full Hessian is indefinite). Translation and rotation are
    /// analysed separately, each with the other marginalised (Schur complement): the information about the
    /// translation when the rotation is free to adjust, and vice versa. Within a block the units agree, so
    /// no length scale has to be chosen to compare metres with radians.
    fn analyse(at: &Evaluation, translation_threshold: f64, rotation_threshold: f64) -> Self {
        let information = symmetric_part(&at.hessian_psd);
        let translation = marginal_information(&information, 0, 3);
        let rotation = marginal_information(&information, 3, 0);
        let mut projector = Matrix6::identity();
        let mut degenerate_directions = 0;
        let mut split = |block: &Matrix3<f64>, offset: usize, threshold: f64| -> [f64; 3] {
            let eigen = SymmetricEigen::new(*block);
            let largest = eigen.eigenvalues.max();
            let mut relative = [0.0; 3];
            if !(largest.is_finite() && largest > 0.0) {
                // No information at all in this block: nothing to compare against (the solve stops itself).
                return relative;
            }
            for (i, value) in eigen.eigenvalues.iter().enumerate() {
                relative[i] = value / largest;
                if relative[i] < threshold {
                    let mut direction = Vector6::zeros();
                    direction
                        .fixed_rows_mut::<3>(offset)
                        .copy_from(&eigen.eigenvectors.column(i));
                    projector -= direction * direction.transpose();
                    degenerate_directions += 1;
                }
            }
            relative.sort_by(f64::total_cmp);
            relative
        };
        let translation_eigenvalues = split(&translation, 0, translation_threshold);
        let rotation_eigenvalues = split(&rotation, 3, rotation_threshold);
        Degeneracy {
            projector: (degenerate_directions > 0).then_some(projector),
            degenerate_directions,
            translation_eigenvalues,
            rotation_eigenvalues,
        }
    }
}

fn symmetric_part(matrix: &Matrix6<f64>) -> Matrix6<f64> {
    (matrix + matrix.transpose()) * 0.5
}

/// The 3×3 information of the block at `keep` with the block at `marginalise` free:
/// `A − B·C⁺·Bᵀ` (pseudo-inverse, so a block with no information in some direction is fine).
fn marginal_information(
    information: &Matrix6<f64>,
    keep: usize,
    marginalise: usize,
) -> Matrix3<f64> {
    let kept = information.fixed_view::<3, 3>(keep, keep).into_owned();
    let coupling = information
        .fixed_view::<3, 3>(keep, marginalise)
        .into_owned();
    let other = SymmetricEigen::new(
        information
            .fixed_view::<3, 3>(marginalise, marginalise)
            .into_owned(),
    );
    let cutoff = other.eigenvalues.amax() * 1e-12;
    let inverse_values = other
        .eigenvalues
        .map(|value| if value > cutoff { 1.0 / value } else { 0.0 });
    let pseudo_inverse = other.eigenvectors
        * Matrix3::from_diagonal(&inverse_values)
        * other.eigenvectors.transpose();
    let marginal = kept - coupling * pseudo_inverse * coupling.transpose();
    (marginal + marginal.transpose()) * 0.5
}

/// The Newton step `−H⁻¹g`; where the full Hessian is not positive definite (far from the optimum) its
/// positive semi-definite first-order part stands in (with a small floor on its eigenvalues). With
/// degenerate directions the step is the Newton step of the problem restricted to the constrained ones
/// (zero along the others). Shortened to the configured step limits. `None` when the curvature vanishes
/// or is not finite.
fn newton_direction(
    at: &Evaluation,
    config: &NdtAlignConfig,
    degeneracy: &Degeneracy,
) -> Option<Vector6<f64>> {
    let hessian = symmetric_part(&at.hessian);
    let hessian_psd = symmetric_part(&at.hessian_psd);
    let mut step = match &degeneracy.projector {
        None => positive_definite_solve(&hessian, &hessian_psd, &at.gradient)?,
        Some(projector) => {
            // P·H·P acts on the constrained subspace; a multiple of the identity on the degenerate one keeps
            // the matrix invertible and, as the gradient is projected too, gives no motion there. For the
            // matrix that defined the split this equals Zhang's remapping of the full solution.
            let rank = (6 - degeneracy.degenerate_directions) as f64;
            let restrict = |matrix: &Matrix6<f64>| {
                let restricted = projector * matrix * projector;
                let filler = restricted.trace() / rank;
                restricted + (Matrix6::identity() - projector) * filler
            };
            projector
                * positive_definite_solve(
                    &restrict(&hessian),
                    &restrict(&hessian_psd),
                    &(projector * at.gradient),
                )?
        }
    };
    let translation = Vector3::new(step[0], step[1], step[2]).norm();
    let rotation = Vector3::new(step[3], step[4], step[5]).norm();
    let shrink = (config.max_step_translation / translation)
        .min(config.max_step_rotation_deg.to_radians() / rotation);
    if shrink < 1.0 {
        step *= shrink;
    }
    step.iter().all(|v| v.is_finite()).then_some(step)
}

/// `−H⁻¹g` with `hessian` if it is positive definite, else with `fallback` (positive semi-definite) and a
/// floor of 1e-9 × its largest eigenvalue. `None` when the fallback has no positive curvature.
fn positive_definite_solve(
    hessian: &Matrix6<f64>,
    fallback: &Matrix6<f64>,
    gradient: &Vector6<f64>,
) -> Option<Vector6<f64>> {
    let full = SymmetricEigen::new(*hessian);
    let eigen = if full.eigenvalues.min() > 0.0 {
        full
    } else {
        SymmetricEigen::new(*fallback)
    };
    let largest = eigen.eigenvalues.amax();
    if !(largest.is_finite() && largest > 0.0) {
        return None;
    }
    let floor = largest * 1e-9;
    let inverse = eigen.eigenvalues.map(|value| 1.0 / value.max(floor));
    let projected = eigen.eigenvectors.transpose() * gradient;
    Some(-(eigen.eigenvectors * projected.component_mul(&inverse)))
}

/// Backtracks along `direction` until the cost drops enough (Armijo). Returns the new pose, its
/// evaluation and the step taken; `None` when no tried step decreases the cost.
fn line_search(
    scorer: &mut Scorer<'_>,
    pose: &Isometry3<f64>,
    current: &Evaluation,
    direction: &Vector6<f64>,
) -> Option<(Isometry3<f64>, Evaluation, Vector6<f64>)> {
    let slope = current.gradient.dot(direction);
    let mut length = 1.0;
    for _ in 0..=MAX_LINE_SEARCH_HALVINGS {
        let step = direction * length;
        let candidate = apply_increment(pose, &step);
        let evaluation = scorer.evaluate(&candidate);
        if evaluation.cost <= current.cost + ARMIJO * length * slope {
            return Some((candidate, evaluation, step));
        }
        length *= 0.5;
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ndt::NdtMapConfig;
    use nalgebra::Matrix4;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A flat patch `origin + u·a + v·b`, `u, v ∈ [0, 1]`.
    type Patch = ([f64; 3], [f64; 3], [f64; 3]);

    /// A street-like scene: ground, three walls (one tilted), boxes and poles.
    fn scene_patches() -> Vec<Patch> {
        let mut patches = vec![
            ([-20.0, -15.0, 0.0], [40.0, 0.0, 0.0], [0.0, 30.0, 0.0]),
            ([18.0, -15.0, 0.0], [0.0, 30.0, 0.0], [0.0, 0.0, 6.0]),
            ([-20.0, 12.0, 0.0], [38.0, 0.0, 0.0], [0.0, 0.5, 5.0]),
            ([-20.0, -14.0, 0.0], [30.0, 0.0, 0.0], [0.0, 0.0, 4.0]),
        ];
        for (corner, size) in [
            ([4.0, 3.0, 0.0], [4.0, 1.8, 1.5]),
            ([-6.0, -5.0, 0.0], [2.0, 2.0, 3.0]),
            ([9.0, -7.0, 0.0], [1.0, 5.0, 2.0]),
            ([-12.0, 6.0, 0.0], [3.0, 1.0, 1.0]),
        ] {
            let [x, y, z] = corner;
            let [dx, dy, dz] = size;
            patches.extend([
                ([x, y, z], [dx, 0.0, 0.0], [0.0, 0.0, dz]),
                ([x, y + dy, z], [dx, 0.0, 0.0], [0.0, 0.0, dz]),
                ([x, y, z], [0.0, dy, 0.0], [0.0, 0.0, dz]),
                ([x + dx, y, z], [0.0, dy, 0.0], [0.0, 0.0, dz]),
                ([x, y, z + dz], [dx, 0.0, 0.0], [0.0, dy, 0.0]),
            ]);
        }
        patches
    }

    /// `count` points drawn uniformly over the scene's area, with 1 cm noise, plus poles.
    fn sample_scene(count: usize, seed: u64) -> Vec<Point3<f64>> {
        let patches = scene_patches();
        let area = |(_, a, b): &Patch| Vector3::from(*a).cross(&Vector3::from(*b)).norm();
        let total: f64 = patches.iter().map(area).sum();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut points = Vec::with_capacity(count);
        let poles = [[2.0, -8.0], [-3.0, 9.0], [12.0, 4.0]];
        while points.len() < count {
            let point = if rng.random::<f64>() < 0.1 {
                let [x, y] = poles[rng.random_range(0..poles.len())];
                let angle: f64 = rng.random::<f64>() * std::f64::consts::TAU;
                Vector3::new(
                    x + 0.15 * angle.cos(),
                    y + 0.15 * angle.sin(),
                    rng.random::<f64>() * 5.0,
                )
            } else {
                let mut pick = rng.random::<f64>() * total;
                let patch = patches
                    .iter()
                    .find(|patch| {
                        pick -= area(patch);
                        pick <= 0.0
                    })
                    .unwrap_or(&patches[0]);
                let (origin, a, b) = patch;
                Vector3::from(*origin)
                    + Vector3::from(*a) * rng.random::<f64>()
                    + Vector3::from(*b) * rng.random::<f64>()
            };
            let noise = Vector3::new(
                rng.random::<f64>(),
                rng.random::<f64>(),
                rng.random::<f64>(),
            ) - Vector3::repeat(0.5);
            points.push(Point3::from(point + noise * 0.02));
        }
        points
    }

    fn map_of(points: &[Point3<f64>]) -> NdtMap {
        let mut map = NdtMap::new(NdtMapConfig::default()).unwrap();
        map.insert(points).unwrap();
        map
    }

    fn motion(translation: [f64; 3], axis_angle_deg: [f64; 3]) -> Isometry3<f64> {
        Isometry3::new(
            Vector3::from(translation),
            Vector3::from(axis_angle_deg).map(f64::to_radians),
        )
    }

    /// Translation (m) and rotation (deg) of `estimate⁻¹ · truth`.
    fn errors(estimate: &Isometry3<f64>, truth: &Isometry3<f64>) -> (f64, f64) {
        let delta = estimate.inverse() * truth;
        (
            delta.translation.vector.norm(),
            delta.rotation.angle().to_degrees(),
        )
    }

    /// Map from one sample of the scene; the source an independent sample seen from `T_map_source`.
    fn align_scene(truth: &Isometry3<f64>, initial: &Isometry3<f64>) -> NdtResult {
        let map = map_of(&sample_scene(40_000, 1));
        let source: Vec<Point3<f64>> = sample_scene(8_000, 2)
            .iter()
            .map(|p| truth.inverse_transform_point(p))
            .collect();
        map.align(&source, initial, &NdtAlignConfig::default())
            .unwrap()
    }

    fn assert_recovers(result: &NdtResult, truth: &Isometry3<f64>) {
        let (translation, rotation) = errors(&result.transform, truth);
        assert!(result.converged, "{result:?}");
        assert!(
            translation < 0.01 && rotation < 0.05,
            "error {translation:.4} m {rotation:.4}°: {result:?}"
        );
        // A well-constrained scene: every direction is solved for.
        assert_eq!(result.degenerate_directions, 0, "{result:?}");
    }

    #[test]
    fn recovers_a_known_motion_from_identity() {
        let truth = motion([0.5, -0.2, 0.05], [0.3, -0.2, 3.0]);
        assert_recovers(&align_scene(&truth, &Isometry3::identity()), &truth);
    }

    #[test]
    fn recovers_the_inverse_motion() {
        let truth = motion([0.5, -0.2, 0.05], [0.3, -0.2, 3.0]).inverse();
        assert_recovers(&align_scene(&truth, &Isometry3::identity()), &truth);
    }

    #[test]
    fn recovers_from_a_noisy_start() {
        let truth = motion([1.0, 0.3, -0.1], [0.0, 0.5, -8.0]);
        let initial = truth * motion([0.25, -0.15, 0.1], [0.8, -0.5, 1.5]);
        let result = align_scene(&truth, &initial);
        assert_recovers(&result, &truth);
        assert!(
            result.score > 0.1 && result.num_correspondences > 1000,
            "{result:?}"
        );
    }

    #[test]
    fn result_is_identical_for_one_and_four_threads() {
        let truth = motion([0.4, 0.1, 0.0], [0.0, 0.0, 2.0]);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| align_scene(&truth, &Isometry3::identity()))
        };
        assert_eq!(run(1), run(4));
    }

    #[test]
    fn degenerate_inputs_are_errors() {
        let map = map_of(&sample_scene(5_000, 3));
        let config = NdtAlignConfig::default();
        let identity = Isometry3::identity();
        let source = sample_scene(500, 4);
        let argument_of = |result: Result<NdtResult>| match result {
            Err(Error::InvalidArgument { argument, .. }) => argument,
            other => panic!("expected InvalidArgument, got {other:?}"),
        };
        assert_eq!(argument_of(map.align(&[], &identity, &config)), "points");
        let mut with_nan = source.clone();
        with_nan[7].y = f64::NAN;
        assert_eq!(
            argument_of(map.align(&with_nan, &identity, &config)),
            "points"
        );
        let empty = NdtMap::new(NdtMapConfig::default()).unwrap();
        assert_eq!(argument_of(empty.align(&source, &identity, &config)), "map");
        let mut scaled = Matrix4::identity();
        scaled[(0, 0)] = 2.0;
        assert_eq!(
            argument_of(map.align_matrix(&source, &scaled, &config)),
            "initial_transform"
        );
        let mut reflected = Matrix4::identity();
        reflected[(2, 2)] = -1.0;
        assert_eq!(
            argument_of(map.align_matrix(&source, &reflected, &config)),
            "initial_transform"
        );
        let mut projective = Matrix4::identity();
        projective[(3, 0)] = 0.1;
        assert_eq!(
            argument_of(map.align_matrix(&source, &projective, &config)),
            "initial_transform"
        );
        let mut not_finite = Matrix4::identity();
        not_finite[(1, 3)] = f64::INFINITY;
        assert_eq!(
            argument_of(map.align_matrix(&source, &not_finite, &config)),
            "initial_transform"
        );
        let bad = NdtAlignConfig {
            outlier_ratio: 1.0,
            ..config.clone()
        };
        assert_eq!(
            argument_of(map.align(&source, &identity, &bad)),
            "outlier_ratio"
        );
        let bad = NdtAlignConfig {
            max_iterations: 0,
            ..config.clone()
        };
        assert_eq!(
            argument_of(map.align(&source, &identity, &bad)),
            "max_iterations"
        );
        let bad = NdtAlignConfig {
            degeneracy_threshold: 1.0,
            ..config.clone()
        };
        assert_eq!(
            argument_of(map.align(&source, &identity, &bad)),
            "degeneracy_threshold"
        );
        let bad = NdtAlignConfig {
            rotation_degeneracy_threshold: f64::NAN,
            ..config.clone()
        };
        assert_eq!(
            argument_of(map.align(&source, &identity, &bad)),
            "rotation_degeneracy_threshold"
        );
        let far_away = motion([500.0, 0.0, 0.0], [0.0, 0.0, 0.0]);
        assert_eq!(
            map.align(&source, &far_away, &config),
            Err(Error::TooFewPoints {
                needed: config.min_correspondences,
                got: 0
            })
        );
    }

    #[test]
    fn planar_map_fixes_the_constrained_directions_and_stays_put_in_the_others() {
        // Only the ground: height, roll and pitch are observable, the in-plane motion is not. The solve
        // must recover the former and neither blow up nor wander off in the latter.
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut plane = |count: usize| -> Vec<Point3<f64>> {
            (0..count)
                .map(|_| {
                    let (x, y, z) = (
                        rng.random::<f64>(),
                        rng.random::<f64>(),
                        rng.random::<f64>(),
                    );
                    Point3::new(40.0 * x - 20.0, 30.0 * y - 15.0, 0.02 * z - 0.01)
                })
                .collect()
        };
        let map = map_of(&plane(40_000));
        let truth = motion([0.0, 0.0, 0.1], [1.0, -0.5, 0.0]);
        let source: Vec<Point3<f64>> = plane(8_000)
            .iter()
            .map(|p| truth.inverse_transform_point(p))
            .collect();
        let result = map
            .align(&source, &Isometry3::identity(), &NdtAlignConfig::default())
            .unwrap();
        let estimate = result.transform;
        assert!(result.converged, "{result:?}");
        assert!((estimate.translation.z - 0.1).abs() < 0.002, "{result:?}");
        let up = estimate.rotation * Vector3::z();
        let true_up = truth.rotation * Vector3::z();
        assert!(up.angle(&true_up).to_degrees() < 0.02, "{result:?}");
        assert!(estimate.translation.vector.xy().norm() < 0.02, "{result:?}");
        // That start is far enough off (10 cm, 1°) for the weights to tilt the analysis: x and y have 6–7 %
        // of z's information there. From a start as close as the odometry's (a few cm) they are found
        // degenerate and held exactly where they started, while z, roll and pitch are still solved.
        let start = truth * motion([0.05, -0.03, 0.01], [0.05, 0.05, 0.1]);
        let result = map
            .align(&source, &start, &NdtAlignConfig::default())
            .unwrap();
        assert!(result.converged, "{result:?}");
        assert!(result.degenerate_directions >= 2, "{result:?}");
        let held = result.transform.translation.vector.xy() - start.translation.vector.xy();
        assert!(held.norm() < 1e-3, "{result:?}"); // the split directions are tilted by the 1 cm z offset
        assert!(
            (result.transform.translation.z - 0.1).abs() < 0.002,
            "{result:?}"
        );
        let up = result.transform.rotation * Vector3::z();
        assert!(up.angle(&true_up).to_degrees() < 0.02, "{result:?}");
    }

    /// Ground and two walls parallel to x, nothing else: `count` points with 1 cm noise over `x ∈ [x0, x1]`.
    fn sample_corridor(count: usize, x_range: (f64, f64), seed: u64) -> Vec<Point3<f64>> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (x0, x1) = x_range;
        let (half_width, height) = (6.0, 4.0);
        let ground_share = 2.0 * half_width / (2.0 * half_width + 2.0 * height);
        (0..count)
            .map(|_| {
                let x = x0 + (x1 - x0) * rng.random::<f64>();
                let noise = Vector3::new(
                    rng.random::<f64>(),
                    rng.random::<f64>(),
                    rng.random::<f64>(),
                ) - Vector3::repeat(0.5);
                let surface = if rng.random::<f64>() < ground_share {
                    Vector3::new(x, half_width * (2.0 * rng.random::<f64>() - 1.0), 0.0)
                } else {
                    let side = if rng.random::<bool>() {
                        half_width
                    } else {
                        -half_width
                    };
                    Vector3::new(x, side, height * rng.random::<f64>())
                };
                Point3::from(surface + noise * 0.02)
            })
            .collect()
    }

    #[test]
    fn corridor_keeps_the_initial_estimate_along_its_axis_and_fixes_the_rest() {
        // The source is seen from `truth` and covers only the middle of the mapped corridor, so no end
        // wall tells where along x it is. Start 0.3 m off along the axis and a little off across it.
        let map = map_of(&sample_corridor(60_000, (-40.0, 40.0), 1));
        let truth = motion([2.0, 0.1, 0.05], [0.2, -0.3, 1.0]);
        let source: Vec<Point3<f64>> = sample_corridor(10_000, (-20.0, 20.0), 2)
            .iter()
            .map(|p| truth.inverse_transform_point(p))
            .collect();
        let along_axis = 0.3;
        let initial = Isometry3::from_parts(
            (truth.translation.vector + Vector3::new(along_axis, -0.08, 0.04)).into(),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.3f64, -0.2, 0.8).map(f64::to_radians))
                * truth.rotation,
        );
        let result = map
            .align(&source, &initial, &NdtAlignConfig::default())
            .unwrap();
        let offset = result.transform.translation.vector - truth.translation.vector;
        assert!(result.converged, "{result:?}");
        assert_eq!(result.degenerate_directions, 1, "{result:?}");
        assert!(
            (offset.x - along_axis).abs() < 0.005,
            "x pulled off the initial estimate: {result:?}"
        );
        assert!(
            offset.y.abs() < 0.005 && offset.z.abs() < 0.005,
            "{result:?}"
        );
        let rotation_error = (result.transform.rotation.inverse() * truth.rotation)
            .angle()
            .to_degrees();
        assert!(
            rotation_error < 0.02,
            "rotation error {rotation_error}°: {result:?}"
        );

        // Without the analysis the weak in-plane information moves x (the old behaviour).
        let unaware = NdtAlignConfig {
            degeneracy_threshold: 0.0,
            rotation_degeneracy_threshold: 0.0,
            ..NdtAlignConfig::default()
        };
        let pulled = map.align(&source, &initial, &unaware).unwrap();
        let pulled_offset = pulled.transform.translation.x - truth.translation.x;
        assert_eq!(pulled.degenerate_directions, 0);
        assert!((pulled_offset - along_axis).abs() > 0.05, "{pulled:?}");
    }

    #[test]
    fn rigid_matrix_round_trips() {
        let pose = motion([1.0, -2.0, 3.0], [10.0, 20.0, -30.0]);
        let back = isometry_from_matrix4(&pose.to_homogeneous(), "m").unwrap();
        assert!(errors(&back, &pose).0 < 1e-12 && errors(&back, &pose).1 < 1e-9);
    }
}
