//! Bindings of the cylinder projection (Eq. 1, 4) and of the ground-truth flow (Eq. 5–8).

use numpy::{IntoPyArray, PyArray2, PyArray3, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::ground_truth;
use crate::projection::{self, CylinderConfig};

use super::convert::{
    counts, flow_array, image, image_array, points_to_numpy, scan_points, transform, vector_f64,
    Int,
};
use super::pool::{run, threads};

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyCylinderConfig>()?;
    m.add_class::<PyProjection>()?;
    m.add_function(wrap_pyfunction!(project, m)?)?;
    m.add_function(wrap_pyfunction!(unproject, m)?)?;
    m.add_function(wrap_pyfunction!(point_cells, m)?)?;
    m.add_function(wrap_pyfunction!(ground_truth_flow, m)?)?;
    Ok(())
}

/// Geometry of a cylinder image (angles in degrees); see the Rust docs of `CylinderConfig`.
#[pyclass(name = "CylinderConfig", module = "dmlo_rs._dmlo_rs", frozen, eq)]
#[derive(Clone, PartialEq)]
pub struct PyCylinderConfig {
    pub(crate) inner: CylinderConfig,
}

#[pymethods]
impl PyCylinderConfig {
    #[new]
    #[pyo3(signature = (*, fov_up_deg = 2.0, fov_down_deg = -24.9, vertical_resolution_deg = 0.4,
                        horizontal_resolution_deg = 0.2, height = 64, width = 1792))]
    fn new(
        fov_up_deg: f64,
        fov_down_deg: f64,
        vertical_resolution_deg: f64,
        horizontal_resolution_deg: f64,
        #[pyo3(from_py_with = counts::height)] height: usize,
        #[pyo3(from_py_with = counts::width)] width: usize,
    ) -> PyResult<Self> {
        let inner = CylinderConfig {
            fov_up_deg,
            fov_down_deg,
            vertical_resolution_deg,
            horizontal_resolution_deg,
            height,
            width,
        };
        inner.validate()?;
        Ok(PyCylinderConfig { inner })
    }

    /// The paper's KITTI HDL-64E setting: 0.4° × 0.2°, full 68 × 1801, centre crop 64 × 1792.
    #[staticmethod]
    fn kitti() -> Self {
        PyCylinderConfig {
            inner: CylinderConfig::kitti(),
        }
    }

    /// The paper's Argoverse setting: 0.3° within −5°…+15°, 0.2° horizontal, 64 × 1792.
    #[staticmethod]
    fn argoverse() -> Self {
        PyCylinderConfig {
            inner: CylinderConfig::argoverse(),
        }
    }

    #[getter]
    fn fov_up_deg(&self) -> f64 {
        self.inner.fov_up_deg
    }
    #[getter]
    fn fov_down_deg(&self) -> f64 {
        self.inner.fov_down_deg
    }
    #[getter]
    fn vertical_resolution_deg(&self) -> f64 {
        self.inner.vertical_resolution_deg
    }
    #[getter]
    fn horizontal_resolution_deg(&self) -> f64 {
        self.inner.horizontal_resolution_deg
    }
    #[getter]
    fn height(&self) -> usize {
        self.inner.height
    }
    #[getter]
    fn width(&self) -> usize {
        self.inner.width
    }
    #[getter]
    fn full_height(&self) -> usize {
        self.inner.full_height()
    }
    #[getter]
    fn full_width(&self) -> usize {
        self.inner.full_width()
    }
    #[getter]
    fn crop_top(&self) -> usize {
        self.inner.crop_top()
    }
    #[getter]
    fn crop_left(&self) -> usize {
        self.inner.crop_left()
    }
    /// The (cropped) row whose centre has elevation 0°.
    #[getter]
    fn row_of_zero_elevation(&self) -> f64 {
        self.inner.row_of_zero_elevation()
    }
    /// The (cropped) column whose centre has azimuth 0° (+x).
    #[getter]
    fn col_of_zero_azimuth(&self) -> f64 {
        self.inner.col_of_zero_azimuth()
    }
    /// True when the image covers all 360° of azimuth (columns wrap).
    #[getter]
    fn wraps_azimuth(&self) -> bool {
        self.inner.wraps_azimuth()
    }

    fn __repr__(&self) -> String {
        let c = &self.inner;
        format!(
            "CylinderConfig(fov_up_deg={:?}, fov_down_deg={:?}, vertical_resolution_deg={:?}, \
             horizontal_resolution_deg={:?}, height={}, width={})",
            c.fov_up_deg,
            c.fov_down_deg,
            c.vertical_resolution_deg,
            c.horizontal_resolution_deg,
            c.height,
            c.width
        )
    }

    /// Pickling (e.g. into spawned DataLoader workers) re-creates the config from its keywords.
    fn __getnewargs_ex__<'py>(
        &self,
        py: Python<'py>,
    ) -> PyResult<(
        Bound<'py, pyo3::types::PyTuple>,
        Bound<'py, pyo3::types::PyDict>,
    )> {
        let c = &self.inner;
        let kwargs = pyo3::types::PyDict::new(py);
        kwargs.set_item("fov_up_deg", c.fov_up_deg)?;
        kwargs.set_item("fov_down_deg", c.fov_down_deg)?;
        kwargs.set_item("vertical_resolution_deg", c.vertical_resolution_deg)?;
        kwargs.set_item("horizontal_resolution_deg", c.horizontal_resolution_deg)?;
        kwargs.set_item("height", c.height)?;
        kwargs.set_item("width", c.width)?;
        Ok((pyo3::types::PyTuple::empty(py), kwargs))
    }
}

