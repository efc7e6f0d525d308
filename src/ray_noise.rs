#![forbid(unsafe_code)]
//! Rigid refit under ray noise (beyond the paper): the motion that is most likely when each matched
//! target point errs across its ray in bearing and along it in range, by Gauss–Newton on SE(3).
//!
//! The network places a match in the target image, i.e. it errs in *bearing*: the 3D error of a match
//! at range `r` grows as `σ_b·r` across the ray, while the range, read from the target scan, errs by a
//! roughly constant `σ_r` along it. The SVD solve (Eq. 12–14) weighs every direction alike, which is
//! maximum likelihood only for isotropic noise: it lets distant matches pull the rotation as much as
//! near ones and throws away that the range is the well-measured part. Here each match gets the
//! information (inverse covariance, up to the common factor `1/σ_b²`)
//!
//! `Ωᵢ = (I − nᵢnᵢᵀ) / rᵢ² + nᵢnᵢᵀ / r*²`,  `nᵢ = qᵢ/‖qᵢ‖`, `rᵢ = ‖qᵢ‖`,
//!
//! where `qᵢ` is the target point in its sensor's frame and `r* = σ_r/σ_b` (metres) the range at which
//! a bearing error moves a point as far as a range error does; only that ratio matters. The refit
//! minimises `Σ eᵢᵀ Ωᵢ eᵢ` with `eᵢ = T·pᵢ − qᵢ`, from a starting motion (RANSAC's), by Gauss–Newton
//! steps `T ← exp(δ)·T`, `δ = (ω, v)`, Jacobian `∂eᵢ/∂δ = [−[T·pᵢ]×, I]`.

use nalgebra::{Isometry3, Matrix3, Matrix6, Point3, SymmetricEigen, Vector3, Vector6};

use crate::error::{Error, Result};
use crate::rigid::check_pairs;

/// Smallest over largest eigenvalue of the normal matrix below which the motion is undetermined
/// (collinear or coincident points).
const DEGENERACY_RATIO: f64 = 1e-12;

/// Target points closer to their sensor than this (metres) have no usable ray.
pub const MIN_RANGE: f64 = 1e-3;

/// Settings of [`ray_noise_refit`]; `Default` is the odometry's.
#[derive(Debug, Clone, PartialEq)]
pub struct RayNoise {
    /// `r* = σ_r / σ_b` in metres: range noise over bearing noise (radians). Larger trusts the range
    /// less; `r*` at a match's own range weighs it isotropically.
    pub range_ratio: f64,
    /// Upper bound on Gauss–Newton steps (≥ 1); the solve settles in 3–5 steps at ratios of 3–30 m,
    /// slower for small ratios (10–20 at 0.5 m).
    pub max_iterations: usize,
}

impl Default for RayNoise {
    fn default() -> Self {
        RayNoise {
            range_ratio: 4.0,
            max_iterations: 20,
        }
    }
}

impl RayNoise {
    /// Checks the settings, naming the field at fault.
    pub fn validate(&self) -> Result<()> {
        if !(self.range_ratio.is_finite() && self.range_ratio > 0.0) {
            return Err(Error::invalid(
                "range_ratio",
                format!("must be finite and > 0 (metres), got {}", self.range_ratio),
            ));
        }
        if self.max_iterations == 0 {
            return Err(Error::invalid("max_iterations", "must be >= 1"));
        }
        Ok(())
    }
}

/// What [`ray_noise_refit`] found.
#[derive(Debug, Clone, PartialEq)]
pub struct RayRefit {
    /// The motion `T` with `dst ≈ T·src`.
    pub transform: Isometry3<f64>,
    /// Gauss–Newton steps taken.
    pub iterations: usize,
    /// Whether the solve settled before `max_iterations` ran out: its last step was below 1e-9 (radians
    /// and metres), or no step along the Gauss–Newton direction lowered the cost any more.
    pub converged: bool,
    /// `Σ eᵢᵀ Ωᵢ eᵢ` at `transform`, in units of the bearing variance (radians²).
    pub cost: f64,
}

