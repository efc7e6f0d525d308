//! Binding of the odometry's per-frame state (`crate::odometry`): the frame clock and the
//! constant-velocity motion model with its judgement of each pair, which `dmlo.Odometry` runs on.

use numpy::PyArray2;
use pyo3::prelude::*;

use crate::odometry::clock::FrameClock;
use crate::odometry::config::schema::Named;
use crate::odometry::config::OdometryConfig;
use crate::odometry::motion::{MotionLimits, MotionModel, PairEvidence};

use super::convert::{counts, matrix4_to_numpy, points3, rigid_matrix};
use super::pool::run;
use super::registration::refit_kind;

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyFrameClock>()?;
    m.add_class::<PyMotionModel>()?;
    m.add_function(wrap_pyfunction!(odometry_config_json, m)?)?;
    m.add_function(wrap_pyfunction!(odometry_config_schema, m)?)?;
    Ok(())
}

/// The odometry's config as the crate reads it (`odometry::config::OdometryConfig`): `text` (a config
/// file's JSON, Python's `Infinity` included) parsed and checked by the crate and written back, every key
/// with its value; None: the crate's defaults. ConfigError names every bad key.
#[pyfunction]
#[pyo3(signature = (text = None))]
fn odometry_config_json(text: Option<&str>) -> PyResult<String> {
    let config = match text {
        Some(text) => OdometryConfig::from_json(text)?,
        None => OdometryConfig::default(),
    };
    Ok(config.to_json())
}

/// The schema of the odometry's config as JSON (`OdometryConfig::schema_json`): every section and setting
/// with its type, rule, default and doc, from the crate's one declaration of each.
#[pyfunction]
fn odometry_config_schema() -> String {
    OdometryConfig::schema_json()
}

/// Frame numbers from scan timestamps: one per scan, or as many sensor periods as a scan's timestamp
/// lies after the last timestamped one (the period: the median of the recent intervals between
/// consecutive scans). `frame` is the newest scan's, −1 before the first.
#[pyclass(name = "FrameClock", module = "dmlo_rs._dmlo_rs")]
pub struct PyFrameClock {
    inner: FrameClock,
}

#[pymethods]
impl PyFrameClock {
    #[new]
    fn new() -> Self {
        PyFrameClock {
            inner: FrameClock::new(),
        }
    }

    #[getter]
    fn frame(&self) -> i64 {
        self.inner
            .frame()
            .map_or(-1, |frame| i64::try_from(frame).unwrap_or(i64::MAX))
    }

    /// The sensor period in the timestamps' unit; None until two consecutive scans had timestamps.
    #[getter]
    fn period(&self) -> Option<f64> {
        self.inner.period()
    }

    /// The next scan's frame number and whether its `timestamp` (any unit, increasing; None: one frame
    /// on) was not after the previous one's (then it is taken for the next frame). A timestamp that is
    /// not finite raises ValueError and changes nothing.
    #[pyo3(signature = (timestamp = None))]
    fn advance(&mut self, timestamp: Option<f64>) -> PyResult<(i64, bool)> {
        let tick = self.inner.advance(timestamp)?;
        Ok((
            i64::try_from(tick.frame).unwrap_or(i64::MAX),
            tick.out_of_order,
        ))
    }

    fn __repr__(&self) -> String {
        format!(
            "FrameClock(frame={}, period={:?})",
            self.frame(),
            self.period()
        )
    }
}

/// The constant-velocity motion model (§III-D-c) and the judgement of each pair's motion against it:
/// too few inliers (`min_inliers`) or inliers resting on the road (`min_inlier_votes`) take the
/// prediction; a motion further from it than `max_deviation` m / `max_deviation_deg` ° a frame (within
/// `prediction_horizon` frames) gives way to the solve of the matches that agree with the prediction
/// (within twice `threshold`; `guided_fraction`; solved by `refit` with `range_ratio`), else to the
/// prediction, never twice in a row. Transforms are 4×4: motions `T_tgt_ref`, poses `T_world_lidar`.
#[pyclass(name = "MotionModel", module = "dmlo_rs._dmlo_rs")]
pub struct PyMotionModel {
    inner: MotionModel,
}

