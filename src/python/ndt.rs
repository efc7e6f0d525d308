//! Bindings of the scan-to-map NDT: `NdtMap` (the local submap, `insert` / `align`) and `NdtResult`.
//!
//! Points come in as `N×3` or `N×4` float32/float64 arrays (any strides; a 4th column is ignored),
//! transforms as 4×4 arrays. Work runs without the GIL in a rayon pool owned by this module and
//! rebuilt after `fork()`; crate errors become `ValueError`, panics `RuntimeError`.

use nalgebra::{Matrix4, Point3};
use numpy::ndarray::{Array2, ArrayView2};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyReadonlyArray2, PyUntypedArray, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;

use super::convert::{counts, Int};

use crate::ndt::{
    isometry_from_matrix4, NdtAlignConfig, NdtMap, NdtMapConfig, NdtResult, NeighbourSearch,
};

use super::pool::{run, threads};

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyNdtMap>()?;
    m.add_class::<PyNdtResult>()?;
    Ok(())
}

// ---- plumbing --------------------------------------------------------------------------------------

/// Describes what was passed, for error messages.
fn describe(value: &Bound<'_, PyAny>) -> String {
    match value.cast::<PyUntypedArray>() {
        Ok(array) => format!("a {} array of shape {:?}", array.dtype(), array.shape()),
        Err(_) => value
            .get_type()
            .name()
            .map_or_else(|_| "?".into(), |n| n.to_string()),
    }
}

/// Reads a float32 or float64 2-D array as rows of f64.
fn read_rows(value: &Bound<'_, PyAny>, argument: &str) -> PyResult<Array2<f64>> {
    if let Ok(array) = value.extract::<PyReadonlyArray2<'_, f64>>() {
        return Ok(array.as_array().to_owned());
    }
    if let Ok(array) = value.extract::<PyReadonlyArray2<'_, f32>>() {
        return Ok(array.as_array().mapv(f64::from));
    }
    Err(PyTypeError::new_err(format!(
        "{argument}: expected a 2-D float32 or float64 numpy array, got {}",
        describe(value)
    )))
}

/// An `N×3` or `N×4` array as points (the 4th column, reflectance, is ignored), read in one pass.
pub(super) fn read_points(value: &Bound<'_, PyAny>, argument: &str) -> PyResult<Vec<Point3<f64>>> {
    if let Ok(array) = value.extract::<PyReadonlyArray2<'_, f64>>() {
        return points_from_rows(array.as_array(), argument);
    }
    if let Ok(array) = value.extract::<PyReadonlyArray2<'_, f32>>() {
        return points_from_rows(array.as_array(), argument);
    }
    Err(PyTypeError::new_err(format!(
        "{argument}: expected a 2-D float32 or float64 numpy array, got {}",
        describe(value)
    )))
}

fn points_from_rows<T: Copy + Into<f64>>(
    rows: ArrayView2<'_, T>,
    argument: &str,
) -> PyResult<Vec<Point3<f64>>> {
    let (count, columns) = rows.dim();
    if columns != 3 && columns != 4 {
        return Err(PyValueError::new_err(format!(
            "{argument}: expected shape (N, 3) or (N, 4), got ({count}, {columns})"
        )));
    }
    Ok(rows
        .outer_iter()
        .map(|row| Point3::new(row[0].into(), row[1].into(), row[2].into()))
        .collect())
}

fn read_transform(value: &Bound<'_, PyAny>, argument: &str) -> PyResult<Matrix4<f64>> {
    let rows = read_rows(value, argument)?;
    if rows.dim() != (4, 4) {
        return Err(PyValueError::new_err(format!(
            "{argument}: expected shape (4, 4), got {:?}",
            rows.dim()
        )));
    }
    Ok(Matrix4::from_fn(|r, c| rows[(r, c)]))
}

// ---- classes ---------------------------------------------------------------------------------------

