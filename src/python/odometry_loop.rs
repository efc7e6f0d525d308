//! Binding of the crate's per-frame odometry (`crate::odometry::pipeline::Odometry`) over a matcher
//! written in Python: any object with `cylinder`, `encode(image)` and `match(reference, target)`, and
//! optionally `match_cells(reference, target, cells)` (the flow of the marked reference cells only) and
//! `wide_match(reference, target, target_image)` (the wide window), as
//! `dmlo.odometry.matcher.OnnxMatcher` gives them, so the loop runs in the crate while the network runs
//! wherever the caller runs it (onnxruntime in `dmlo`). A moving-object network written in Python is any
//! object with `cylinder` and `probability(range, height)`.

use std::sync::{Arc, Mutex};

use numpy::{IntoPyArray, PyArray3};
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::dense_match::DenseFlow;
use crate::error::{Error, Result};
use crate::odometry::config::schema::Named;
use crate::odometry::config::{MatchingStage, OdometryConfig};
use crate::odometry::motion::Fallback;
use crate::odometry::moving::MovingObjectNetwork;
use crate::odometry::pipeline::{FrameMatcher, Odometry, Scan};
use crate::projection::CylinderConfig;

use super::diagnostics::PyFrameDiagnostics;
use super::convert::{matrix4_to_numpy, named_scan_points, shape_error, vector_f64};
use super::pair::{pair_from_flow, FlowImages, PyPairMotion};
use super::pool::run;
use super::projection::PyCylinderConfig;

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyOdometry>()?;
    Ok(())
}

/// A Python matcher behind the crate's [`FrameMatcher`]: each call takes the GIL for the Python call
/// alone. An exception the matcher raises is kept and raised again unchanged by the binding.
struct PythonMatcher {
    object: Py<PyAny>,
    cylinder: CylinderConfig,
    uses_reflectance: bool,
    matches_cells: bool,
    guides_windows: bool,
    wide_window: bool,
    /// The matcher encodes a scan inside its `match` (`defers_encoding`): the two are timed as one.
    defers_encoding: bool,
    raised: Raised,
}

/// Where the matchers of one odometry keep the exception a call raised, for the binding to raise again.
type Raised = Arc<Mutex<Option<PyErr>>>;

impl PythonMatcher {
    /// `object` checked for the protocol (module docs); errors name it as `name`.
    fn new(name: &str, object: &Bound<'_, PyAny>, raised: &Raised) -> PyResult<Self> {
        let cylinder = object
            .getattr_opt("cylinder")?
            .and_then(|c| c.extract::<PyCylinderConfig>().ok())
            .ok_or_else(|| {
                PyValueError::new_err(format!(
                    "{name}: expected a `cylinder` attribute of type CylinderConfig"
                ))
            })?;
        let uses_reflectance = match object.getattr_opt("uses_reflectance")? {
            Some(value) => value.extract::<bool>().map_err(|_| {
                PyValueError::new_err(format!("{name}: `uses_reflectance` must be True or False"))
            })?,
            None => true,
        };
        for method in ["encode", "match"] {
            if !object.getattr_opt(method)?.is_some_and(|m| m.is_callable()) {
                return Err(PyValueError::new_err(format!(
                    "{name}: expected a method `{method}`"
                )));
            }
        }
        let callable = |method: &str| -> PyResult<bool> {
            Ok(object.getattr_opt(method)?.is_some_and(|m| m.is_callable()))
        };
        Ok(PythonMatcher {
            object: object.clone().unbind(),
            cylinder: cylinder.inner,
            uses_reflectance,
            matches_cells: callable("match_cells")?,
            guides_windows: callable("match_guided")?,
            wide_window: callable("wide_match")?,
            defers_encoding: match object.getattr_opt("defers_encoding")? {
                Some(value) => value.is_truthy()?,
                None => false,
            },
            raised: raised.clone(),
        })
    }