// ---- projection ------------------------------------------------------------------------------------

/// A scan's cylinder image: `range`, `reflectance` (H×W float32, 0 = empty), `index` (H×W int64 index
/// of the kept point, −1 = empty), and counts of dropped points.
#[pyclass(name = "Projection", module = "dmlo_rs._dmlo_rs", frozen)]
pub struct PyProjection {
    #[pyo3(get)]
    range: Py<PyArray2<f32>>,
    #[pyo3(get)]
    reflectance: Py<PyArray2<f32>>,
    #[pyo3(get)]
    index: Py<PyArray2<i64>>,
    #[pyo3(get)]
    num_non_finite: usize,
    #[pyo3(get)]
    num_out_of_view: usize,
}

#[pymethods]
impl PyProjection {
    fn __repr__(&self, py: Python<'_>) -> String {
        let shape = self.range.bind(py).shape().to_vec();
        format!(
            "Projection(shape={:?}, num_non_finite={}, num_out_of_view={})",
            shape, self.num_non_finite, self.num_out_of_view
        )
    }
}

/// Φ (Eq. 1): `points` N×4 (x, y, z, reflectance) or N×3, float32 (float64 is converted) → Projection.
#[pyfunction]
#[pyo3(signature = (points, config, *, num_threads = None))]
fn project(
    py: Python<'_>,
    points: &Bound<'_, PyAny>,
    config: &PyCylinderConfig,
    num_threads: Option<Int>,
) -> PyResult<PyProjection> {
    let (array, columns) = scan_points(points)?;
    let data = array.f32_data();
    let config = config.inner;
    let data_ref: &[f32] = &data;
    let image = run(py, threads(num_threads)?, || {
        projection::project_flat(data_ref, columns, &config)
    })?;
    let (h, w) = (image.height, image.width);
    Ok(PyProjection {
        range: image_array(h, w, image.range)?.into_pyarray(py).unbind(),
        reflectance: image_array(h, w, image.reflectance)?
            .into_pyarray(py)
            .unbind(),
        index: image_array(h, w, image.index)?.into_pyarray(py).unbind(),
        num_non_finite: image.num_non_finite,
        num_out_of_view: image.num_out_of_view,
    })
}

/// Φ⁻¹ (Eq. 4): continuous `rows`, `cols` (cropped-image coordinates) and `ranges` (metres), 1-D
/// float arrays of equal length → N×3 float64 points.
#[pyfunction]
fn unproject<'py>(
    py: Python<'py>,
    rows: &Bound<'py, PyAny>,
    cols: &Bound<'py, PyAny>,
    ranges: &Bound<'py, PyAny>,
    config: &PyCylinderConfig,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let (rows, cols, ranges) = (
        vector_f64("rows", rows)?,
        vector_f64("cols", cols)?,
        vector_f64("ranges", ranges)?,
    );
    let config = config.inner;
    let points = run(py, Some(1), || {
        projection::unproject_many(&rows, &cols, &ranges, &config)
    })?;
    Ok(points_to_numpy(py, &points))
}

/// Ground-truth flow (Eq. 5–8) → `(flow[2, H, W] float32 (Δrow, Δcol), valid[H, W] bool)`.
#[pyfunction]
#[pyo3(signature = (ref_range, tgt_range, T_tgt_ref, config, max_range_error = 0.1, *, num_threads = None))]
#[allow(non_snake_case, clippy::type_complexity)]
fn ground_truth_flow<'py>(
    py: Python<'py>,
    ref_range: &Bound<'py, PyAny>,
    tgt_range: &Bound<'py, PyAny>,
    T_tgt_ref: &Bound<'py, PyAny>,
    config: &PyCylinderConfig,
    max_range_error: f64,
    num_threads: Option<Int>,
) -> PyResult<(Bound<'py, PyArray3<f32>>, Bound<'py, PyArray2<bool>>)> {
    let config = config.inner;
    let (reference, target) = (
        image("ref_range", ref_range, &config)?,
        image("tgt_range", tgt_range, &config)?,
    );
    let (reference, target) = (reference.f32_data(), target.f32_data());
    let (reference, target): (&[f32], &[f32]) = (&reference, &target);
    let motion = transform("T_tgt_ref", T_tgt_ref)?;
    let gt = run(py, threads(num_threads)?, || {
        ground_truth::ground_truth_flow(reference, target, &motion, &config, max_range_error)
    })?;
    let (h, w) = (gt.height, gt.width);
    let flow = flow_array(h, w, gt.flow)?;
    let valid = image_array(h, w, gt.valid)?;
    Ok((flow.into_pyarray(py), valid.into_pyarray(py)))
}

/// Each point's flat cell index (`row · width + col`) in `config`'s image, by the rule `project` uses;
/// −1 outside the image, at the origin or non-finite. `points` as for `project` → int64 array of N.
#[pyfunction]
#[pyo3(signature = (points, config, *, num_threads = None))]
fn point_cells<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    config: &PyCylinderConfig,
    num_threads: Option<Int>,
) -> PyResult<Bound<'py, numpy::PyArray1<i64>>> {
    let (array, columns) = scan_points(points)?;
    let data = array.f32_data();
    let config = config.inner;
    let data_ref: &[f32] = &data;
    let cells = run(py, threads(num_threads)?, || {
        projection::point_cells(data_ref, columns, &config)
    })?;
    Ok(cells.into_pyarray(py))
}