/// The information `Ω` of a target point `q` seen from its sensor's origin (see the module docs);
/// `None` when `q` lies within [`MIN_RANGE`] of the origin.
pub fn ray_information(q: &Vector3<f64>, range_ratio: f64) -> Option<Matrix3<f64>> {
    let range_sq = q.norm_squared();
    if range_sq.is_nan() || range_sq < MIN_RANGE * MIN_RANGE {
        return None;
    }
    // (I − nnᵀ)/r² + nnᵀ/r*², with nnᵀ = qqᵀ/r².
    let across = 1.0 / range_sq;
    let along = 1.0 / (range_ratio * range_ratio);
    Some(Matrix3::identity() * across + q * q.transpose() * ((along - across) / range_sq))
}

/// Checks that every target point has a ray (lies at least [`MIN_RANGE`] from its sensor's origin),
/// naming the first that does not.
pub(crate) fn check_rays(dst: &[Point3<f64>]) -> Result<()> {
    match dst.iter().position(|q| ray_information(&q.coords, 1.0).is_none()) {
        Some(i) => Err(Error::invalid(
            "dst",
            format!("point {i} lies within {MIN_RANGE} m of the sensor (no ray for the ray-noise refit)"),
        )),
        None => Ok(()),
    }
}

/// Refines `initial` (`dst ≈ T·src`) to the motion of least `Σ eᵢᵀ Ωᵢ eᵢ`, `dst` being the target points
/// in their sensor's frame (the ray of each runs from the origin).
///
/// Errors: [`Error::TooFewPoints`] for fewer than 3 pairs; [`Error::InvalidArgument`] for bad settings,
/// mismatched lengths, non-finite points or a target point at the sensor's origin;
/// [`Error::Degenerate`] when the points do not determine the motion (collinear, coincident).
pub fn ray_noise_refit(
    src: &[Point3<f64>],
    dst: &[Point3<f64>],
    initial: &Isometry3<f64>,
    noise: &RayNoise,
) -> Result<RayRefit> {
    noise.validate()?;
    check_pairs(src, dst)?;
    if src.len() < 3 {
        return Err(Error::TooFewPoints {
            needed: 3,
            got: src.len(),
        });
    }
    check_rays(dst)?;
    // Every point has a ray now, so nothing is filtered out.
    let information: Vec<Matrix3<f64>> = dst
        .iter()
        .filter_map(|q| ray_information(&q.coords, noise.range_ratio))
        .collect();

    let cost_at = |transform: &Isometry3<f64>| -> f64 {
        src.iter()
            .zip(dst)
            .zip(&information)
            .map(|((p, q), omega)| {
                let e = transform * p - q;
                e.dot(&(omega * e))
            })
            .sum()
    };
    let mut transform = *initial;
    let mut cost = cost_at(&transform);
    let mut iterations = 0;
    let mut converged = false;
    while iterations < noise.max_iterations {
        iterations += 1;
        // J = [−[m]×, I] with m = T·p: JᵀΩJ = [[−[m]×Ω[m]×, [m]×Ω], [([m]×Ω)ᵀ, Ω]], JᵀΩe = [[m]×Ωe, Ωe].
        let (mut rotation_rotation, mut rotation_translation) =
            (Matrix3::zeros(), Matrix3::zeros());
        let mut translation_translation = Matrix3::zeros();
        let (mut rotation_gradient, mut translation_gradient) =
            (Vector3::zeros(), Vector3::zeros());
        for ((p, q), omega) in src.iter().zip(dst).zip(&information) {
            let moved = (transform * p).coords;
            let skew = moved.cross_matrix();
            let skew_omega = skew * omega;
            let omega_e = omega * (moved - q.coords);
            rotation_rotation -= skew_omega * skew;
            rotation_translation += skew_omega;
            translation_translation += omega;
            rotation_gradient += skew * omega_e;
            translation_gradient += omega_e;
        }
        let mut hessian = Matrix6::zeros();
        hessian
            .fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&rotation_rotation);
        hessian
            .fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&rotation_translation);
        hessian
            .fixed_view_mut::<3, 3>(3, 0)
            .copy_from(&rotation_translation.transpose());
        hessian
            .fixed_view_mut::<3, 3>(3, 3)
            .copy_from(&translation_translation);
        let mut gradient = Vector6::zeros();
        gradient
            .fixed_rows_mut::<3>(0)
            .copy_from(&rotation_gradient);
        gradient
            .fixed_rows_mut::<3>(3)
            .copy_from(&translation_gradient);
        let step = solve_normal_equations(&hessian, &gradient)?;
        // Backtracking keeps every accepted step a descent (Gauss–Newton can overshoot far from the
        // optimum; near it the full step is taken).
        let mut scale = 1.0;
        let mut accepted = None;
        for _ in 0..8 {
            let delta = step * scale;
            let candidate = Isometry3::new(
                delta.fixed_rows::<3>(3).into_owned(),
                delta.fixed_rows::<3>(0).into_owned(),
            ) * transform;
            let candidate_cost = cost_at(&candidate);
            if candidate_cost <= cost {
                accepted = Some((candidate, candidate_cost, delta));
                break;
            }
            scale *= 0.5;
        }
        let Some((candidate, candidate_cost, delta)) = accepted else {
            converged = true; // no step lowers the cost: at the optimum to rounding
            break;
        };
        transform = candidate;
        cost = candidate_cost;
        if delta.amax() < 1e-9 {
            converged = true;
            break;
        }
    }
    Ok(RayRefit {
        transform,
        iterations,
        converged,
        cost,
    })
}