    /// Keeps the matcher's exception for the binding and tells the crate that the call failed.
    fn failed(&self, method: &str, err: PyErr) -> Error {
        let message = format!("the matcher's {method} raised {err}");
        *self.raised.lock().unwrap_or_else(|p| p.into_inner()) = Some(err);
        Error::Model(message)
    }
}

impl FrameMatcher for PythonMatcher {
    type Features = Py<PyAny>;

    fn cylinder(&self) -> &CylinderConfig {
        &self.cylinder
    }

    fn uses_reflectance(&self) -> bool {
        self.uses_reflectance
    }

    fn encode(&self, image: &[f32]) -> Result<Py<PyAny>> {
        Python::attach(|py| {
            let array = self.image(py, image)?;
            self.object.call_method1(py, "encode", (array,))
        })
        .map_err(|e| self.failed("encode", e))
    }

    fn flow(&self, reference: &Py<PyAny>, target: &Py<PyAny>) -> Result<DenseFlow> {
        Python::attach(|py| {
            let output = self.object.call_method1(py, "match", (reference, target))?;
            self.dense_flow(py, "match", &output)
        })
        .map_err(|e| self.failed("match", e))
    }

    fn flow_of_cells(
        &self,
        reference: &Py<PyAny>,
        target: &Py<PyAny>,
        cells: &[bool],
    ) -> Result<DenseFlow> {
        if !self.matches_cells {
            return self.flow(reference, target);
        }
        Python::attach(|py| {
            let (height, width) = (self.cylinder.height, self.cylinder.width);
            let cells = PyArray1::from_slice(py, cells).reshape([height, width])?;
            let output = self
                .object
                .call_method1(py, "match_cells", (reference, target, cells))?;
            self.dense_flow(py, "match_cells", &output)
        })
        .map_err(|e| self.failed("match_cells", e))
    }

    fn guided_flow_of_cells(
        &self,
        reference: &Py<PyAny>,
        target: &Py<PyAny>,
        cells: &[bool],
        expected: &[[f32; 2]],
    ) -> Result<Option<DenseFlow>> {
        if !self.guides_windows {
            return Ok(None);
        }
        Python::attach(|py| {
            let (height, width) = (self.cylinder.height, self.cylinder.width);
            let cells = PyArray1::from_slice(py, cells).reshape([height, width])?;
            let expected =
                PyArray1::from_slice(py, expected.as_flattened()).reshape([height, width, 2])?;
            let output = self.object.call_method1(
                py,
                "match_guided",
                (reference, target, cells, expected),
            )?;
            self.dense_flow(py, "match_guided", &output)
        })
        .map(Some)
        .map_err(|e| self.failed("match_guided", e))
    }

    /// The Python matcher was opened for the config's stage (`dmlo.odometry.matcher.OnnxMatcher`).
    fn runs_matching_stage(&self, _stage: MatchingStage) -> bool {
        true
    }

    fn has_wide_window(&self) -> bool {
        self.wide_window
    }

    fn wide_flow(
        &self,
        reference: &Py<PyAny>,
        target: &Py<PyAny>,
        target_image: &[f32],
    ) -> Result<DenseFlow> {
        Python::attach(|py| {
            let image = self.image(py, target_image)?;
            let output = self
                .object
                .call_method1(py, "wide_match", (reference, target, image))?;
            self.dense_flow(py, "wide_match", &output)
        })
        .map_err(|e| self.failed("wide_match", e))
    }
}

impl PythonMatcher {
    /// A `(2, H, W)` image as numpy.
    fn image<'py>(&self, py: Python<'py>, image: &[f32]) -> PyResult<Bound<'py, PyAny>> {
        let (height, width) = (self.cylinder.height, self.cylinder.width);
        Ok(PyArray1::from_slice(py, image)
            .reshape([2, height, width])?
            .into_any())
    }

    /// A `(flow [2, H, W], confidence [H, W])` float32 pair returned by the matcher's `method`, checked.
    fn dense_flow(&self, py: Python<'_>, method: &str, output: &Py<PyAny>) -> PyResult<DenseFlow> {
        let (height, width) = (self.cylinder.height, self.cylinder.width);
        let (flow, confidence): (PyReadonlyArray3<'_, f32>, PyReadonlyArray2<'_, f32>) =
            output.extract(py)?;
        if flow.shape() != [2, height, width] {
            return Err(shape_error(
                &format!("{method}: flow"),
                &format!("(2, {height}, {width}) float32"),
                flow.shape(),
            ));
        }
        if confidence.shape() != [height, width] {
            return Err(shape_error(
                &format!("{method}: confidence"),
                &format!("({height}, {width}) float32"),
                confidence.shape(),
            ));
        }
        Ok(DenseFlow {
            flow: flow.as_array().iter().copied().collect(),
            confidence: confidence.as_array().iter().copied().collect(),
            height,
            width,
        })
    }
}