/// The outcome of `NdtMap.align`.
#[pyclass(name = "NdtResult", module = "dmlo_rs._dmlo_rs", frozen)]
pub struct PyNdtResult {
    transform: Matrix4<f64>,
    /// Whether the last step was below both epsilons.
    #[pyo3(get)]
    converged: bool,
    /// Newton steps taken.
    #[pyo3(get)]
    iterations: usize,
    /// Thinned source points with a map distribution nearby at the final pose.
    #[pyo3(get)]
    num_correspondences: usize,
    /// Mean NDT likelihood per thinned source point (each nearby distribution adds up to 1, far away 0).
    #[pyo3(get)]
    score: f64,
    /// Directions of the pose held at the initial estimate because the map does not constrain them.
    #[pyo3(get)]
    degenerate_directions: usize,
    translation_eigenvalues: [f64; 3],
    rotation_eigenvalues: [f64; 3],
}

impl From<NdtResult> for PyNdtResult {
    fn from(result: NdtResult) -> Self {
        PyNdtResult {
            transform: result.transform.to_homogeneous(),
            converged: result.converged,
            iterations: result.iterations,
            num_correspondences: result.num_correspondences,
            score: result.score,
            degenerate_directions: result.degenerate_directions,
            translation_eigenvalues: result.translation_eigenvalues,
            rotation_eigenvalues: result.rotation_eigenvalues,
        }
    }
}

#[pymethods]
impl PyNdtResult {
    /// `T_map_source` as a 4×4 float64 array.
    #[getter]
    fn transform<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        Array2::from_shape_fn((4, 4), |(r, c)| self.transform[(r, c)]).into_pyarray(py)
    }

    /// Eigenvalues of the information about the translation (rotation marginalised) at the initial pose,
    /// ascending, divided by the largest (3 float64); those below `degeneracy_threshold` are degenerate
    /// (held at the initial estimate).
    #[getter]
    fn translation_eigenvalues<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.translation_eigenvalues.to_vec().into_pyarray(py)
    }

    /// The same for the rotation (translation marginalised), against `rotation_degeneracy_threshold`.
    #[getter]
    fn rotation_eigenvalues<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.rotation_eigenvalues.to_vec().into_pyarray(py)
    }

    fn __repr__(&self) -> String {
        let t = &self.transform;
        format!(
            "NdtResult(converged={}, iterations={}, num_correspondences={}, score={:.4}, degenerate_directions={}, translation=[{:.4}, {:.4}, {:.4}])",
            if self.converged { "True" } else { "False" },
            self.iterations,
            self.num_correspondences,
            self.score,
            self.degenerate_directions,
            t[(0, 3)],
            t[(1, 3)],
            t[(2, 3)]
        )
    }
}

/// A local NDT submap of the most recent scans, and scan-to-map registration against it.
#[pyclass(name = "NdtMap", module = "dmlo_rs._dmlo_rs")]
pub struct PyNdtMap {
    inner: NdtMap,
}

#[pymethods]
impl PyNdtMap {
    #[new]
    #[pyo3(signature = (voxel_size = 1.0, max_scans = 10, min_points_per_voxel = 5, min_eigenvalue_ratio = 0.01))]
    fn new(
        voxel_size: f64,
        #[pyo3(from_py_with = counts::max_scans)] max_scans: usize,
        #[pyo3(from_py_with = counts::min_points_per_voxel)] min_points_per_voxel: usize,
        min_eigenvalue_ratio: f64,
    ) -> PyResult<Self> {
        let config = NdtMapConfig {
            voxel_size,
            min_points_per_voxel,
            max_scans,
            min_eigenvalue_ratio,
        };
        Ok(PyNdtMap {
            inner: NdtMap::new(config)?,
        })
    }

    /// Adds a scan in map (world) coordinates, `N×3` or `N×4`; evicts the oldest beyond `max_scans`.
    #[pyo3(signature = (points_world, *, num_threads = None))]
    fn insert(
        &mut self,
        py: Python<'_>,
        points_world: &Bound<'_, PyAny>,
        num_threads: Option<Int>,
    ) -> PyResult<()> {
        let points = read_points(points_world, "points_world")?;
        let inner = &mut self.inner;
        run(py, threads(num_threads)?, move || inner.insert(&points))
    }

