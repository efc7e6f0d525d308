//! Bindings of the core: projection, ground truth, rigid solve, RANSAC, NMS, match decoding, deskewing.
//!
//! Every function checks dtype, shape and finiteness at the boundary (naming the argument), copies
//! non-contiguous or float64 input where a float32 buffer is needed, releases the GIL around the work,
//! runs rayon work in a pool owned by this module (recreated after `fork()`, never the global pool),
//! and turns any panic into a `RuntimeError`.

use std::borrow::Cow;

use nalgebra::{Isometry3, Matrix4, Point3};
use numpy::ndarray::{Array1, Array2, Array3};
use numpy::{
    Element, IntoPyArray, PyArray1, PyArray2, PyArray3, PyArrayDescrMethods, PyReadonlyArrayDyn,
    PyUntypedArray, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyOverflowError, PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;

use crate::coherence::{self, CoherenceConfig};
use crate::ground_truth;
use crate::matches::{self, DecodeConfig};
use crate::nms;
use crate::projection::{self, CylinderConfig};
use crate::ransac::{self, RansacConfig, Refit};
use crate::ray_noise::{self, RayNoise};
use crate::rigid;

use super::pool::{run, threads};

// ---- plumbing --------------------------------------------------------------------------------------

/// An integer argument as Python gave it, of any size. pyo3's conversions to Rust integers raise an
/// `OverflowError` that does not say which argument it was, for a negative `usize` as for a value beyond
/// 64 bits; so every integer argument of the bindings arrives as an `Int` and becomes what the crate
/// takes through [`count`], [`to_seed`] or [`super::pool::threads`], which refuse a value out of range
/// by name as a `ValueError`. A non-integer (a float) stays pyo3's `TypeError` naming the argument.
#[derive(Debug, Clone)]
pub(crate) enum Int {
    /// A value within 128 bits.
    Fits(i128),
    /// A larger one, kept as its decimal text for the error message.
    Huge { negative: bool, text: String },
}

impl<'a, 'py> FromPyObject<'a, 'py> for Int {
    type Error = PyErr;

    fn extract(obj: Borrowed<'a, 'py, PyAny>) -> PyResult<Self> {
        match obj.extract::<i128>() {
            Ok(value) => Ok(Int::Fits(value)),
            Err(err) if err.is_instance_of::<PyOverflowError>(obj.py()) => Ok(Int::Huge {
                negative: obj.lt(0)?,
                text: obj.str()?.to_string(),
            }),
            Err(err) => Err(err),
        }
    }
}

impl std::fmt::Display for Int {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Int::Fits(value) => write!(f, "{value}"),
            Int::Huge { text, .. } => f.write_str(text),
        }
    }
}

impl Int {
    /// The value when it fits a `T`.
    pub(crate) fn fitting<T: TryFrom<i128>>(&self) -> Option<T> {
        match self {
            Int::Fits(value) => T::try_from(*value).ok(),
            Int::Huge { .. } => None,
        }
    }

    pub(crate) fn is_negative(&self) -> bool {
        match self {
            Int::Fits(value) => *value < 0,
            Int::Huge { negative, .. } => *negative,
        }
    }
}

/// A count or size from Python as a `usize`, refused by name when negative or too large.
pub(super) fn count(name: &str, value: Int) -> PyResult<usize> {
    value.fitting().ok_or_else(|| {
        let limit = if value.is_negative() {
            ">= 0".to_string()
        } else {
            format!("at most {}", usize::MAX)
        };
        PyValueError::new_err(format!("{name}: must be {limit}, got {value}"))
    })
}

/// A sampler seed from Python: any value a `u64` holds.
pub(super) fn to_seed(value: Int) -> PyResult<u64> {
    value.fitting().ok_or_else(|| {
        PyValueError::new_err(format!("seed: must be in 0 ..= 2^64 - 1, got {value}"))
    })
}

/// `#[pyo3(from_py_with = …)]` extractors of the integer arguments that have a literal default: such an
/// argument must stay a plain Rust integer for its default to show in the Python signature, and goes
/// through [`Int`] and [`count`] here under its own name (`from_py_with` takes a function path, which
/// carries no string, hence one function per argument name).
pub(super) mod counts {
    use pyo3::prelude::*;

    use super::{count, to_seed, Int};

    macro_rules! named_counts {
        ($($name:ident),* $(,)?) => {$(
            pub(crate) fn $name(obj: &Bound<'_, PyAny>) -> PyResult<usize> {
                count(stringify!($name), obj.extract::<Int>()?)
            }
        )*};
    }

    named_counts!(
        height,
        width,
        max_iterations,
        refine_iterations,
        radius,
        nms_radius,
        max_scans,
        min_points_per_voxel,
        min_correspondences,
    );

