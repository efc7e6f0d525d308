//! Binding of the odometry's local map (`crate::odometry::mapping`): scan-to-map NDT of every pose and
//! of a consecutive pair, with the near-keyframe handling, which `dmlo.Odometry` runs on.

use numpy::PyArray2;
use pyo3::prelude::*;

use crate::odometry::mapping::{self, LocalMap, MappingConfig};
use crate::projection::CylinderConfig;

use super::convert::{counts, matrix4_to_numpy, point_image, points_to_numpy, rigid_matrix};
use super::ndt::read_points;
use super::pool::run;
use super::projection::PyCylinderConfig;

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyLocalMap>()?;
    m.add_class::<PyMapRefinement>()?;
    m.add_function(wrap_pyfunction!(upright_points, m)?)?;
    m.add_function(wrap_pyfunction!(heading_and_level, m)?)?;
    Ok(())
}

/// What the map made of a pose: the refined `pose` (4×4, the one given when no alignment converged),
/// whether an alignment `converged`, the `degenerate_directions` the map left open (None when none ran),
/// whether the horizontal motion came from the upright surfaces alone (`upright_only`), and the winning
/// `start` ("dmlo", "motion_model", "standing"; None when none converged).
#[pyclass(name = "MapRefinement", module = "dmlo_rs._dmlo_rs", frozen)]
pub struct PyMapRefinement {
    #[pyo3(get)]
    pose: Py<PyArray2<f64>>,
    #[pyo3(get)]
    converged: bool,
    #[pyo3(get)]
    degenerate_directions: Option<usize>,
    #[pyo3(get)]
    upright_only: bool,
    #[pyo3(get)]
    start: Option<&'static str>,
}

#[pymethods]
impl PyMapRefinement {
    fn __repr__(&self) -> String {
        format!(
            "MapRefinement(converged={}, start={:?}, upright_only={})",
            if self.converged { "True" } else { "False" },
            self.start,
            if self.upright_only { "True" } else { "False" }
        )
    }
}

/// The local map of the most recent keyframes (scan-to-map NDT, §III-D-c) for scans projected with
/// `cylinder`, with the odometry's `mapping` settings.
#[pyclass(name = "LocalMap", module = "dmlo_rs._dmlo_rs")]
pub struct PyLocalMap {
    inner: LocalMap,
    cylinder: CylinderConfig,
}

fn cloud_points(obj: &Bound<'_, PyAny>) -> PyResult<Vec<nalgebra::Point3<f64>>> {
    read_points(obj, "cloud")
}

/// A keyframe's scan (points in its sensor frame), pose and point image.
type KeyframeScan = (Vec<nalgebra::Point3<f64>>, nalgebra::Matrix4<f64>, Vec<f32>);

impl PyLocalMap {
    /// A keyframe's scan, pose and point image, checked.
    fn keyframe_arguments(
        &self,
        cloud: &Bound<'_, PyAny>,
        pose: &Bound<'_, PyAny>,
        points: &Bound<'_, PyAny>,
    ) -> PyResult<KeyframeScan> {
        let (cloud, pose) = (cloud_points(cloud)?, rigid_matrix("pose", pose)?);
        let points = point_image("points", points, &self.cylinder)?;
        let points = points.f32_data().into_owned();
        Ok((cloud, pose, points))
    }
}

