#![forbid(unsafe_code)]
//! Closed-form rigid alignment (paper Eq. 12–14): the rotation and translation minimising
//! `Σ wᵢ ‖qᵢ − (R pᵢ + t)‖²`, by the SVD of the cross-covariance (faer), with the reflection fix.
//!
//! `H = Σ wᵢ (pᵢ − p̄)(qᵢ − q̄)ᵀ = U S Vᵀ`, `R = V diag(1, 1, d) Uᵀ` with `d = sign det(V Uᵀ)` (so that
//! `R ∈ SO(3)` even when the unconstrained optimum is a reflection), `t = q̄ − R p̄`.

use nalgebra::{
    Isometry3, Matrix3, Matrix4, Point3, Rotation3, Translation3, UnitQuaternion, Vector3,
};

use crate::error::{Error, Result};

/// Ratio `σ₂/σ₁` of the cross-covariance's singular values below which the points are taken as
/// collinear (or coincident): the rotation about their line is then undetermined.
pub const DEGENERACY_RATIO: f64 = 1e-9;

/// Reusable buffers for the 3×3 SVD, so hot loops (RANSAC's minimal solves) do not allocate: faer's
/// allocation-free SVD core with its scratch sized once, run sequentially (`Par::Seq`).
pub(crate) struct Svd3 {
    scratch: faer::dyn_stack::MemBuffer,
    a: faer::Mat<f64>,
    u: faer::Mat<f64>,
    v: faer::Mat<f64>,
    s: faer::diag::Diag<f64>,
}

impl Svd3 {
    pub(crate) fn new() -> Self {
        use faer::linalg::svd::{svd_scratch, ComputeSvdVectors};
        let request = svd_scratch::<f64>(
            3,
            3,
            ComputeSvdVectors::Full,
            ComputeSvdVectors::Full,
            faer::Par::Seq,
            Default::default(),
        );
        Svd3 {
            scratch: faer::dyn_stack::MemBuffer::new(request),
            a: faer::Mat::zeros(3, 3),
            u: faer::Mat::zeros(3, 3),
            v: faer::Mat::zeros(3, 3),
            s: faer::diag::Diag::zeros(3),
        }
    }

    /// Rotation from a cross-covariance `H = Σ w (p − p̄)(q − q̄)ᵀ`, or `None` when `H` has rank < 2.
    pub(crate) fn rotation_from_cross_covariance(
        &mut self,
        h: &Matrix3<f64>,
    ) -> Option<Matrix3<f64>> {
        if !h.iter().all(|v| v.is_finite()) {
            return None;
        }
        // The rotation does not depend on the scale of `H`; bringing its entries near 1 keeps the SVD
        // from overflowing or underflowing on points of any scale, so the degeneracy test below judges
        // shape alone.
        let scale = power_of_two_scale(h.amax());
        for i in 0..3 {
            for j in 0..3 {
                self.a[(i, j)] = h[(i, j)] * scale;
            }
        }
        faer::linalg::svd::svd(
            self.a.as_ref(),
            self.s.as_mut(),
            Some(self.u.as_mut()),
            Some(self.v.as_mut()),
            faer::Par::Seq,
            faer::dyn_stack::MemStack::new(&mut self.scratch),
            Default::default(),
        )
        .ok()?;
        let s = self.s.as_ref().column_vector();
        let singular = [s[0].abs(), s[1].abs(), s[2].abs()];
        let mut sorted = singular;
        sorted.sort_by(|a, b| b.total_cmp(a));
        if sorted[0] == 0.0 || sorted[1] <= DEGENERACY_RATIO * sorted[0] {
            return None;
        }
        // The column of V with the smallest singular value takes the reflection fix.
        let smallest = (0..3)
            .min_by(|&a, &b| singular[a].total_cmp(&singular[b]))
            .unwrap_or(2);
        let u = Matrix3::from_fn(|i, j| self.u[(i, j)]);
        let mut v = Matrix3::from_fn(|i, j| self.v[(i, j)]);
        if (v * u.transpose()).determinant() < 0.0 {
            v.column_mut(smallest).neg_mut();
        }
        Some(v * u.transpose())
    }
}

/// A power of two that brings `largest` (≥ 0) to [1, 2): multiplying by it is exact, so it rescales
/// without rounding. 1 for 0.
fn power_of_two_scale(largest: f64) -> f64 {
    if largest > 0.0 && largest.is_finite() {
        2f64.powi(-(largest.log2().floor() as i32))
    } else {
        1.0
    }
}