/// A scan's network input `[2, H, W]` and its range image `[H, W]`.
type NetworkImage<'py> = (Bound<'py, PyArray3<f32>>, Bound<'py, numpy::PyArray2<f32>>);

/// A Python moving-object network behind the crate's [`MovingObjectNetwork`]: its `probability(range,
/// height)` takes the two `[H, W]` float32 images and returns the `[H, W]` probabilities. An exception it
/// raises is kept and raised again unchanged by the binding.
struct PythonMovingObjects {
    object: Py<PyAny>,
    cylinder: CylinderConfig,
    raised: Raised,
}

impl PythonMovingObjects {
    fn new(object: &Bound<'_, PyAny>, raised: &Raised) -> PyResult<Self> {
        let cylinder = object
            .getattr_opt("cylinder")?
            .and_then(|c| c.extract::<PyCylinderConfig>().ok())
            .ok_or_else(|| {
                PyValueError::new_err(
                    "moving_objects: expected a `cylinder` attribute of type CylinderConfig",
                )
            })?;
        if !object
            .getattr_opt("probability")?
            .is_some_and(|m| m.is_callable())
        {
            return Err(PyValueError::new_err(
                "moving_objects: expected a method `probability`",
            ));
        }
        Ok(PythonMovingObjects {
            object: object.clone().unbind(),
            cylinder: cylinder.inner,
            raised: raised.clone(),
        })
    }
}

impl MovingObjectNetwork for PythonMovingObjects {
    fn cylinder(&self) -> &CylinderConfig {
        &self.cylinder
    }

    fn probability(&self, range: &[f32], height: &[f32]) -> Result<Vec<f32>> {
        let (rows, columns) = (self.cylinder.height, self.cylinder.width);
        Python::attach(|py| -> PyResult<Vec<f32>> {
            let range = PyArray1::from_slice(py, range).reshape([rows, columns])?;
            let height = PyArray1::from_slice(py, height).reshape([rows, columns])?;
            let output = self
                .object
                .call_method1(py, "probability", (range, height))?;
            let probability: PyReadonlyArray2<'_, f32> = output.extract(py)?;
            if probability.shape() != [rows, columns] {
                return Err(shape_error(
                    "probability",
                    &format!("({rows}, {columns}) float32"),
                    probability.shape(),
                ));
            }
            Ok(probability.as_array().iter().copied().collect())
        })
        .map_err(|err| {
            let message = format!("the moving-object network's probability raised {err}");
            *self.raised.lock().unwrap_or_else(|p| p.into_inner()) = Some(err);
            Error::Model(message)
        })
    }
}

/// DMLO odometry run by the crate, the network by `matcher` (see the stub for the protocol).
#[pyclass(name = "Odometry", module = "dmlo_rs._dmlo_rs")]
pub struct PyOdometry {
    inner: Odometry<PythonMatcher>,
    raised: Raised,
    threads: Option<i64>,
    /// The matcher encodes scans while matching them: its matching time is counted as the network's.
    encoding_in_matching: bool,
}

impl PyOdometry {
    /// `result` of a call into the crate, the matcher's own exception in place of the crate's report of it.
    fn raised_or<T>(&self, result: PyResult<T>) -> PyResult<T> {
        let raised = self.raised.lock().unwrap_or_else(|p| p.into_inner()).take();
        result.map_err(|err| raised.unwrap_or(err))
    }
}