    pub(crate) fn seed(obj: &Bound<'_, PyAny>) -> PyResult<u64> {
        to_seed(obj.extract::<Int>()?)
    }
}

/// A numpy array of floats, whichever width it came in.
pub(super) enum Floats<'py> {
    F32(PyReadonlyArrayDyn<'py, f32>),
    F64(PyReadonlyArrayDyn<'py, f64>),
}

fn as_array<'a, 'py>(
    name: &str,
    obj: &'a Bound<'py, PyAny>,
) -> PyResult<&'a Bound<'py, PyUntypedArray>> {
    obj.cast::<PyUntypedArray>().map_err(|_| {
        let type_name = obj
            .get_type()
            .name()
            .map(|n| n.to_string())
            .unwrap_or_else(|_| "?".into());
        PyTypeError::new_err(format!("{name}: expected a numpy array, got {type_name}"))
    })
}

fn is_dtype<T: Element>(array: &Bound<'_, PyUntypedArray>) -> bool {
    array.dtype().is_equiv_to(&numpy::dtype::<T>(array.py()))
}

fn dtype_name(array: &Bound<'_, PyUntypedArray>) -> String {
    array.dtype().to_string()
}

pub(super) fn floats<'py>(name: &str, obj: &Bound<'py, PyAny>) -> PyResult<Floats<'py>> {
    let array = as_array(name, obj)?;
    if is_dtype::<f32>(array) {
        Ok(Floats::F32(array.extract()?))
    } else if is_dtype::<f64>(array) {
        Ok(Floats::F64(array.extract()?))
    } else {
        Err(PyTypeError::new_err(format!(
            "{name}: expected float32 or float64, got {}",
            dtype_name(array)
        )))
    }
}

impl Floats<'_> {
    pub(super) fn shape(&self) -> &[usize] {
        match self {
            Floats::F32(a) => a.shape(),
            Floats::F64(a) => a.shape(),
        }
    }

    /// Row-major float32 data, borrowed when already contiguous float32.
    pub(super) fn f32_data(&self) -> Cow<'_, [f32]> {
        match self {
            // `as_slice` also accepts Fortran order, whose memory order is not the row-major we need.
            Floats::F32(a) if a.is_c_contiguous() => match a.as_slice() {
                Ok(slice) => Cow::Borrowed(slice),
                Err(_) => Cow::Owned(a.as_array().iter().copied().collect()),
            },
            Floats::F32(a) => Cow::Owned(a.as_array().iter().copied().collect()),
            Floats::F64(a) => Cow::Owned(a.as_array().iter().map(|&v| v as f32).collect()),
        }
    }

    /// Row-major float64 data (always a copy unless contiguous float64).
    fn f64_data(&self) -> Cow<'_, [f64]> {
        match self {
            Floats::F32(a) => Cow::Owned(a.as_array().iter().map(|&v| v as f64).collect()),
            Floats::F64(a) if a.is_c_contiguous() => match a.as_slice() {
                Ok(slice) => Cow::Borrowed(slice),
                Err(_) => Cow::Owned(a.as_array().iter().copied().collect()),
            },
            Floats::F64(a) => Cow::Owned(a.as_array().iter().copied().collect()),
        }
    }
}

pub(super) fn shape_error(name: &str, expected: &str, shape: &[usize]) -> PyErr {
    PyValueError::new_err(format!("{name}: expected shape {expected}, got {shape:?}"))
}

fn check_finite(name: &str, values: &[f64]) -> PyResult<()> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(i) => Err(PyValueError::new_err(format!(
            "{name}: element {i} is not finite ({})",
            values[i]
        ))),
        None => Ok(()),
    }
}

/// An `N×3` float array → points (float64).
fn points3(name: &str, obj: &Bound<'_, PyAny>) -> PyResult<Vec<Point3<f64>>> {
    let array = floats(name, obj)?;
    let shape = array.shape();
    if shape.len() != 2 || shape[1] != 3 {
        return Err(shape_error(name, "(N, 3)", shape));
    }
    let data = array.f64_data();
    check_finite(name, &data)?;
    Ok(data
        .chunks_exact(3)
        .map(|p| Point3::new(p[0], p[1], p[2]))
        .collect())
}

/// An `N×4` or `N×3` scan (x, y, z[, reflectance]) of float32 or float64, and its column count.
fn scan_points<'py>(obj: &Bound<'py, PyAny>) -> PyResult<(Floats<'py>, usize)> {
    let array = floats("points", obj)?;
    let shape = array.shape().to_vec();
    if shape.len() != 2 || !(shape[1] == 3 || shape[1] == 4) {
        return Err(shape_error("points", "(N, 4) or (N, 3)", &shape));
    }
    Ok((array, shape[1]))
}