#[pymethods]
impl PyMotionModel {
    #[new]
    #[pyo3(signature = (*, min_inliers = 10, min_inlier_votes = 5.0, max_deviation = 0.3,
                        max_deviation_deg = 3.0, guided_fraction = 0.5, prediction_horizon = 20,
                        threshold = 0.1, refit = "point_to_point", range_ratio = 4.0))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        #[pyo3(from_py_with = counts::min_inliers)] min_inliers: usize,
        min_inlier_votes: f64,
        max_deviation: f64,
        max_deviation_deg: f64,
        guided_fraction: f64,
        #[pyo3(from_py_with = counts::prediction_horizon)] prediction_horizon: usize,
        threshold: f64,
        refit: &str,
        range_ratio: f64,
    ) -> PyResult<Self> {
        // The bearing tolerance only chooses RANSAC's inliers; the guided solve has no use for it.
        let refit = refit_kind(refit, range_ratio, 0.0)?;
        let limits = MotionLimits {
            min_inliers,
            min_inlier_votes,
            max_deviation,
            max_deviation_deg,
            guided_fraction,
            prediction_horizon,
            threshold,
            refit,
        };
        limits.validate()?;
        Ok(PyMotionModel {
            inner: MotionModel::new(limits),
        })
    }

    /// The per-frame motion `T_tgt_ref` last measured (the identity before any).
    #[getter]
    fn velocity<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        matrix4_to_numpy(py, self.inner.velocity())
    }

    /// Whether a velocity was measured; until then the prediction is "standing still", a guess.
    #[getter]
    fn measured(&self) -> bool {
        self.inner.is_measured()
    }

    /// Whether the last judged motion was replaced by the prediction as implausible.
    #[getter]
    fn gated_last(&self) -> bool {
        self.inner.gated_last()
    }

    /// The constant-velocity motion `T_tgt_ref` across `frames` frames.
    fn predicted<'py>(
        &self,
        py: Python<'py>,
        #[pyo3(from_py_with = counts::frames)] frames: usize,
    ) -> Bound<'py, PyArray2<f64>> {
        matrix4_to_numpy(py, &self.inner.predicted(frames))
    }

    /// Measures the velocity from two poses `frames` frames apart (consecutive frames only).
    fn update(
        &mut self,
        reference_pose: &Bound<'_, PyAny>,
        pose: &Bound<'_, PyAny>,
        #[pyo3(from_py_with = counts::frames)] frames: usize,
    ) -> PyResult<()> {
        let reference_pose = rigid_matrix("reference_pose", reference_pose)?;
        let pose = rigid_matrix("pose", pose)?;
        self.inner.update(&reference_pose, &pose, frames);
        Ok(())
    }

    /// Whether `motion` lies further from `predicted` than `gap` frames of a car's change of speed allow.
    fn implausible(
        &self,
        motion: &Bound<'_, PyAny>,
        predicted: &Bound<'_, PyAny>,
        #[pyo3(from_py_with = counts::gap)] gap: usize,
    ) -> PyResult<bool> {
        let motion = rigid_matrix("motion", motion)?;
        let predicted = rigid_matrix("predicted", predicted)?;
        Ok(self.inner.implausible(&motion, &predicted, gap))
    }

    /// The motion a frame `gap` frames after its reference takes from its pair (RANSAC's `motion`, its
    /// `num_inliers` and `inlier_votes`, the matches' `source` and `target` points, N×3) and the
    /// constant-velocity `predicted` motion → `(T_tgt_ref, fallback)`, the fallback None for the pair's
    /// own motion, else "constant_velocity", "degenerate_scene", "guided_consensus" or
    /// "implausible_motion".
    #[allow(clippy::too_many_arguments)]
    fn judge<'py>(
        &mut self,
        py: Python<'py>,
        motion: &Bound<'py, PyAny>,
        #[pyo3(from_py_with = counts::num_inliers)] num_inliers: usize,
        inlier_votes: Option<f64>,
        source: &Bound<'py, PyAny>,
        target: &Bound<'py, PyAny>,
        predicted: &Bound<'py, PyAny>,
        #[pyo3(from_py_with = counts::gap)] gap: usize,
    ) -> PyResult<(Bound<'py, PyArray2<f64>>, Option<&'static str>)> {
        let motion = rigid_matrix("motion", motion)?;
        let predicted = rigid_matrix("predicted", predicted)?;
        let (source, target) = (points3("source", source)?, points3("target", target)?);
        if source.len() != target.len() {
            return Err(pyo3::exceptions::PyValueError::new_err(format!(
                "source and target: {} and {} points, expected one target per source",
                source.len(),
                target.len()
            )));
        }
        let model = &mut self.inner;
        let judged = run(py, Some(1), || {
            let pair = PairEvidence::new(motion, num_inliers, inlier_votes, &source, &target);
            Ok(model.judge(&pair, &predicted, gap))
        })?;
        Ok((
            matrix4_to_numpy(py, &judged.motion),
            judged.fallback.map(|fallback| fallback.name()),
        ))
    }

    fn __repr__(&self) -> String {
        format!(
            "MotionModel(measured={}, gated_last={})",
            if self.inner.is_measured() {
                "True"
            } else {
                "False"
            },
            if self.inner.gated_last() {
                "True"
            } else {
                "False"
            }
        )
    }
}