#[pymethods]
impl PyOdometry {
    #[new]
    #[pyo3(signature = (matcher, config_json = None, num_threads = None, range_only = None, allow_zero_reflectance = false, moving_objects = None))]
    fn new(
        matcher: &Bound<'_, PyAny>,
        config_json: Option<&str>,
        num_threads: Option<super::convert::Int>,
        range_only: Option<&Bound<'_, PyAny>>,
        allow_zero_reflectance: bool,
        moving_objects: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let config = match config_json {
            Some(text) => OdometryConfig::from_json(text)?,
            None => OdometryConfig::default(),
        };
        let raised = Raised::default();
        let matcher = PythonMatcher::new("matcher", matcher, &raised)?;
        let encoding_in_matching = matcher.defers_encoding;
        let mut odometry = Odometry::new(matcher, config)?;
        if let Some(range_only) = range_only {
            let range_only = PythonMatcher::new("range_only", range_only, &raised)?;
            odometry = odometry.with_range_only(range_only)?;
        }
        if allow_zero_reflectance {
            odometry = odometry.allowing_zero_reflectance();
        }
        if let Some(network) = moving_objects {
            odometry = odometry.with_moving_objects(PythonMovingObjects::new(network, &raised)?)?;
        }
        Ok(PyOdometry {
            inner: odometry,
            raised,
            threads: super::pool::threads(num_threads)?,
            encoding_in_matching,
        })
    }

    /// Adds the next scan (`N×4` x, y, z, reflectance or `N×3` without it, float32 or float64;
    /// non-finite rows left out) and returns its pose `T_world_lidar` (4×4 float64). `moving`: one flag per
    /// point, left out of matching and the map; `timestamp`: the scan's time (a finite number), from which
    /// dropped scans are counted; `point_times`: with `deskew.enabled`, each point's time in sensor periods
    /// (None: from its azimuth).
    #[pyo3(signature = (points, moving = None, timestamp = None, point_times = None))]
    fn register<'py>(
        &mut self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
        moving: Option<numpy::PyReadonlyArray1<'py, bool>>,
        timestamp: Option<&Bound<'py, PyAny>>,
        point_times: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, numpy::PyArray2<f64>>> {
        let (cloud, has_reflectance) = scan_cloud("points", points)?;
        let timestamp = timestamp.map(seconds).transpose()?;
        let times = point_times
            .map(|t| vector_f64("point_times", t))
            .transpose()?;
        let mask: Option<Vec<bool>> = moving
            .as_ref()
            .map(|m| m.as_array().iter().copied().collect());
        let threads = self.threads;
        let inner = &mut self.inner;
        let result = run(py, threads, || {
            inner.register_matrix(Scan {
                points: &cloud,
                has_reflectance,
                moving: mask.as_deref(),
                timestamp,
                point_times: times.as_deref(),
            })
        });
        let pose = self.raised_or(result)?;
        Ok(matrix4_to_numpy(py, &pose))
    }