/// A 1-D float array (any float width) → float64 values, checked finite.
fn vector_f64(name: &str, obj: &Bound<'_, PyAny>) -> PyResult<Vec<f64>> {
    let array = floats(name, obj)?;
    if array.shape().len() != 1 {
        return Err(shape_error(name, "(N,)", array.shape()));
    }
    let data = array.f64_data().into_owned();
    check_finite(name, &data)?;
    Ok(data)
}

/// A 1-D integer array (int32 or int64) → i64 values.
pub(super) fn vector_i64(name: &str, obj: &Bound<'_, PyAny>) -> PyResult<Vec<i64>> {
    let array = as_array(name, obj)?;
    if array.ndim() != 1 {
        return Err(shape_error(name, "(N,)", array.shape()));
    }
    if is_dtype::<i64>(array) {
        let a: PyReadonlyArrayDyn<'_, i64> = array.extract()?;
        Ok(a.as_array().iter().copied().collect())
    } else if is_dtype::<i32>(array) {
        let a: PyReadonlyArrayDyn<'_, i32> = array.extract()?;
        Ok(a.as_array().iter().map(|&v| v as i64).collect())
    } else {
        Err(PyTypeError::new_err(format!(
            "{name}: expected int32 or int64, got {}",
            dtype_name(array)
        )))
    }
}

/// A `height × width` float image (float32, or float64 to be converted by `f32_data`).
fn image<'py>(
    name: &str,
    obj: &Bound<'py, PyAny>,
    config: &CylinderConfig,
) -> PyResult<Floats<'py>> {
    let array = floats(name, obj)?;
    let shape = array.shape();
    if shape != [config.height, config.width] {
        return Err(shape_error(
            name,
            &format!("({}, {}) (the config's image)", config.height, config.width),
            shape,
        ));
    }
    Ok(array)
}

/// A `2 × height × width` flow (Δrow, Δcol) over the config's image.
fn flow_image<'py>(obj: &Bound<'py, PyAny>, config: &CylinderConfig) -> PyResult<Floats<'py>> {
    let flow = floats("flow", obj)?;
    let (h, w) = (config.height, config.width);
    if flow.shape() != [2, h, w] {
        return Err(shape_error("flow", &format!("(2, {h}, {w})"), flow.shape()));
    }
    Ok(flow)
}

/// A 4×4 rigid transform (float64 or float32), checked to be one.
fn transform(name: &'static str, obj: &Bound<'_, PyAny>) -> PyResult<Isometry3<f64>> {
    let array = floats(name, obj)?;
    if array.shape() != [4, 4] {
        return Err(shape_error(name, "(4, 4)", array.shape()));
    }
    let data = array.f64_data();
    let matrix = Matrix4::from_row_slice(&data);
    Ok(rigid::isometry_from_matrix(&matrix, name)?)
}

fn matrix_to_numpy<'py>(py: Python<'py>, isometry: &Isometry3<f64>) -> Bound<'py, PyArray2<f64>> {
    let m = isometry.to_homogeneous();
    Array2::from_shape_fn((4, 4), |(i, j)| m[(i, j)]).into_pyarray(py)
}

fn points_to_numpy<'py>(py: Python<'py>, points: &[Point3<f64>]) -> Bound<'py, PyArray2<f64>> {
    Array2::from_shape_fn((points.len(), 3), |(i, j)| points[i][j]).into_pyarray(py)
}

/// A `(2, height, width)` flow (Δrow plane, then Δcol) the crate returned as a flat vector.
pub(super) fn flow_array(height: usize, width: usize, values: Vec<f32>) -> PyResult<Array3<f32>> {
    Array3::from_shape_vec((2, height, width), values)
        .map_err(|e| PyRuntimeError::new_err(format!("internal error in dmlo_rs: {e}")))
}

/// A row-major `height × width` image (or any 2-D array, e.g. N points × columns) the crate returned as a
/// flat vector.
pub(super) fn image_array<T>(height: usize, width: usize, values: Vec<T>) -> PyResult<Array2<T>> {
    Array2::from_shape_vec((height, width), values)
        .map_err(|e| PyRuntimeError::new_err(format!("internal error in dmlo_rs: {e}")))
}

// ---- CylinderConfig --------------------------------------------------------------------------------

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

