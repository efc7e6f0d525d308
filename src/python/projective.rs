//! Bindings of the projective module: point-to-plane ICP of a pair that barely moved.

use numpy::PyArray2;
use pyo3::prelude::*;

use crate::projective::{self, PointToPlaneConfig};

use super::convert::{matrix_to_numpy, point_image, transform};
use super::pool::run;
use super::projection::PyCylinderConfig;

/// `T_tgt_ref` refined by projective point-to-plane ICP of the `target` point image's points against the
/// `reference` point image (both `[H, W, 3]` of `config`'s image, each cell's kept point, NaN where
/// empty, their own sensor frames), from `start` (4×4). Each round moves the target's points into the
/// reference frame, finds the reference cell each falls in and solves the small motion that brings them
/// onto the planes of those cells (normals from each cell's four neighbours; Gauss–Newton, Huber weights
/// beyond `huber` m, pairs farther than `max_distance` m apart left out); directions with less than
/// `min_information` of the best one's information keep the estimate. → 4×4 float64, or None when the
/// first round finds fewer than six correspondences.
#[pyfunction]
#[pyo3(signature = (reference, target, start, config, *, iterations = 10, max_distance = 0.3, huber = 0.02,
    min_information = 1e-5, edge_range_ratio = 0.1, num_threads = None))]
#[allow(clippy::too_many_arguments)]
fn point_to_plane<'py>(
    py: Python<'py>,
    reference: &Bound<'py, PyAny>,
    target: &Bound<'py, PyAny>,
    start: &Bound<'py, PyAny>,
    config: &PyCylinderConfig,
    iterations: usize,
    max_distance: f64,
    huber: f64,
    min_information: f64,
    edge_range_ratio: f64,
    num_threads: Option<i64>,
) -> PyResult<Option<Bound<'py, PyArray2<f64>>>> {
    let cylinder = config.inner;
    let reference = point_image("reference", reference, &cylinder)?;
    let target = point_image("target", target, &cylinder)?;
    let start = transform("start", start)?;
    let settings = PointToPlaneConfig {
        iterations,
        max_distance,
        huber,
        min_information,
        edge_range_ratio,
    };
    let (reference, target) = (reference.f32_data(), target.f32_data());
    let (reference, target): (&[f32], &[f32]) = (&reference, &target);
    let refined = run(py, num_threads, || {
        projective::point_to_plane(reference, target, &cylinder, &start, &settings)
    })?;
    Ok(refined.map(|pose| matrix_to_numpy(py, &pose)))
}

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(point_to_plane, m)?)?;
    Ok(())
}
