//! Bindings of the rigid solve (Eq. 12–14), RANSAC (§III-D-b) and the ray-noise refit.

use numpy::ndarray::Array1;
use numpy::{IntoPyArray, PyArray1, PyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::ransac::{self, RansacConfig, Refit};
use crate::ray_noise::{self, RayNoise};
use crate::rigid;

use super::convert::{counts, matrix_to_numpy, points3, transform, vector_f64, Int};
use super::pool::{run, threads};

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyRansacResult>()?;
    m.add_class::<PyRayRefit>()?;
    m.add_function(wrap_pyfunction!(rigid_transform, m)?)?;
    m.add_function(wrap_pyfunction!(ransac_rigid, m)?)?;
    m.add_function(wrap_pyfunction!(ray_noise_refit, m)?)?;
    m.add_function(wrap_pyfunction!(refit_rigid, m)?)?;
    Ok(())
}

/// Closed-form weighted rigid solve (Eq. 12–14): `src`, `dst` N×3 → 4×4 float64 `T` with `dst ≈ T·src`.
#[pyfunction]
#[pyo3(signature = (src, dst, weights = None))]
fn rigid_transform<'py>(
    py: Python<'py>,
    src: &Bound<'py, PyAny>,
    dst: &Bound<'py, PyAny>,
    weights: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let (src, dst) = (points3("src", src)?, points3("dst", dst)?);
    let weights = weights.map(|w| vector_f64("weights", w)).transpose()?;
    let solved = run(py, Some(1), || {
        rigid::rigid_transform(&src, &dst, weights.as_deref())
    })?;
    Ok(matrix_to_numpy(py, &solved))
}

/// Result of `ransac_rigid`: `transform` (4×4 float64), `inliers` (bool mask), `num_inliers`,
/// `iterations` (hypotheses drawn) and `rmse` of the inliers under `transform`.
#[pyclass(name = "RansacResult", module = "dmlo_rs._dmlo_rs", frozen)]
pub struct PyRansacResult {
    #[pyo3(get)]
    transform: Py<PyArray2<f64>>,
    #[pyo3(get)]
    inliers: Py<PyArray1<bool>>,
    #[pyo3(get)]
    num_inliers: usize,
    #[pyo3(get)]
    iterations: usize,
    #[pyo3(get)]
    rmse: f64,
}

#[pymethods]
impl PyRansacResult {
    fn __repr__(&self) -> String {
        format!(
            "RansacResult(num_inliers={}, iterations={}, rmse={:.6})",
            self.num_inliers, self.iterations, self.rmse
        )
    }
}

/// The refit `refit` names: "point_to_point" or "ray_noise" (with `range_ratio` and
/// `bearing_threshold_deg`).
pub(super) fn refit_kind(
    refit: &str,
    range_ratio: f64,
    bearing_threshold_deg: f64,
) -> PyResult<Refit> {
    match refit {
        "point_to_point" => Ok(Refit::PointToPoint),
        "ray_noise" => Ok(Refit::RayNoise {
            noise: RayNoise {
                range_ratio,
                ..Default::default()
            },
            bearing_threshold_deg,
        }),
        other => Err(PyValueError::new_err(format!(
            "refit: expected 'point_to_point' or 'ray_noise', got {other:?}"
        ))),
    }
}

/// RANSAC around the rigid solve: minimal samples of 3, inliers within `threshold` metres,
/// adaptive iterations for `confidence`, deterministic for a `seed` whatever `num_threads`. With
/// `votes` (one per match, ≥ 0) a hypothesis's consensus is the sum of its inliers' votes.
#[pyfunction]
#[pyo3(signature = (src, dst, threshold = 0.1, confidence = 0.999, max_iterations = 1000, seed = 0, *,
                    refine_iterations = 10, refit = "point_to_point", range_ratio = 4.0,
                    bearing_threshold_deg = 0.2, votes = None, num_threads = None))]