    /// Adds a scan in its sensor frame (`N×3` or `N×4`) at the pose `transform` (`T_map_sensor`, 4×4):
    /// the same map as `insert` of the transformed points, without building them in numpy.
    #[pyo3(signature = (points, transform, *, num_threads = None))]
    fn insert_scan(
        &mut self,
        py: Python<'_>,
        points: &Bound<'_, PyAny>,
        transform: &Bound<'_, PyAny>,
        num_threads: Option<Int>,
    ) -> PyResult<()> {
        let points = read_points(points, "points")?;
        let transform =
            isometry_from_matrix4(&read_transform(transform, "transform")?, "transform")?;
        let inner = &mut self.inner;
        run(py, threads(num_threads)?, move || {
            inner.insert_scan(&points, &transform)
        })
    }

    /// Forgets every scan.
    fn clear(&mut self) {
        self.inner.clear();
    }

    /// Registers `points` (sensor frame, `N×3` or `N×4`) to the map from `initial_transform`
    /// (`T_map_source`, 4×4); returns the refined `T_map_source`.
    #[pyo3(signature = (
        points,
        initial_transform,
        *,
        max_iterations = 30,
        translation_epsilon = 1e-4,
        rotation_epsilon_deg = 1e-3,
        outlier_ratio = 0.55,
        source_voxel_size = 0.5,
        neighbours = "direct7",
        max_step_translation = 0.5,
        max_step_rotation_deg = 5.0,
        min_correspondences = 20,
        degeneracy_threshold = 0.05,
        rotation_degeneracy_threshold = 0.01,
        num_threads = None,
    ))]
    #[allow(clippy::too_many_arguments)]
    fn align(
        &self,
        py: Python<'_>,
        points: &Bound<'_, PyAny>,
        initial_transform: &Bound<'_, PyAny>,
        #[pyo3(from_py_with = counts::max_iterations)] max_iterations: usize,
        translation_epsilon: f64,
        rotation_epsilon_deg: f64,
        outlier_ratio: f64,
        source_voxel_size: f64,
        neighbours: &str,
        max_step_translation: f64,
        max_step_rotation_deg: f64,
        #[pyo3(from_py_with = counts::min_correspondences)] min_correspondences: usize,
        degeneracy_threshold: f64,
        rotation_degeneracy_threshold: f64,
        num_threads: Option<Int>,
    ) -> PyResult<PyNdtResult> {
        let neighbours = match neighbours {
            "containing" => NeighbourSearch::Containing,
            "direct7" => NeighbourSearch::Direct7,
            "direct27" => NeighbourSearch::Direct27,
            other => {
                return Err(PyValueError::new_err(format!(
                    "neighbours: expected 'containing', 'direct7' or 'direct27', got {other:?}"
                )))
            }
        };
        let config = NdtAlignConfig {
            max_iterations,
            translation_epsilon,
            rotation_epsilon_deg,
            outlier_ratio,
            source_voxel_size,
            neighbours,
            max_step_translation,
            max_step_rotation_deg,
            min_correspondences,
            degeneracy_threshold,
            rotation_degeneracy_threshold,
            ..Default::default()
        };
        let points = read_points(points, "points")?;
        let initial = read_transform(initial_transform, "initial_transform")?;
        let inner = &self.inner;
        let result = run(py, threads(num_threads)?, move || {
            inner.align_matrix(&points, &initial, &config)
        })?;
        Ok(result.into())
    }

    /// Voxels holding a distribution.
    #[getter]
    fn num_voxels(&self) -> usize {
        self.inner.num_voxels()
    }

    /// Voxels holding at least one point.
    #[getter]
    fn num_occupied_voxels(&self) -> usize {
        self.inner.num_occupied_voxels()
    }

    /// Scans in the window.
    #[getter]
    fn num_scans(&self) -> usize {
        self.inner.num_scans()
    }

    /// Voxel edge length, metres.
    #[getter]
    fn voxel_size(&self) -> f64 {
        self.inner.config().voxel_size
    }

    /// Window length, scans.
    #[getter]
    fn max_scans(&self) -> usize {
        self.inner.config().max_scans
    }

    fn __repr__(&self) -> String {
        let config = self.inner.config();
        format!(
            "NdtMap(voxel_size={}, max_scans={}, num_scans={}, num_voxels={})",
            config.voxel_size,
            config.max_scans,
            self.inner.num_scans(),
            self.inner.num_voxels()
        )
    }
}
