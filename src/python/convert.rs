//! Plumbing of the bindings: integer arguments of any size, numpy arrays in (dtype, shape,
//! finiteness and contiguity checked, named) and out.

use std::borrow::Cow;

use nalgebra::{Isometry3, Matrix4, Point3};
use numpy::ndarray::{Array2, Array3};
use numpy::{
    Element, IntoPyArray, PyArray2, PyArrayDescrMethods, PyReadonlyArrayDyn, PyUntypedArray,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyOverflowError, PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;

use crate::projection::CylinderConfig;
use crate::rigid;

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
        coherence_radius,
        nms_radius,
        max_matches,
        max_scans,
        min_points_per_voxel,
        min_correspondences,
        frames,
        gap,
        min_inliers,
        num_inliers,
        prediction_horizon,
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

pub(super) fn as_array<'a, 'py>(
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

pub(super) fn is_dtype<T: Element>(array: &Bound<'_, PyUntypedArray>) -> bool {
    array.dtype().is_equiv_to(&numpy::dtype::<T>(array.py()))
}

pub(super) fn dtype_name(array: &Bound<'_, PyUntypedArray>) -> String {
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

/// A point image of `cylinder` (`[H, W, 3]` floats, each cell's kept point, NaN where empty).
pub(super) fn point_image<'py>(
    name: &str,
    obj: &Bound<'py, PyAny>,
    cylinder: &CylinderConfig,
) -> PyResult<Floats<'py>> {
    config_image(name, obj, cylinder, &[3])
}

/// A float array shaped as `config`'s image, `[H, W]` followed by `per_cell` (e.g. `[3]` for a point a cell).
fn config_image<'py>(
    name: &str,
    obj: &Bound<'py, PyAny>,
    config: &CylinderConfig,
    per_cell: &[usize],
) -> PyResult<Floats<'py>> {
    let array = floats(name, obj)?;
    let expected: Vec<usize> = [config.height, config.width]
        .iter()
        .chain(per_cell)
        .copied()
        .collect();
    if array.shape() != expected.as_slice() {
        let dims: Vec<String> = expected.iter().map(usize::to_string).collect();
        let expected = format!("({}) (the config's image)", dims.join(", "));
        return Err(shape_error(name, &expected, array.shape()));
    }
    Ok(array)
}

pub(super) fn shape_error(name: &str, expected: &str, shape: &[usize]) -> PyErr {
    PyValueError::new_err(format!("{name}: expected shape {expected}, got {shape:?}"))
}

pub(super) fn check_finite(name: &str, values: &[f64]) -> PyResult<()> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(i) => Err(PyValueError::new_err(format!(
            "{name}: element {i} is not finite ({})",
            values[i]
        ))),
        None => Ok(()),
    }
}

/// An `N×3` float array → points (float64).
pub(super) fn points3(name: &str, obj: &Bound<'_, PyAny>) -> PyResult<Vec<Point3<f64>>> {
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
pub(super) fn scan_points<'py>(obj: &Bound<'py, PyAny>) -> PyResult<(Floats<'py>, usize)> {
    named_scan_points("points", obj)
}

/// [`scan_points`] of the argument `name`.
pub(super) fn named_scan_points<'py>(
    name: &str,
    obj: &Bound<'py, PyAny>,
) -> PyResult<(Floats<'py>, usize)> {
    let array = floats(name, obj)?;
    let shape = array.shape().to_vec();
    if shape.len() != 2 || !(shape[1] == 3 || shape[1] == 4) {
        return Err(shape_error(name, "(N, 4) or (N, 3)", &shape));
    }
    Ok((array, shape[1]))
}

/// A 1-D float array (any float width) → float64 values, checked finite.
pub(super) fn vector_f64(name: &str, obj: &Bound<'_, PyAny>) -> PyResult<Vec<f64>> {
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
pub(super) fn image<'py>(
    name: &str,
    obj: &Bound<'py, PyAny>,
    config: &CylinderConfig,
) -> PyResult<Floats<'py>> {
    config_image(name, obj, config, &[])
}

/// A boolean `height × width` image over the config's image (a mask of cells), as a row-major vector.
pub(super) fn bool_image(
    name: &str,
    obj: &Bound<'_, PyAny>,
    config: &CylinderConfig,
) -> PyResult<Vec<bool>> {
    let array = as_array(name, obj)?;
    if !is_dtype::<bool>(array) {
        return Err(PyTypeError::new_err(format!(
            "{name}: expected bool, got {}",
            dtype_name(array)
        )));
    }
    let (h, w) = (config.height, config.width);
    if array.shape() != [h, w] {
        return Err(shape_error(name, &format!("({h}, {w})"), array.shape()));
    }
    let values: PyReadonlyArrayDyn<'_, bool> = array.extract()?;
    Ok(values.as_array().iter().copied().collect())
}

/// A `2 × height × width` flow (Δrow, Δcol) over the config's image.
pub(super) fn flow_image<'py>(
    obj: &Bound<'py, PyAny>,
    config: &CylinderConfig,
) -> PyResult<Floats<'py>> {
    let flow = floats("flow", obj)?;
    let (h, w) = (config.height, config.width);
    if flow.shape() != [2, h, w] {
        return Err(shape_error("flow", &format!("(2, {h}, {w})"), flow.shape()));
    }
    Ok(flow)
}

/// A 4×4 rigid transform (float64 or float32), checked to be one.
pub(super) fn transform(name: &'static str, obj: &Bound<'_, PyAny>) -> PyResult<Isometry3<f64>> {
    let array = floats(name, obj)?;
    if array.shape() != [4, 4] {
        return Err(shape_error(name, "(4, 4)", array.shape()));
    }
    let data = array.f64_data();
    let matrix = Matrix4::from_row_slice(&data);
    Ok(rigid::isometry_from_matrix(&matrix, name)?)
}

/// A 4×4 rigid transform from Python as the matrix given (checked as [`transform`] does).
pub(super) fn rigid_matrix(name: &'static str, obj: &Bound<'_, PyAny>) -> PyResult<Matrix4<f64>> {
    let array = floats(name, obj)?;
    if array.shape() != [4, 4] {
        return Err(shape_error(name, "(4, 4)", array.shape()));
    }
    let matrix = Matrix4::from_row_slice(&array.f64_data());
    rigid::isometry_from_matrix(&matrix, name)?;
    Ok(matrix)
}

/// A 4×4 matrix as a float64 numpy array.
pub(super) fn matrix4_to_numpy<'py>(
    py: Python<'py>,
    m: &Matrix4<f64>,
) -> Bound<'py, PyArray2<f64>> {
    Array2::from_shape_fn((4, 4), |(i, j)| m[(i, j)]).into_pyarray(py)
}

pub(super) fn matrix_to_numpy<'py>(
    py: Python<'py>,
    isometry: &Isometry3<f64>,
) -> Bound<'py, PyArray2<f64>> {
    let m = isometry.to_homogeneous();
    Array2::from_shape_fn((4, 4), |(i, j)| m[(i, j)]).into_pyarray(py)
}

pub(super) fn points_to_numpy<'py>(
    py: Python<'py>,
    points: &[Point3<f64>],
) -> Bound<'py, PyArray2<f64>> {
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
