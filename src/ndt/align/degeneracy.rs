#![forbid(unsafe_code)]
//! Which directions of the pose the map constrains (Zhang, Kaess & Singh 2016): an eigen-analysis of
//! the information at the initial pose, translation and rotation each with the other marginalised.

use nalgebra::{Matrix3, Matrix6, SymmetricEigen, Vector6};

use super::super::score::Evaluation;

/// Which directions of the increment the map constrains, decided once at the initial pose.
pub(super) struct Degeneracy {
    /// Orthogonal projector onto the constrained directions; `None` when every direction is constrained
    /// (or the test is off), which leaves the solve exactly as without the analysis.
    pub(super) projector: Option<Matrix6<f64>>,
    pub(super) degenerate_directions: usize,
    pub(super) translation_eigenvalues: [f64; 3],
    pub(super) rotation_eigenvalues: [f64; 3],
}

impl Degeneracy {
    /// Eigen-analysis of the first-order Hessian `Σ w·JᵀΣ⁻¹J` at the initial pose, the NDT counterpart of
    /// the information matrix `JᵀJ` Zhang et al. analyse (positive semi-definite everywhere, so its
    /// spectrum means something even where the full Hessian is indefinite). Translation and rotation are
    /// analysed separately, each with the other marginalised (Schur complement): the information about the
    /// translation when the rotation is free to adjust, and vice versa. Within a block the units agree, so
    /// no length scale has to be chosen to compare metres with radians.
    pub(super) fn analyse(
        at: &Evaluation,
        translation_threshold: f64,
        rotation_threshold: f64,
    ) -> Self {
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

pub(super) fn symmetric_part(matrix: &Matrix6<f64>) -> Matrix6<f64> {
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