/// `δ = −H⁻¹ g`, or [`Error::Degenerate`] when `H` is (nearly) singular.
fn solve_normal_equations(hessian: &Matrix6<f64>, gradient: &Vector6<f64>) -> Result<Vector6<f64>> {
    let degenerate = || Error::Degenerate("the points do not determine the motion".into());
    if !hessian.iter().all(|v| v.is_finite()) {
        return Err(degenerate());
    }
    let eigenvalues = SymmetricEigen::new(*hessian).eigenvalues;
    let largest = eigenvalues.amax();
    let smallest = eigenvalues.min();
    if !(largest > 0.0 && smallest > DEGENERACY_RATIO * largest) {
        return Err(degenerate());
    }
    let cholesky = hessian.cholesky().ok_or_else(degenerate)?;
    Ok(-cholesky.solve(gradient))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rigid::rigid_transform;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn motion(translation: [f64; 3], axis_angle_deg: [f64; 3]) -> Isometry3<f64> {
        Isometry3::new(
            Vector3::from(translation),
            Vector3::from(axis_angle_deg.map(f64::to_radians)),
        )
    }

    /// Reference points of a street-like scan (2–60 m away, around the sensor) and their targets under
    /// `truth`, each target moved by `bearing_noise` radians across its ray and `range_noise` metres
    /// along it (Gaussian).
    fn scan_pairs(
        rng: &mut ChaCha8Rng,
        n: usize,
        truth: &Isometry3<f64>,
        bearing_noise: f64,
        range_noise: f64,
    ) -> (Vec<Point3<f64>>, Vec<Point3<f64>>) {
        let mut gaussian = || {
            // Box–Muller: rand without rand_distr.
            let (u, v): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random_range(0.0..1.0));
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        };
        let mut src = Vec::new();
        let mut dst = Vec::new();
        let mut rng_points = ChaCha8Rng::seed_from_u64(n as u64);
        for _ in 0..n {
            let range: f64 = rng_points.random_range(2.0..60.0);
            let azimuth: f64 = rng_points.random_range(-std::f64::consts::PI..std::f64::consts::PI);
            let elevation: f64 = rng_points.random_range(-0.4..0.03);
            let p = Point3::new(
                range * elevation.cos() * azimuth.cos(),
                range * elevation.cos() * azimuth.sin(),
                range * elevation.sin(),
            );
            let q = (truth * p).coords;
            let ray = q.normalize();
            let across_1 = ray.cross(&Vector3::z()).normalize();
            let across_2 = ray.cross(&across_1);
            let r = q.norm();
            let noisy = q
                + ray * (range_noise * gaussian())
                + across_1 * (bearing_noise * r * gaussian())
                + across_2 * (bearing_noise * r * gaussian());
            src.push(p);
            dst.push(Point3::from(noisy));
        }
        (src, dst)
    }

    fn rotation_error_deg(a: &Isometry3<f64>, b: &Isometry3<f64>) -> f64 {
        (a.rotation.inverse() * b.rotation).angle().to_degrees()
    }

    fn cost(src: &[Point3<f64>], dst: &[Point3<f64>], t: &Isometry3<f64>, ratio: f64) -> f64 {
        src.iter()
            .zip(dst)
            .map(|(p, q)| {
                let e = t * p - q;
                e.dot(&(ray_information(&q.coords, ratio).unwrap() * e))
            })
            .sum()
    }

    #[test]
    fn information_is_bearing_across_the_ray_and_range_along_it() {
        let q = Vector3::new(3.0, 4.0, 0.0); // r = 5
        let omega = ray_information(&q, 2.0).unwrap();
        let ray = q / 5.0;
        let across = Vector3::new(-4.0, 3.0, 0.0) / 5.0;
        assert!((ray.dot(&(omega * ray)) - 1.0 / 4.0).abs() < 1e-15);
        assert!((across.dot(&(omega * across)) - 1.0 / 25.0).abs() < 1e-15);
        assert!((Vector3::z().dot(&(omega * Vector3::z())) - 1.0 / 25.0).abs() < 1e-15);
        assert!((ray.dot(&(omega * across))).abs() < 1e-15);
        assert!(ray_information(&Vector3::new(1e-4, 0.0, 0.0), 2.0).is_none());
    }

    #[test]
    fn noise_free_pairs_give_the_motion_from_far_starts() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let truth = motion([0.9, -0.1, 0.03], [0.2, -0.3, 4.0]);
        let (src, dst) = scan_pairs(&mut rng, 200, &truth, 0.0, 0.0);
        for start in [
            Isometry3::identity(),
            motion([2.0, 1.0, -0.5], [3.0, -2.0, 20.0]),
            truth.inverse(),
        ] {
            let refit = ray_noise_refit(&src, &dst, &start, &RayNoise::default()).unwrap();
            let gap = (refit.transform.to_homogeneous() - truth.to_homogeneous())
                .abs()
                .max();
            assert!(gap < 1e-9, "from {start}: {gap} from the truth");
            assert!(refit.converged && refit.cost < 1e-18, "{refit:?}");
        }
    }

    #[test]
    fn equal_ranges_at_the_range_ratio_reduce_to_the_closed_form_solve() {
        // Ω = I/r*² for every target at range r*: the isotropic least squares of Eq. 12–14.
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let truth = motion([0.5, 0.2, 0.0], [0.0, 0.5, -3.0]);
        let (_, dst) = scan_pairs(&mut rng, 100, &truth, 0.0, 0.0);
        let sphere: Vec<Point3<f64>> = dst
            .iter()
            .map(|q| Point3::from(q.coords.normalize() * 7.0))
            .collect();
        // Sources that match the sphere up to a few centimetres, so the two optima differ.
        let src: Vec<Point3<f64>> = sphere
            .iter()
            .map(|q| {
                let wobble = Vector3::new(
                    rng.random_range(-0.05..0.05),
                    rng.random_range(-0.05..0.05),
                    0.0,
                );
                truth.inverse() * (q + wobble)
            })
            .collect();
        let closed_form = rigid_transform(&src, &sphere, None).unwrap();
        assert!(closed_form != truth);
        let noise = RayNoise {
            range_ratio: 7.0,
            ..Default::default()
        };
        let refit = ray_noise_refit(&src, &sphere, &Isometry3::identity(), &noise).unwrap();
        let gap = (refit.transform.to_homogeneous() - closed_form.to_homogeneous())
            .abs()
            .max();
        assert!(gap < 1e-9, "{gap}");
    }

    #[test]
    fn the_refit_is_a_minimum_of_the_weighted_cost() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let truth = motion([1.1, 0.05, -0.02], [-0.1, 0.2, 2.0]);
        let (src, dst) = scan_pairs(&mut rng, 300, &truth, 0.002, 0.02);
        let noise = RayNoise::default();
        let refit = ray_noise_refit(&src, &dst, &Isometry3::identity(), &noise).unwrap();
        let best = cost(&src, &dst, &refit.transform, noise.range_ratio);
        assert!((best - refit.cost).abs() <= 1e-12 * best);
        for k in 0..6 {
            for sign in [-1.0, 1.0] {
                let mut delta = Vector6::zeros();
                delta[k] = sign * 1e-5;
                let moved = Isometry3::new(
                    delta.fixed_rows::<3>(3).into_owned(),
                    delta.fixed_rows::<3>(0).into_owned(),
                ) * refit.transform;
                assert!(
                    cost(&src, &dst, &moved, noise.range_ratio) > best,
                    "direction {k} {sign}"
                );
            }
        }
    }

    #[test]
    fn under_ray_noise_it_beats_the_closed_form_solve() {
        // Bearing noise of 0.05° (a fraction of a cell) and 2 cm in range: the SVD solve lets distant
        // matches' large lateral errors pull the rotation; the refit weighs them down.
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let truth = motion([0.8, 0.0, 0.0], [0.0, 0.0, 1.5]);
        let (mut closed_form_sum, mut refit_sum) = (0.0, 0.0);
        for _ in 0..40 {
            let (src, dst) = scan_pairs(&mut rng, 400, &truth, 0.05f64.to_radians(), 0.02);
            let closed_form = rigid_transform(&src, &dst, None).unwrap();
            let noise = RayNoise {
                range_ratio: 0.02 / 0.05f64.to_radians(),
                ..Default::default()
            };
            let refit = ray_noise_refit(&src, &dst, &closed_form, &noise).unwrap();
            closed_form_sum += rotation_error_deg(&closed_form, &truth);
            refit_sum += rotation_error_deg(&refit.transform, &truth);
        }
        assert!(
            refit_sum < 0.85 * closed_form_sum,
            "{refit_sum} vs {closed_form_sum}"
        );
    }

    #[test]
    fn bad_and_degenerate_input_are_errors() {
        let p = |x: f64, y: f64, z: f64| Point3::new(x, y, z);
        let three = [p(5.0, 0.0, 0.0), p(0.0, 5.0, 0.0), p(0.0, 0.0, 5.0)];
        let start = Isometry3::identity();
        let noise = RayNoise::default();
        assert_eq!(
            ray_noise_refit(&three[..2], &three[..2], &start, &noise),
            Err(Error::TooFewPoints { needed: 3, got: 2 })
        );
        assert!(ray_noise_refit(&three, &three, &start, &noise).is_ok());
        assert!(matches!(
            ray_noise_refit(&three, &three[..2], &start, &noise),
            Err(Error::InvalidArgument {
                argument: "dst",
                ..
            })
        ));
        let nan = [p(f64::NAN, 0.0, 0.0), three[1], three[2]];
        assert!(matches!(
            ray_noise_refit(&nan, &three, &start, &noise),
            Err(Error::InvalidArgument {
                argument: "src",
                ..
            })
        ));
        let at_origin = [p(0.0, 0.0, 0.0), three[1], three[2]];
        assert!(matches!(
            ray_noise_refit(&three, &at_origin, &start, &noise),
            Err(Error::InvalidArgument {
                argument: "dst",
                ..
            })
        ));
        let collinear: Vec<_> = (1..20).map(|i| p(i as f64, 2.0 * i as f64, 0.5)).collect();
        assert!(matches!(
            ray_noise_refit(&collinear, &collinear, &start, &noise),
            Err(Error::Degenerate(_))
        ));
        for bad in [
            RayNoise {
                range_ratio: 0.0,
                ..Default::default()
            },
            RayNoise {
                range_ratio: f64::INFINITY,
                ..Default::default()
            },
            RayNoise {
                max_iterations: 0,
                ..Default::default()
            },
        ] {
            assert!(matches!(
                ray_noise_refit(&three, &three, &start, &bad),
                Err(Error::InvalidArgument { .. })
            ));
        }
    }
}