#[pymethods]
impl PyLocalMap {
    #[new]
    #[pyo3(signature = (cylinder, *, voxel_size = 1.0, max_scans = 10, keyframe_distance = 2.0,
                        keyframe_angle_deg = 5.0, ring_lock_distance = 0.5,
                        motion_model_start_distance = 0.3, motion_model_start_angle_deg = 1.5,
                        downsample = 0.75, downsample_far = 0.4, far_range = 15.0,
                        level_without_far_upright = true, max_iterations = 30, degeneracy_threshold = 0.05,
                        rotation_degeneracy_threshold = 0.01))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        cylinder: &PyCylinderConfig,
        voxel_size: f64,
        #[pyo3(from_py_with = counts::max_scans)] max_scans: usize,
        keyframe_distance: f64,
        keyframe_angle_deg: f64,
        ring_lock_distance: f64,
        motion_model_start_distance: f64,
        motion_model_start_angle_deg: f64,
        downsample: f64,
        downsample_far: f64,
        far_range: f64,
        level_without_far_upright: bool,
        #[pyo3(from_py_with = counts::max_iterations)] max_iterations: usize,
        degeneracy_threshold: f64,
        rotation_degeneracy_threshold: f64,
    ) -> PyResult<Self> {
        let config = MappingConfig {
            voxel_size,
            max_scans,
            keyframe_distance,
            keyframe_angle_deg,
            ring_lock_distance,
            motion_model_start_distance,
            motion_model_start_angle_deg,
            downsample,
            downsample_far,
            far_range,
            level_without_far_upright,
            max_iterations,
            degeneracy_threshold,
            rotation_degeneracy_threshold,
        };
        Ok(PyLocalMap {
            inner: LocalMap::new(config)?,
            cylinder: cylinder.inner,
        })
    }

    /// The newest keyframe's pose (4×4), None before the first.
    #[getter]
    fn last_keyframe<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray2<f64>>> {
        self.inner
            .last_keyframe()
            .map(|pose| matrix4_to_numpy(py, pose))
    }

    /// Keyframes in the map.
    #[getter]
    fn num_scans(&self) -> usize {
        self.inner.num_scans()
    }

    /// Whether a scan at `pose` moved or turned far enough from the newest keyframe to enter the map.
    fn is_keyframe(&self, pose: &Bound<'_, PyAny>) -> PyResult<bool> {
        Ok(self.inner.is_keyframe(&rigid_matrix("pose", pose)?))
    }

    /// Adds a scan (`cloud` N×3/N×4 in its sensor frame, `points` its point image [H, W, 3]) at `pose`
    /// as the newest keyframe.
    fn insert(
        &mut self,
        py: Python<'_>,
        cloud: &Bound<'_, PyAny>,
        pose: &Bound<'_, PyAny>,
        points: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let (cloud, pose, points) = self.keyframe_arguments(cloud, pose, points)?;
        let map = &mut self.inner;
        run(py, None, || map.insert(&cloud, &pose, &points))
    }

    /// Empties the map and starts it again from one scan (as `insert`).
    fn restart(
        &mut self,
        py: Python<'_>,
        cloud: &Bound<'_, PyAny>,
        pose: &Bound<'_, PyAny>,
        points: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let (cloud, pose, points) = self.keyframe_arguments(cloud, pose, points)?;
        let map = &mut self.inner;
        run(py, None, || map.restart(&cloud, &pose, &points))
    }

    /// The `pose` of a scan (`cloud`, its point image `points`) refined against the map: near the newest
    /// keyframe by point-to-plane ICP (a standing car) or the upright surfaces' split, else NDT of the
    /// whole scan from `pose` and, when it lies far from it, from the constant-velocity `prediction`
    /// (None: no velocity measured, or beyond its horizon), the better score winning.
    fn refine(
        &self,
        py: Python<'_>,
        cloud: &Bound<'_, PyAny>,
        points: &Bound<'_, PyAny>,
        pose: &Bound<'_, PyAny>,
        prediction: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<PyMapRefinement> {
        let (cloud, pose) = (cloud_points(cloud)?, rigid_matrix("pose", pose)?);
        let prediction = prediction
            .map(|p| rigid_matrix("prediction", p))
            .transpose()?;
        let points = point_image("points", points, &self.cylinder)?;
        let points = points.f32_data();
        let (map, cylinder) = (&self.inner, &self.cylinder);
        let refined = run(py, None, || {
            map.refine(&cloud, &points, &pose, prediction.as_ref(), cylinder)
        })?;
        Ok(PyMapRefinement {
            pose: matrix4_to_numpy(py, &refined.pose).unbind(),
            converged: refined.converged,
            degenerate_directions: refined.degenerate_directions,
            upright_only: refined.upright_only,
            start: refined.start.map(|start| start.name()),
        })
    }

    /// `t_tgt_ref` of a consecutive pair (the scans' clouds and point images) refined against the
    /// reference scan alone, with this map's settings but not its scans: a pair that stands by
    /// point-to-plane ICP, a pair within `ring_lock_distance` by the upright surfaces' split, else NDT of
    /// the whole target. None when the alignment fails.
    fn refine_pair<'py>(
        &self,
        py: Python<'py>,
        reference: &Bound<'py, PyAny>,
        target: &Bound<'py, PyAny>,
        reference_points: &Bound<'py, PyAny>,
        target_points: &Bound<'py, PyAny>,
        t_tgt_ref: &Bound<'py, PyAny>,
    ) -> PyResult<Option<Bound<'py, PyArray2<f64>>>> {
        let (reference, target) = (cloud_points(reference)?, cloud_points(target)?);
        let t_tgt_ref = rigid_matrix("t_tgt_ref", t_tgt_ref)?;
        let reference_points = point_image("reference_points", reference_points, &self.cylinder)?;
        let target_points = point_image("target_points", target_points, &self.cylinder)?;
        let (reference_points, target_points) =
            (reference_points.f32_data(), target_points.f32_data());
        let (config, cylinder) = (self.inner.config(), &self.cylinder);
        let refined = run(py, None, || {
            mapping::refine_consecutive_pair(
                &reference,
                &target,
                &reference_points,
                &target_points,
                &t_tgt_ref,
                config,
                cylinder,
            )
        })?;
        Ok(refined.map(|pose| matrix4_to_numpy(py, &pose)))
    }

    fn __repr__(&self) -> String {
        format!("LocalMap(num_scans={})", self.inner.num_scans())
    }
}

/// The upright surfaces of a scan's point image `points` [H, W, 3] (NaN where empty): each kept point
/// whose surface's normal is mostly horizontal, one cell per `voxel` m (0: every cell) → N×3 float64.
#[pyfunction]
#[pyo3(signature = (points, config, voxel))]
fn upright_points<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    config: &PyCylinderConfig,
    voxel: f64,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let cylinder = config.inner;
    let points = point_image("points", points, &cylinder)?;
    let points = points.f32_data();
    let upright = run(py, Some(1), || {
        mapping::upright_points(&points, &cylinder, voxel)
    })?;
    Ok(points_to_numpy(py, &upright))
}

/// A pose (4×4) with the horizontal position and heading of `horizontal` and the height, roll and pitch
/// of `level`.
#[pyfunction]
fn heading_and_level<'py>(
    py: Python<'py>,
    horizontal: &Bound<'py, PyAny>,
    level: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let horizontal = rigid_matrix("horizontal", horizontal)?;
    let level = rigid_matrix("level", level)?;
    Ok(matrix4_to_numpy(
        py,
        &mapping::heading_and_level(&horizontal, &level),
    ))
}