/// An isometry from a rotation matrix (already orthonormal, det +1) and a translation.
pub(crate) fn isometry_from_parts(
    rotation: &Matrix3<f64>,
    translation: &Vector3<f64>,
) -> Isometry3<f64> {
    let rotation =
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(*rotation));
    Isometry3::from_parts(Translation3::from(*translation), rotation)
}

/// Checks that `src` and `dst` pair up (same length) and hold only finite points, naming the one at fault.
pub(crate) fn check_pairs(src: &[Point3<f64>], dst: &[Point3<f64>]) -> Result<()> {
    if dst.len() != src.len() {
        return Err(Error::invalid(
            "dst",
            format!("has {} points, src has {}", dst.len(), src.len()),
        ));
    }
    for (name, points) in [("src", src), ("dst", dst)] {
        if let Some(i) = points
            .iter()
            .position(|p| !p.coords.iter().all(|v| v.is_finite()))
        {
            return Err(Error::invalid(name, format!("point {i} is not finite")));
        }
    }
    Ok(())
}

/// Solves Eq. 12–14: the rigid `T` (an [`Isometry3`], `dst ≈ T · src`) minimising the weighted squared
/// distances. `weights` (optional) must be finite and ≥ 0 with at least 3 positive.
///
/// Errors: [`Error::TooFewPoints`] for fewer than 3 (positively weighted) pairs,
/// [`Error::Degenerate`] when the source or target points are collinear or coincide,
/// [`Error::InvalidArgument`] for mismatched lengths or non-finite values.
pub fn rigid_transform(
    src: &[Point3<f64>],
    dst: &[Point3<f64>],
    weights: Option<&[f64]>,
) -> Result<Isometry3<f64>> {
    check_pairs(src, dst)?;
    if let Some(w) = weights {
        if w.len() != src.len() {
            return Err(Error::invalid(
                "weights",
                format!("has {} values, src has {} points", w.len(), src.len()),
            ));
        }
        if let Some(i) = w.iter().position(|w| !(w.is_finite() && *w >= 0.0)) {
            return Err(Error::invalid(
                "weights",
                format!("element {i} is {} (need finite and >= 0)", w[i]),
            ));
        }
    }
    let weight = |i: usize| weights.map_or(1.0, |w| w[i]);
    let used = (0..src.len()).filter(|&i| weight(i) > 0.0).count();
    if used < 3 {
        return Err(Error::TooFewPoints {
            needed: 3,
            got: used,
        });
    }
    let total: f64 = (0..src.len()).map(weight).sum();
    let mut p_mean = Vector3::zeros();
    let mut q_mean = Vector3::zeros();
    for i in 0..src.len() {
        p_mean += src[i].coords * weight(i);
        q_mean += dst[i].coords * weight(i);
    }
    p_mean /= total;
    q_mean /= total;
    // Each side's offsets from its centroid are rescaled (exactly, by a power of two) before they are
    // multiplied, so that `H` neither overflows for huge coordinates nor underflows for tiny ones.
    let spread = |points: &[Point3<f64>], mean: &Vector3<f64>| {
        points
            .iter()
            .map(|p| (p.coords - mean).amax())
            .fold(0.0, f64::max)
    };
    let (p_scale, q_scale) = (
        power_of_two_scale(spread(src, &p_mean)),
        power_of_two_scale(spread(dst, &q_mean)),
    );
    let mut h = Matrix3::zeros();
    for i in 0..src.len() {
        h += ((src[i].coords - p_mean) * p_scale)
            * ((dst[i].coords - q_mean) * q_scale).transpose()
            * weight(i);
    }
    let rotation = Svd3::new()
        .rotation_from_cross_covariance(&h)
        .ok_or_else(|| Error::Degenerate("the points are collinear or coincident".into()))?;
    Ok(isometry_from_parts(
        &rotation,
        &(q_mean - rotation * p_mean),
    ))
}

