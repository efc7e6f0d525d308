//! Bindings of the surface module: the vote of each match for a horizontal motion, and the cheap test
//! of an upright surface.

use numpy::ndarray::Array1;
use numpy::{IntoPyArray, PyArray1};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::projection::CylinderConfig;
use crate::surface;

use super::convert::{point_image, vector_i64};
use super::pool::run;
use super::projection::PyCylinderConfig;

/// Per reference cell (`rows[i]`, `cols[i]`, e.g. a decoded match's cell): the weight of its vote for a
/// horizontal motion, the horizontal part of the normal of the surface there in the reference scan's
/// point image `points` (`[H, W, 3]`, each cell's kept point, NaN where empty): ≈ 0 on level ground, 1
/// on a wall; at least `floor`, and 1 where the normal cannot be told. → float64.
#[pyfunction]
#[pyo3(signature = (points, rows, cols, config, *, floor = 0.0))]
fn horizontal_votes<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    rows: &Bound<'py, PyAny>,
    cols: &Bound<'py, PyAny>,
    config: &PyCylinderConfig,
    floor: f64,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    per_cell(py, points, rows, cols, config, |points, cylinder, cells| {
        surface::horizontal_votes(points, cylinder, cells, floor)
    })
}

/// Per cell (`rows[i]`, `cols[i]`) of a scan's point image `points` (`[H, W, 3]`, NaN where empty):
/// whether it lies on an upright surface, told from the segment to the next point of its column above or
/// below alone (either one rising at least as steeply as a surface whose normal's horizontal part is
/// `min_sine`), without the plane fit of `horizontal_votes`; true for an empty cell and where the column
/// holds no other point nearby. → bool.
#[pyfunction]
#[pyo3(signature = (points, rows, cols, config, *, min_sine = 0.5))]
fn steep_to_next_ring<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    rows: &Bound<'py, PyAny>,
    cols: &Bound<'py, PyAny>,
    config: &PyCylinderConfig,
    min_sine: f64,
) -> PyResult<Bound<'py, PyArray1<bool>>> {
    per_cell(py, points, rows, cols, config, |points, cylinder, cells| {
        surface::steep_to_next_ring(points, cylinder, cells, min_sine)
    })
}

/// `answer` of the point image `points` (`[H, W, 3]` of `config`'s image) at the cells (`rows[i]`,
/// `cols[i]`), checked and converted as both surface functions take them, off the GIL on one thread.
fn per_cell<'py, T: numpy::Element + Send>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    rows: &Bound<'py, PyAny>,
    cols: &Bound<'py, PyAny>,
    config: &PyCylinderConfig,
    answer: impl FnOnce(&[f32], &CylinderConfig, &[[usize; 2]]) -> crate::Result<Vec<T>> + Send,
) -> PyResult<Bound<'py, PyArray1<T>>> {
    let cylinder = config.inner;
    let points = point_image("points", points, &cylinder)?;
    let cells = image_cells(rows, cols)?;
    let points = points.f32_data();
    let points: &[f32] = &points;
    let values = run(py, Some(1), || answer(points, &cylinder, &cells))?;
    Ok(Array1::from_vec(values).into_pyarray(py))
}

/// The cells `[row, col]` of two equally long integer arrays, or an error naming them.
fn image_cells(rows: &Bound<'_, PyAny>, cols: &Bound<'_, PyAny>) -> PyResult<Vec<[usize; 2]>> {
    let (rows, cols) = (vector_i64("rows", rows)?, vector_i64("cols", cols)?);
    if rows.len() != cols.len() {
        return Err(PyValueError::new_err(format!(
            "rows and cols: {} rows but {} cols",
            rows.len(),
            cols.len()
        )));
    }
    rows.iter()
        .zip(&cols)
        .map(|(&r, &c)| match (usize::try_from(r), usize::try_from(c)) {
            (Ok(r), Ok(c)) => Ok([r, c]),
            _ => Err(PyValueError::new_err(format!(
                "rows and cols: cell ({r}, {c}) is negative"
            ))),
        })
        .collect()
}

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(horizontal_votes, m)?)?;
    m.add_function(wrap_pyfunction!(steep_to_next_ring, m)?)?;
    Ok(())
}
