#![forbid(unsafe_code)]
//! One Newton step on the NDT score: its direction (restricted to the constrained directions and
//! shortened to the step limits), the backtracking line search along it, and the convergence test.

use nalgebra::{Isometry3, Matrix6, SymmetricEigen, Vector3, Vector6};

use super::super::score::{apply_increment, Evaluation, Scorer};
use super::degeneracy::{symmetric_part, Degeneracy};
use super::NdtAlignConfig;

/// Halvings tried by the line search before giving up on a direction.
const MAX_LINE_SEARCH_HALVINGS: usize = 12;
/// Armijo's sufficient-decrease constant.
const ARMIJO: f64 = 1e-4;

/// Whether an increment `(v, ω)` moves by less than both tolerances (metres, radians).
pub(super) fn is_small(
    step: &Vector6<f64>,
    translation_epsilon: f64,
    rotation_epsilon: f64,
) -> bool {
    Vector3::new(step[0], step[1], step[2]).norm() < translation_epsilon
        && Vector3::new(step[3], step[4], step[5]).norm() < rotation_epsilon
}

/// The Newton step `−H⁻¹g`; where the full Hessian is not positive definite (far from the optimum) its
/// positive semi-definite first-order part stands in (with a small floor on its eigenvalues). With
/// degenerate directions the step is the Newton step of the problem restricted to the constrained ones
/// (zero along the others). Shortened to the configured step limits. `None` when the curvature vanishes
/// or is not finite.
pub(super) fn newton_direction(
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

/// How a line search along a Newton direction ended.
// Made once a search and matched at once: boxing the evaluation would buy nothing.
#[allow(clippy::large_enum_variant)]
pub(super) enum LineSearch {
    /// The cost dropped enough at this pose (its evaluation, the step taken).
    Decreased(Isometry3<f64>, Evaluation, Vector6<f64>),
    /// Backtracking shortened the step below the tolerances without the cost dropping enough: the pose
    /// already sits at the optimum as closely as they ask.
    Stalled,
    /// No tried step decreased the cost.
    Failed,
}

/// Backtracks along `direction` (a descent direction) until the cost drops enough (Armijo), evaluating no
/// step shorter than the tolerances (metres, radians): near the optimum the cost changes less than it
/// jumps where thinned points cross voxel borders, and halving on would evaluate the scan again and again
/// for moves the convergence test already counts as none.
pub(super) fn line_search(
    scorer: &mut Scorer<'_>,
    pose: &Isometry3<f64>,
    current: &Evaluation,
    direction: &Vector6<f64>,
    translation_epsilon: f64,
    rotation_epsilon: f64,
) -> LineSearch {
    let slope = current.gradient.dot(direction);
    let mut length = 1.0;
    for _ in 0..=MAX_LINE_SEARCH_HALVINGS {
        let step = direction * length;
        if is_small(&step, translation_epsilon, rotation_epsilon) {
            return LineSearch::Stalled;
        }
        let candidate = apply_increment(pose, &step);
        let evaluation = scorer.evaluate(&candidate);
        if evaluation.cost <= current.cost + ARMIJO * length * slope {
            return LineSearch::Decreased(candidate, evaluation, step);
        }
        length *= 0.5;
    }
    LineSearch::Failed
}