/// Converts a 4×4 homogeneous matrix into an [`Isometry3`], checking that it is one: finite, last row
/// `0 0 0 1`, rotation block orthonormal (to 1e-6) with determinant +1. `argument` names it in errors.
pub fn isometry_from_matrix(
    matrix: &Matrix4<f64>,
    argument: &'static str,
) -> Result<Isometry3<f64>> {
    if !matrix.iter().all(|v| v.is_finite()) {
        return Err(Error::invalid(argument, "has non-finite entries"));
    }
    let last_row = matrix.row(3);
    if (last_row[0].abs() + last_row[1].abs() + last_row[2].abs() + (last_row[3] - 1.0).abs())
        > 1e-9
    {
        return Err(Error::invalid(
            argument,
            format!("last row must be [0, 0, 0, 1], got {last_row}"),
        ));
    }
    let rotation: Matrix3<f64> = matrix.fixed_view::<3, 3>(0, 0).into_owned();
    let orthonormality = (rotation.transpose() * rotation - Matrix3::identity())
        .abs()
        .max();
    if orthonormality > 1e-6 || rotation.determinant() <= 0.0 {
        return Err(Error::invalid(
            argument,
            format!(
                "rotation block is not a rotation (|RᵀR − I| = {orthonormality:.2e}, det = {:.6})",
                rotation.determinant()
            ),
        ));
    }
    let translation: Vector3<f64> = matrix.fixed_view::<3, 1>(0, 3).into_owned();
    let rotation = UnitQuaternion::from_matrix(&rotation);
    Ok(Isometry3::from_parts(
        Translation3::from(translation),
        rotation,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_isometry(rng: &mut ChaCha8Rng) -> Isometry3<f64> {
        let axis_angle = Vector3::new(
            rng.random_range(-3.0..3.0),
            rng.random_range(-3.0..3.0),
            rng.random_range(-3.0..3.0),
        );
        let translation = Vector3::new(
            rng.random_range(-10.0..10.0),
            rng.random_range(-10.0..10.0),
            rng.random_range(-10.0..10.0),
        );
        Isometry3::new(translation, axis_angle)
    }

    fn random_points(rng: &mut ChaCha8Rng, n: usize) -> Vec<Point3<f64>> {
        (0..n)
            .map(|_| {
                Point3::new(
                    rng.random_range(-20.0..20.0),
                    rng.random_range(-20.0..20.0),
                    rng.random_range(-3.0..3.0),
                )
            })
            .collect()
    }

    fn assert_close(a: &Isometry3<f64>, b: &Isometry3<f64>, tolerance: f64) {
        let difference = (a.to_homogeneous() - b.to_homogeneous()).abs().max();
        assert!(
            difference < tolerance,
            "transforms differ by {difference}:\n{a}\n{b}"
        );
    }

    #[test]
    fn recovers_random_transforms_exactly_on_noise_free_data() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for n in [3, 4, 10, 500] {
            for _ in 0..50 {
                let truth = random_isometry(&mut rng);
                let src = random_points(&mut rng, n);
                let dst: Vec<_> = src.iter().map(|p| truth * p).collect();
                assert_close(&rigid_transform(&src, &dst, None).unwrap(), &truth, 1e-9);
                // The inverse direction gives the inverse transform.
                assert_close(
                    &rigid_transform(&dst, &src, None).unwrap(),
                    &truth.inverse(),
                    1e-9,
                );
            }
        }
    }

    #[test]
    fn coplanar_points_and_mirrored_targets_still_give_a_proper_rotation() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        for _ in 0..200 {
            // Coplanar sources: the smallest singular value is 0 and the SVD's third axis sign is
            // arbitrary, so without the fix about half of these come out as reflections.
            let truth = random_isometry(&mut rng);
            let src: Vec<_> = (0..6)
                .map(|_| {
                    Point3::new(
                        rng.random_range(-5.0..5.0),
                        rng.random_range(-5.0..5.0),
                        0.0,
                    )
                })
                .collect();
            let dst: Vec<_> = src.iter().map(|p| truth * p).collect();
            let estimate = rigid_transform(&src, &dst, None).unwrap();
            assert!(
                (estimate
                    .rotation
                    .to_rotation_matrix()
                    .matrix()
                    .determinant()
                    - 1.0)
                    .abs()
                    < 1e-9
            );
            assert_close(&estimate, &truth, 1e-9);
        }
        // A mirror image cannot be reached by a rotation: the result is still in SO(3).
        let src = random_points(&mut rng, 20);
        let mirrored: Vec<_> = src.iter().map(|p| Point3::new(p.x, p.y, -p.z)).collect();
        let estimate = rigid_transform(&src, &mirrored, None).unwrap();
        assert!(
            (estimate
                .rotation
                .to_rotation_matrix()
                .matrix()
                .determinant()
                - 1.0)
                .abs()
                < 1e-9
        );
    }

    #[test]
    fn weights_select_the_points_that_count() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let truth = random_isometry(&mut rng);
        let src = random_points(&mut rng, 30);
        let mut dst: Vec<_> = src.iter().map(|p| truth * p).collect();
        let mut weights = vec![1.0; 30];
        for i in 0..10 {
            dst[i] += Vector3::new(5.0, -3.0, 1.0); // outliers with zero weight
            weights[i] = 0.0;
        }
        assert_close(
            &rigid_transform(&src, &dst, Some(&weights)).unwrap(),
            &truth,
            1e-9,
        );
    }

    #[test]
    fn too_few_degenerate_and_bad_inputs_are_errors() {
        let p = |x: f64, y: f64, z: f64| Point3::new(x, y, z);
        let two = [p(0.0, 0.0, 0.0), p(1.0, 0.0, 0.0)];
        assert_eq!(
            rigid_transform(&two, &two, None),
            Err(Error::TooFewPoints { needed: 3, got: 2 })
        );
        let collinear = [
            p(0.0, 0.0, 0.0),
            p(1.0, 1.0, 1.0),
            p(2.0, 2.0, 2.0),
            p(-3.0, -3.0, -3.0),
        ];
        assert!(matches!(
            rigid_transform(&collinear, &collinear, None),
            Err(Error::Degenerate(_))
        ));
        let same = [p(1.0, 2.0, 3.0); 5];
        assert!(matches!(
            rigid_transform(&same, &same, None),
            Err(Error::Degenerate(_))
        ));
        let three = [p(0.0, 0.0, 0.0), p(1.0, 0.0, 0.0), p(0.0, 1.0, 0.0)];
        assert!(rigid_transform(&three, &three[..2], None).is_err());
        assert!(rigid_transform(&three, &three, Some(&[1.0, 1.0, f64::NAN])).is_err());
        assert!(matches!(
            rigid_transform(&three, &three, Some(&[1.0, 1.0, 0.0])),
            Err(Error::TooFewPoints { .. })
        ));
        let nan = [p(0.0, 0.0, f64::NAN), p(1.0, 0.0, 0.0), p(0.0, 1.0, 0.0)];
        assert!(rigid_transform(&nan, &three, None).is_err());
    }

    #[test]
    fn degeneracy_is_judged_on_shape_whatever_the_scale() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for scale in [1e-100, 1e-30, 1e30, 1e100, 1e150] {
            let truth = random_isometry(&mut rng);
            let src = random_points(&mut rng, 20);
            let dst: Vec<_> = src.iter().map(|p| truth * p).collect();
            let scaled = |points: &[Point3<f64>]| -> Vec<_> {
                points
                    .iter()
                    .map(|p| Point3::from(p.coords * scale))
                    .collect()
            };
            let estimate = rigid_transform(&scaled(&src), &scaled(&dst), None)
                .unwrap_or_else(|e| panic!("scale {scale}: {e}"));
            let rotation_error = (estimate.rotation.inverse() * truth.rotation).angle();
            assert!(rotation_error < 1e-9, "scale {scale}: {rotation_error} rad");
            let translation_error =
                (estimate.translation.vector / scale - truth.translation.vector).norm();
            assert!(
                translation_error < 1e-9,
                "scale {scale}: {translation_error}"
            );
            // Collinear points stay collinear at any scale.
            let line: Vec<_> = (0..10)
                .map(|i| Point3::new(i as f64, 2.0 * i as f64, 3.0) * scale)
                .collect();
            assert!(matches!(
                rigid_transform(&line, &line, None),
                Err(Error::Degenerate(_))
            ));
        }
    }

    #[test]
    fn matrices_are_checked_before_becoming_isometries() {
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        let truth = random_isometry(&mut rng);
        assert_close(
            &isometry_from_matrix(&truth.to_homogeneous(), "T").unwrap(),
            &truth,
            1e-12,
        );
        let mut scaled = truth.to_homogeneous();
        scaled[(0, 0)] *= 2.0;
        assert!(isometry_from_matrix(&scaled, "T").is_err());
        let mut bad_row = truth.to_homogeneous();
        bad_row[(3, 0)] = 0.5;
        assert!(isometry_from_matrix(&bad_row, "T").is_err());
        let mirror = Matrix4::from_diagonal(&nalgebra::Vector4::new(1.0, 1.0, -1.0, 1.0));
        assert!(isometry_from_matrix(&mirror, "T").is_err());
    }
}