    /// The motion between two scans (N×4 each, or N×3 without reflectance) with no motion model or
    /// initial guess (`Odometry::register_pair`): `(T_tgt_ref 4×4, matches PairMotion, map_refined bool |
    /// None, rounds, notices)`, each notice a `(kind, message)` pair; `*_moving`: one flag per point, left
    /// out.
    #[pyo3(signature = (reference, target, large_motion = false, reference_moving = None, target_moving = None))]
    #[allow(clippy::type_complexity)]
    fn register_pair<'py>(
        &mut self,
        py: Python<'py>,
        reference: &Bound<'py, PyAny>,
        target: &Bound<'py, PyAny>,
        large_motion: bool,
        reference_moving: Option<numpy::PyReadonlyArray1<'py, bool>>,
        target_moving: Option<numpy::PyReadonlyArray1<'py, bool>>,
    ) -> PyResult<(
        Bound<'py, numpy::PyArray2<f64>>,
        PyPairMotion,
        Option<bool>,
        usize,
        Vec<(&'static str, String)>,
    )> {
        let ((reference, reference_reflectance), (target, target_reflectance)) = (
            scan_cloud("reference", reference)?,
            scan_cloud("target", target)?,
        );
        let flags = |m: &Option<numpy::PyReadonlyArray1<'py, bool>>| -> Option<Vec<bool>> {
            m.as_ref().map(|m| m.as_array().iter().copied().collect())
        };
        let (reference_moving, target_moving) = (flags(&reference_moving), flags(&target_moving));
        let threads = self.threads;
        let inner = &mut self.inner;
        let result = run(py, threads, || {
            inner.register_pair(
                Scan {
                    moving: reference_moving.as_deref(),
                    has_reflectance: reference_reflectance,
                    ..Scan::new(&reference)
                },
                Scan {
                    moving: target_moving.as_deref(),
                    has_reflectance: target_reflectance,
                    ..Scan::new(&target)
                },
                large_motion,
            )
        });
        let pair = self.raised_or(result)?;
        Ok((
            matrix4_to_numpy(py, &pair.transform),
            PyPairMotion::new(py, pair.matches),
            pair.map_refined,
            pair.rounds,
            pair.notices
                .iter()
                .map(|n| (n.kind(), n.message()))
                .collect(),
        ))
    }

    /// Forgets the drive: the next scan is the world again (`Odometry::reset`).
    fn reset(&mut self) {
        self.inner.reset();
    }

    /// Records a scan that could not be read: its pose from the motion model, `reason` in its diagnostics.
    #[pyo3(signature = (reason = "unreadable_scan"))]
    fn predict_skipped<'py>(
        &mut self,
        py: Python<'py>,
        reason: &str,
    ) -> PyResult<Bound<'py, numpy::PyArray2<f64>>> {
        let reason = Fallback::from_name(reason).ok_or_else(|| {
            let names: Vec<&str> = <Fallback as Named>::NAMES
                .iter()
                .map(|(_, name)| *name)
                .collect();
            PyValueError::new_err(format!(
                "reason: expected one of {}, got {reason:?}",
                names.join(", ")
            ))
        })?;
        let pose = self.inner.predict_skipped_matrix(reason)?;
        Ok(matrix4_to_numpy(py, &pose))
    }

    /// Every pose so far, `(N, 4, 4)` float64.
    #[getter]
    fn poses<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray3<f64>> {
        let poses = self.inner.pose_matrices();
        numpy::ndarray::Array3::from_shape_fn((poses.len(), 4, 4), |(n, i, j)| poses[n][(i, j)])
            .into_pyarray(py)
    }

    /// The back end alone with this odometry's settings: a pair's motion from any flow `[2, H, W]` and
    /// confidence `[H, W]` between the range images `ref_range` and `tgt_range` (§III-D; `match_pair` with
    /// the config's matching and RANSAC settings). `ref_points` `[H, W, 3]`: the surfaces under the
    /// matches (None: the virtual points of the reference's cells); `leave_out` `[H, W]`: cells left out;
    /// `tilt_votes` False: one vote a match whatever `ransac.vote_by_tilt` says.
    #[pyo3(signature = (ref_range, tgt_range, flow, confidence, *, ref_points = None, leave_out = None, tilt_votes = true))]
    #[allow(clippy::too_many_arguments)]
    fn pose_from_flow(
        &self,
        py: Python<'_>,
        ref_range: &Bound<'_, PyAny>,
        tgt_range: &Bound<'_, PyAny>,
        flow: &Bound<'_, PyAny>,
        confidence: &Bound<'_, PyAny>,
        ref_points: Option<&Bound<'_, PyAny>>,
        leave_out: Option<&Bound<'_, PyAny>>,
        tilt_votes: bool,
    ) -> PyResult<PyPairMotion> {
        let images = FlowImages {
            ref_range,
            tgt_range,
            flow,
            confidence,
            ref_points,
            leave_out,
        };
        let settings = self.inner.config().pair_config();
        let cylinder = *self.inner.matcher().cylinder();
        pair_from_flow(py, images, &cylinder, &settings, tilt_votes, self.threads)
    }

    /// Every frame's diagnostics (those kept: `keeping_history`).
    #[getter]
    fn diagnostics(&self) -> PyResult<Vec<PyFrameDiagnostics>> {
        self.inner
            .diagnostics()
            .iter()
            .map(|d| PyFrameDiagnostics::new(d, self.encoding_in_matching))
            .collect()
    }

    /// The newest frame's diagnostics, None before the first scan.
    #[getter]
    fn last_diagnostics(&self) -> PyResult<Option<PyFrameDiagnostics>> {
        self.inner
            .diagnostics()
            .last()
            .map(|d| PyFrameDiagnostics::new(d, self.encoding_in_matching))
            .transpose()
    }

    /// The reflectance scale chosen on the first matched scan, as the config names it ("unit", "0-255",
    /// "0-65535", or "none": not used), None before it.
    #[getter]
    fn reflectance_scale(&self) -> Option<String> {
        let scale = self.inner.reflectance_scale()?;
        Some(scale.name().to_string())
    }

    /// The network's input `[2, H, W]` (range, reflectance) of a scan (N×4, or N×3 without reflectance) and
    /// its range image `[H, W]` (Eq. 1), the reflectance on the scale the odometry chose (before the first
    /// scan, the one it would choose); nothing is decided by it.
    fn network_image<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
    ) -> PyResult<NetworkImage<'py>> {
        let (cloud, has_reflectance) = scan_cloud("points", points)?;
        let inner = &self.inner;
        let (image, range) = run(py, self.threads, || {
            inner.network_image(Scan {
                has_reflectance,
                ..Scan::new(&cloud)
            })
        })?;
        let cylinder = inner.matcher().cylinder();
        let (height, width) = (cylinder.height, cylinder.width);
        Ok((
            PyArray1::from_vec(py, image).reshape([2, height, width])?,
            PyArray1::from_vec(py, range).reshape([height, width])?,
        ))
    }

    /// Whether the range-only model runs in place of the model (from the first scan without usable
    /// reflectance on).
    #[getter]
    fn runs_range_only(&self) -> bool {
        self.inner.runs_range_only()
    }

    /// The config it runs with, as JSON (`dmlo run`'s `config.json` format).
    #[getter]
    fn config_json(&self) -> String {
        self.inner.config().to_json()
    }

    fn __len__(&self) -> usize {
        self.inner.pose_matrices().len()
    }

    fn __repr__(&self) -> String {
        format!("Odometry(scans={})", self.inner.pose_matrices().len())
    }
}