// ---- rigid solve and RANSAC ------------------------------------------------------------------------

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
fn refit_kind(refit: &str, range_ratio: f64, bearing_threshold_deg: f64) -> PyResult<Refit> {
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

// ---- NMS and match decoding ------------------------------------------------------------------------

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
    let (h, w) = (cylinder.height, cylinder.width);
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
    let mask = match mask {
        None => None,
        Some(obj) => {
            let array = as_array("mask", obj)?;
            if !is_dtype::<bool>(array) {
                return Err(PyTypeError::new_err(format!(
                    "mask: expected bool, got {}",
                    dtype_name(array)
                )));
            }
            if array.shape() != [h, w] {
                return Err(shape_error("mask", &format!("({h}, {w})"), array.shape()));
            }
            let a: PyReadonlyArrayDyn<'_, bool> = array.extract()?;
            Some(a.as_array().iter().copied().collect::<Vec<bool>>())
        }
    };
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

// ---- deskewing -------------------------------------------------------------------------------------

/// Sweep times of `points` (N×4 or N×3) from their azimuth: fractions of a sweep period, 0 at the
/// moment the sensor looks at `reference_azimuth_deg` (x forward = 0), e.g. −0.25 for a point 90°
/// counter-clockwise of it on a `clockwise` sensor (KITTI's HDL-64E). A non-finite point gets 0.
#[pyfunction]
#[pyo3(signature = (points, *, clockwise = true, reference_azimuth_deg = 0.0, num_threads = None))]
fn sweep_times<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    clockwise: bool,
    reference_azimuth_deg: f64,
    num_threads: Option<Int>,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    let (array, columns) = scan_points(points)?;
    let data = array.f32_data();
    let data_ref: &[f32] = &data;
    let pattern = crate::deskew::SweepPattern {
        clockwise,
        reference_azimuth_deg,
    };
    let times = run(py, threads(num_threads)?, || {
        crate::deskew::sweep_times(data_ref, columns, &pattern)
    })?;
    Ok(Array1::from_vec(times).into_pyarray(py))
}

/// Motion compensation: `points` (N×4 or N×3; reflectance copied) moved from the sensor frame of the
/// moment each was measured into that of the sweep's reference moment, as float32.
///
/// `motion` (4×4) is the sensor's motion over one sweep period, `T_reference_next` (the inverse of the
/// odometry's `T_tgt_ref`); `times` (N) are the points' sweep times in periods, 0 at the reference, or
/// None to take them from the azimuth (`sweep_times` with the same pattern). Between the reference and
/// time s the sensor turns by s times the motion's rotation vector and moves by s times its translation.
#[pyfunction]
#[pyo3(signature = (points, motion, times = None, *, clockwise = true, reference_azimuth_deg = 0.0,
                    num_threads = None))]
#[allow(clippy::too_many_arguments)]
fn deskew<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    motion: &Bound<'py, PyAny>,
    times: Option<&Bound<'py, PyAny>>,
    clockwise: bool,
    reference_azimuth_deg: f64,
    num_threads: Option<Int>,
) -> PyResult<Bound<'py, PyArray2<f32>>> {
    let (array, columns) = scan_points(points)?;
    let motion = transform("motion", motion)?;
    let times = times.map(|t| vector_f64("times", t)).transpose()?;
    let data = array.f32_data();
    let data_ref: &[f32] = &data;
    let pattern = crate::deskew::SweepPattern {
        clockwise,
        reference_azimuth_deg,
    };
    let moved = run(py, threads(num_threads)?, || {
        let derived;
        let times = match &times {
            Some(times) => times.as_slice(),
            None => {
                derived = crate::deskew::sweep_times(data_ref, columns, &pattern)?;
                derived.as_slice()
            }
        };
        crate::deskew::deskew(data_ref, columns, times, &motion)
    })?;
    Ok(image_array(moved.len() / columns, columns, moved)?.into_pyarray(py))
}

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyCylinderConfig>()?;
    m.add_class::<PyProjection>()?;
    m.add_class::<PyRansacResult>()?;
    m.add_class::<PyRayRefit>()?;
    m.add_class::<PyMatches>()?;
    m.add_function(wrap_pyfunction!(project, m)?)?;
    m.add_function(wrap_pyfunction!(unproject, m)?)?;
    m.add_function(wrap_pyfunction!(ground_truth_flow, m)?)?;
    m.add_function(wrap_pyfunction!(rigid_transform, m)?)?;
    m.add_function(wrap_pyfunction!(ransac_rigid, m)?)?;
    m.add_function(wrap_pyfunction!(ray_noise_refit, m)?)?;
    m.add_function(wrap_pyfunction!(refit_rigid, m)?)?;
    m.add_function(wrap_pyfunction!(non_maximum_suppression, m)?)?;
    m.add_function(wrap_pyfunction!(decode_matches, m)?)?;
    m.add_function(wrap_pyfunction!(coherent_confidence, m)?)?;
    m.add_function(wrap_pyfunction!(sweep_times, m)?)?;
    m.add_function(wrap_pyfunction!(deskew, m)?)?;
    m.add("MAX_COHERENCE_RADIUS", coherence::MAX_RADIUS)?;
    Ok(())
}
