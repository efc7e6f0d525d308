//! Bindings of NMS (§III-D-a), match decoding (§III-D) and the coherence of a match with its
//! neighbours.

use numpy::ndarray::{Array1, Array2};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::coherence::{self, CoherenceConfig};
use crate::matches::{self, DecodeConfig};
use crate::nms;

use super::convert::{
    bool_image, count, counts, floats, flow_image, image, image_array, points_to_numpy,
    shape_error, vector_i64, Int,
};
use super::pool::{run, threads};
use super::projection::PyCylinderConfig;

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyMatches>()?;
    m.add_function(wrap_pyfunction!(non_maximum_suppression, m)?)?;
    m.add_function(wrap_pyfunction!(decode_matches, m)?)?;
    m.add_function(wrap_pyfunction!(coherent_confidence, m)?)?;
    m.add("MAX_COHERENCE_RADIUS", coherence::MAX_RADIUS)?;
    Ok(())
}

/// Greedy NMS on the cylinder grid: keeps the highest `scores` first and suppresses every other entry
/// within `radius` cells (square window); at most `top_n` (None = all). With `config` (the image the
/// cells belong to) the cells are checked to lie in it, and when it covers 360° the columns wrap, so
/// entries either side of the azimuth seam suppress each other. → kept indices (int64), best first.
#[pyfunction]
#[pyo3(name = "nms", signature = (rows, cols, scores, radius = 1, top_n = None, *, config = None))]
fn non_maximum_suppression<'py>(
    py: Python<'py>,
    rows: &Bound<'py, PyAny>,
    cols: &Bound<'py, PyAny>,
    scores: &Bound<'py, PyAny>,
    #[pyo3(from_py_with = counts::radius)] radius: usize,
    top_n: Option<Int>,
    config: Option<&PyCylinderConfig>,
) -> PyResult<Bound<'py, PyArray1<i64>>> {
    let top_n = top_n.map(|n| count("top_n", n)).transpose()?;
    let (rows, cols) = (vector_i64("rows", rows)?, vector_i64("cols", cols)?);
    let array = floats("scores", scores)?;
    if array.shape().len() != 1 {
        return Err(shape_error("scores", "(N,)", array.shape()));
    }
    let scores = array.f32_data().into_owned();
    let column_period = match config {
        None => None,
        Some(config) => {
            let config = config.inner;
            for (name, values, limit) in [
                ("rows", &rows, config.height),
                ("cols", &cols, config.width),
            ] {
                if let Some(i) = values.iter().position(|&v| v >= limit as i64) {
                    return Err(PyValueError::new_err(format!(
                        "{name}: element {i} ({}) is outside the config's {} x {} image",
                        values[i], config.height, config.width
                    )));
                }
            }
            config.column_period()
        }
    };
    let kept = run(py, Some(1), || {
        nms::nms_wrapping(&rows, &cols, &scores, radius, top_n, column_period)
    })?;
    Ok(Array1::from_iter(kept.into_iter().map(|i| i as i64)).into_pyarray(py))
}

/// 3D matches decoded from the network's output; all arrays have one entry per match.
#[pyclass(name = "Matches", module = "dmlo_rs._dmlo_rs", frozen)]
pub struct PyMatches {
    /// N×3 float64 virtual reference points p'_r (cell centres).
    #[pyo3(get)]
    source: Py<PyArray2<f64>>,
    /// N×3 float64 predicted target points p̂_t.
    #[pyo3(get)]
    target: Py<PyArray2<f64>>,
    /// N float32 confidences.
    #[pyo3(get)]
    confidence: Py<PyArray1<f32>>,
    /// N×2 int64 reference cells (row, col).
    #[pyo3(get)]
    cells: Py<PyArray2<i64>>,
}

#[pymethods]
impl PyMatches {
    fn __len__(&self, py: Python<'_>) -> usize {
        self.confidence.bind(py).len()
    }

    fn __repr__(&self, py: Python<'_>) -> String {
        format!("Matches(n={})", self.__len__(py))
    }
}

/// Network output → 3D matches: `flow[2, H, W]` (Δrow, Δcol) and `confidence[H, W]` with both range
/// images; cells below `min_confidence`, without range, or where `mask` (H×W bool, True = exclude, e.g.
/// moving objects) is set are dropped. With `top_n`, NMS (`nms_radius`) is fused in: only the kept
/// matches are decoded, best first — the same result as `nms(..., config=config)` on the full output
/// (wrapping round the azimuth seam when the image covers 360°), much faster.
#[pyfunction]
#[pyo3(signature = (ref_range, tgt_range, flow, confidence, config, min_confidence = 0.0, mask = None, *,
                    max_relative_range_spread = 0.1, top_n = None, nms_radius = 1, num_threads = None))]