/// A scan `name` given as N×4 (x, y, z, reflectance) or N×3 (no reflectance) float32 or float64, as the
/// crate reads it (N×3 with a placeholder reflectance), and whether it has a reflectance.
fn scan_cloud(name: &str, points: &Bound<'_, PyAny>) -> PyResult<(Vec<[f32; 4]>, bool)> {
    let (array, columns) = named_scan_points(name, points)?;
    let data = array.f32_data();
    let cloud = data
        .chunks_exact(columns)
        .map(|p| [p[0], p[1], p[2], if columns == 4 { p[3] } else { 0.0 }])
        .collect();
    Ok((cloud, columns == 4))
}

/// A scan's timestamp: a finite number (not a boolean, not a string).
fn seconds(timestamp: &Bound<'_, PyAny>) -> PyResult<f64> {
    let refused = || {
        PyValueError::new_err(format!(
            "timestamp: expected a finite number (seconds), got {}",
            timestamp
                .repr()
                .map_or_else(|_| "?".into(), |r| r.to_string())
        ))
    };
    if timestamp.is_instance_of::<pyo3::types::PyBool>()
        || timestamp.is_instance_of::<pyo3::types::PyString>()
    {
        return Err(refused());
    }
    let value: f64 = timestamp.extract().map_err(|_| refused())?;
    if value.is_finite() {
        Ok(value)
    } else {
        Err(refused())
    }
}