#[allow(clippy::too_many_arguments)]
fn ransac_rigid(
    py: Python<'_>,
    src: &Bound<'_, PyAny>,
    dst: &Bound<'_, PyAny>,
    threshold: f64,
    confidence: f64,
    #[pyo3(from_py_with = counts::max_iterations)] max_iterations: usize,
    #[pyo3(from_py_with = counts::seed)] seed: u64,
    #[pyo3(from_py_with = counts::refine_iterations)] refine_iterations: usize,
    refit: &str,
    range_ratio: f64,
    bearing_threshold_deg: f64,
    votes: Option<&Bound<'_, PyAny>>,
    num_threads: Option<Int>,
) -> PyResult<PyRansacResult> {
    let (src, dst) = (points3("src", src)?, points3("dst", dst)?);
    let votes = votes.map(|v| vector_f64("votes", v)).transpose()?;
    let config = RansacConfig {
        threshold,
        confidence,
        max_iterations,
        seed,
        refine_iterations,
        refit: refit_kind(refit, range_ratio, bearing_threshold_deg)?,
        ..Default::default()
    };
    let result = run(py, threads(num_threads)?, || {
        ransac::ransac_rigid_voted(&src, &dst, votes.as_deref(), &config)
    })?;
    Ok(PyRansacResult {
        transform: matrix_to_numpy(py, &result.transform).unbind(),
        inliers: Array1::from_vec(result.inliers).into_pyarray(py).unbind(),
        num_inliers: result.num_inliers,
        iterations: result.iterations,
        rmse: result.rmse,
    })
}

/// The motion of pairs taken as inliers, solved as one of `ransac_rigid`'s refits with the same `refit`
/// and `range_ratio`: the closed-form solve, then for "ray_noise" its Gauss–Newton refit → 4×4 float64.
#[pyfunction]
#[pyo3(signature = (src, dst, *, refit = "point_to_point", range_ratio = 4.0))]
fn refit_rigid<'py>(
    py: Python<'py>,
    src: &Bound<'py, PyAny>,
    dst: &Bound<'py, PyAny>,
    refit: &str,
    range_ratio: f64,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    // The bearing tolerance only chooses RANSAC's inliers; a solve on given pairs has no use for it.
    let refit = refit_kind(refit, range_ratio, 0.0)?;
    let (src, dst) = (points3("src", src)?, points3("dst", dst)?);
    let solved = run(py, Some(1), || refit.solve(&src, &dst))?;
    Ok(matrix_to_numpy(py, &solved))
}

/// Result of `ray_noise_refit`: `transform` (4×4 float64), Gauss–Newton `iterations`, whether it
/// `converged`, and the weighted `cost` at `transform`.
#[pyclass(name = "RayRefit", module = "dmlo_rs._dmlo_rs", frozen)]
pub struct PyRayRefit {
    #[pyo3(get)]
    transform: Py<PyArray2<f64>>,
    #[pyo3(get)]
    iterations: usize,
    #[pyo3(get)]
    converged: bool,
    #[pyo3(get)]
    cost: f64,
}

#[pymethods]
impl PyRayRefit {
    fn __repr__(&self) -> String {
        format!(
            "RayRefit(iterations={}, converged={}, cost={:.6e})",
            self.iterations,
            if self.converged { "True" } else { "False" },
            self.cost
        )
    }
}

/// Gauss–Newton refit of `initial` (`dst ≈ T·src`) under ray noise: each target point (in its sensor's
/// frame) errs across its ray in bearing and along it by `range_ratio` metres per radian of bearing.
#[pyfunction]
#[pyo3(signature = (src, dst, initial, range_ratio = 4.0, max_iterations = 20))]
fn ray_noise_refit(
    py: Python<'_>,
    src: &Bound<'_, PyAny>,
    dst: &Bound<'_, PyAny>,
    initial: &Bound<'_, PyAny>,
    range_ratio: f64,
    #[pyo3(from_py_with = counts::max_iterations)] max_iterations: usize,
) -> PyResult<PyRayRefit> {
    let noise = RayNoise {
        range_ratio,
        max_iterations,
    };
    let (src, dst) = (points3("src", src)?, points3("dst", dst)?);
    let initial = transform("initial", initial)?;
    let refit = run(py, Some(1), || {
        ray_noise::ray_noise_refit(&src, &dst, &initial, &noise)
    })?;
    Ok(PyRayRefit {
        transform: matrix_to_numpy(py, &refit.transform).unbind(),
        iterations: refit.iterations,
        converged: refit.converged,
        cost: refit.cost,
    })
}