#[allow(clippy::too_many_arguments)]
fn decode_matches(
    py: Python<'_>,
    ref_range: &Bound<'_, PyAny>,
    tgt_range: &Bound<'_, PyAny>,
    flow: &Bound<'_, PyAny>,
    confidence: &Bound<'_, PyAny>,
    config: &PyCylinderConfig,
    min_confidence: f32,
    mask: Option<&Bound<'_, PyAny>>,
    max_relative_range_spread: f32,
    top_n: Option<Int>,
    #[pyo3(from_py_with = counts::nms_radius)] nms_radius: usize,
    num_threads: Option<Int>,
) -> PyResult<PyMatches> {
    let top_n = top_n.map(|n| count("top_n", n)).transpose()?;
    let cylinder = config.inner;
    let reference = image("ref_range", ref_range, &cylinder)?;
    let target = image("tgt_range", tgt_range, &cylinder)?;
    let confidence = image("confidence", confidence, &cylinder)?;
    let flow = flow_image(flow, &cylinder)?;
    let (reference, target, confidence, flow) = (
        reference.f32_data(),
        target.f32_data(),
        confidence.f32_data(),
        flow.f32_data(),
    );
    let (reference, target, confidence, flow): (&[f32], &[f32], &[f32], &[f32]) =
        (&reference, &target, &confidence, &flow);
    let mask = mask
        .map(|obj| bool_image("mask", obj, &cylinder))
        .transpose()?;
    let decode = DecodeConfig {
        min_confidence,
        max_relative_range_spread,
    };
    let mask = mask.as_deref();
    let decoded = run(py, threads(num_threads)?, || match top_n {
        None => matches::decode_matches(
            reference, target, flow, confidence, mask, &cylinder, &decode,
        ),
        Some(top_n) => matches::select_matches(
            reference, target, flow, confidence, mask, &cylinder, &decode, nms_radius, top_n,
        ),
    })?;
    let cells = Array2::from_shape_fn((decoded.cells.len(), 2), |(i, j)| {
        decoded.cells[i][j] as i64
    });
    Ok(PyMatches {
        source: points_to_numpy(py, &decoded.source).unbind(),
        target: points_to_numpy(py, &decoded.target).unbind(),
        confidence: Array1::from_vec(decoded.confidence)
            .into_pyarray(py)
            .unbind(),
        cells: cells.into_pyarray(py).unbind(),
    })
}

/// The confidence `[H, W]` weighted by flow coherence (beyond the paper): each cell's times
/// `exp(−d / scale_px)`, `d` the pixel distance of its flow from the separable median flow of the
/// `(2·radius+1)²` cells around it (per component, the median down each window column over the cells with
/// a range in `ref_range`, then the median of those across the columns; they wrap on a 360° image).
/// Cells without a range or with a non-finite flow get 0; `radius` ≤ `MAX_COHERENCE_RADIUS` (15).
/// → float32 `[H, W]`.
#[pyfunction]
#[pyo3(signature = (flow, confidence, ref_range, config, *, radius = 2, scale_px = 0.5, num_threads = None))]
#[allow(clippy::too_many_arguments)]
fn coherent_confidence<'py>(
    py: Python<'py>,
    flow: &Bound<'py, PyAny>,
    confidence: &Bound<'py, PyAny>,
    ref_range: &Bound<'py, PyAny>,
    config: &PyCylinderConfig,
    #[pyo3(from_py_with = counts::radius)] radius: usize,
    scale_px: f32,
    num_threads: Option<Int>,
) -> PyResult<Bound<'py, PyArray2<f32>>> {
    let cylinder = config.inner;
    let (h, w) = (cylinder.height, cylinder.width);
    let reference = image("ref_range", ref_range, &cylinder)?;
    let confidence = image("confidence", confidence, &cylinder)?;
    let flow = flow_image(flow, &cylinder)?;
    let (reference, confidence, flow) =
        (reference.f32_data(), confidence.f32_data(), flow.f32_data());
    let (reference, confidence, flow): (&[f32], &[f32], &[f32]) = (&reference, &confidence, &flow);
    let settings = CoherenceConfig { radius, scale_px };
    let weighted = run(py, threads(num_threads)?, || {
        coherence::coherent_confidence(flow, confidence, reference, &cylinder, &settings)
    })?;
    Ok(image_array(h, w, weighted)?.into_pyarray(py))
}
