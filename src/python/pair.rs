//! Binding of one pair's motion from the matcher's output (`crate::pair`): the chain `dmlo.Odometry`
//! runs on every pair, in one call.

use numpy::ndarray::{Array1, Array2};
use numpy::{IntoPyArray, PyArray1, PyArray2};
use pyo3::prelude::*;

use crate::coherence::CoherenceConfig;
use crate::pair::{self, PairConfig, PairImages};
use crate::projection::CylinderConfig;
use crate::ransac::RansacConfig;

use super::convert::{
    bool_image, counts, flow_image, image, matrix_to_numpy, point_image, points_to_numpy, Int,
};
use super::pool::{run, threads};
use super::projection::PyCylinderConfig;
use super::registration::refit_kind;

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyPairMotion>()?;
    m.add_function(wrap_pyfunction!(match_pair, m)?)?;
    Ok(())
}

/// Result of `match_pair`: `transform` (4×4 float64 `T_tgt_ref`, the identity when the matches give no
/// motion), the matches' `source` and `target` points (N×3 float64) and reference `cells` (N×2 int64),
/// RANSAC's `inliers` (bool) and `num_inliers`, and with tilt votes `inlier_votes` (the inliers' votes
/// above the floor; None without them).
#[pyclass(name = "PairMotion", module = "dmlo_rs._dmlo_rs", frozen)]
pub struct PyPairMotion {
    #[pyo3(get)]
    transform: Py<PyArray2<f64>>,
    #[pyo3(get)]
    source: Py<PyArray2<f64>>,
    #[pyo3(get)]
    target: Py<PyArray2<f64>>,
    #[pyo3(get)]
    cells: Py<PyArray2<i64>>,
    #[pyo3(get)]
    inliers: Py<PyArray1<bool>>,
    #[pyo3(get)]
    num_inliers: usize,
    #[pyo3(get)]
    inlier_votes: Option<f64>,
}

#[pymethods]
impl PyPairMotion {
    fn __repr__(&self, py: Python<'_>) -> String {
        format!(
            "PairMotion(num_matches={}, num_inliers={})",
            self.inliers.bind(py).len().unwrap_or(0),
            self.num_inliers
        )
    }
}

/// A pair's motion from the matcher's `flow` `[2, H, W]` and `confidence` `[H, W]` between the range
/// images `ref_range` and `tgt_range` (§III-D): the confidence weighted by the flow's coherence
/// (`coherence_px` None: not), the matches decoded to 3D with NMS fused in (the top `max_matches` of
/// radius `nms_radius`, `min_confidence`, cells of `leave_out` `[H, W]` bool left out), with
/// `tilt_votes` each match's vote from the tilt of the surface under it in `ref_points` (`[H, W, 3]`,
/// None: the cells' virtual points; at least `tilt_vote_floor`, None: one vote each) divided by the square
/// root of its `vote_voxel` cube's crowding (None: not), and RANSAC with `ransac_rigid`'s settings.
#[pyfunction]
#[pyo3(signature = (ref_range, tgt_range, flow, confidence, config, *, ref_points = None, leave_out = None,
                    tilt_votes = true, min_confidence = 0.0, nms_radius = 1, max_matches = 1000,
                    coherence_px = Some(0.5), coherence_radius = 2, threshold = 0.1, confidence_level = 0.999,
                    max_iterations = 1000, seed = 0, refit = "ray_noise", range_ratio = 4.0,
                    bearing_threshold_deg = 0.2, tilt_vote_floor = Some(0.05), vote_voxel = Some(2.0),
                    num_threads = None))]
#[allow(clippy::too_many_arguments)]
fn match_pair(
    py: Python<'_>,
    ref_range: &Bound<'_, PyAny>,
    tgt_range: &Bound<'_, PyAny>,
    flow: &Bound<'_, PyAny>,
    confidence: &Bound<'_, PyAny>,
    config: &PyCylinderConfig,
    ref_points: Option<&Bound<'_, PyAny>>,
    leave_out: Option<&Bound<'_, PyAny>>,
    tilt_votes: bool,
    min_confidence: f32,
    #[pyo3(from_py_with = counts::nms_radius)] nms_radius: usize,
    #[pyo3(from_py_with = counts::max_matches)] max_matches: usize,
    coherence_px: Option<f32>,
    #[pyo3(from_py_with = counts::coherence_radius)] coherence_radius: usize,
    threshold: f64,
    confidence_level: f64,
    #[pyo3(from_py_with = counts::max_iterations)] max_iterations: usize,
    #[pyo3(from_py_with = counts::seed)] seed: u64,
    refit: &str,
    range_ratio: f64,
    bearing_threshold_deg: f64,
    tilt_vote_floor: Option<f64>,
    vote_voxel: Option<f64>,
    num_threads: Option<Int>,
) -> PyResult<PyPairMotion> {
    let settings = PairConfig {
        min_confidence,
        nms_radius,
        max_matches,
        coherence: coherence_px.map(|scale_px| CoherenceConfig {
            radius: coherence_radius,
            scale_px,
        }),
        ransac: RansacConfig {
            threshold,
            confidence: confidence_level,
            max_iterations,
            seed,
            refit: refit_kind(refit, range_ratio, bearing_threshold_deg)?,
            ..Default::default()
        },
        tilt_vote_floor,
        vote_voxel,
    };
    let images = FlowImages {
        ref_range,
        tgt_range,
        flow,
        confidence,
        ref_points,
        leave_out,
    };
    pair_from_flow(py, images, &config.inner, &settings, tilt_votes, threads(num_threads)?)
}

/// A pair's images as Python gives them ([`pair_from_flow`]).
pub(super) struct FlowImages<'a, 'py> {
    pub ref_range: &'a Bound<'py, PyAny>,
    pub tgt_range: &'a Bound<'py, PyAny>,
    pub flow: &'a Bound<'py, PyAny>,
    pub confidence: &'a Bound<'py, PyAny>,
    pub ref_points: Option<&'a Bound<'py, PyAny>>,
    pub leave_out: Option<&'a Bound<'py, PyAny>>,
}

/// The pair's motion from a flow (`pair::match_pair`), its images checked against `cylinder`.
pub(super) fn pair_from_flow(
    py: Python<'_>,
    given: FlowImages<'_, '_>,
    cylinder: &CylinderConfig,
    settings: &PairConfig,
    tilt_votes: bool,
    threads: Option<i64>,
) -> PyResult<PyPairMotion> {
    let (ref_range, tgt_range) = (
        image("ref_range", given.ref_range, cylinder)?,
        image("tgt_range", given.tgt_range, cylinder)?,
    );
    let (flow, confidence) = (
        flow_image(given.flow, cylinder)?,
        image("confidence", given.confidence, cylinder)?,
    );
    let ref_points = given
        .ref_points
        .map(|p| point_image("ref_points", p, cylinder))
        .transpose()?;
    let leave_out = given
        .leave_out
        .map(|m| bool_image("leave_out", m, cylinder))
        .transpose()?;
    let (ref_range, tgt_range, flow, confidence) = (
        ref_range.f32_data(),
        tgt_range.f32_data(),
        flow.f32_data(),
        confidence.f32_data(),
    );
    let ref_points = ref_points.as_ref().map(|p| p.f32_data());
    let images = PairImages {
        ref_range: &ref_range,
        tgt_range: &tgt_range,
        flow: &flow,
        confidence: &confidence,
        ref_points: ref_points.as_deref(),
        leave_out: leave_out.as_deref(),
    };
    let motion = run(py, threads, || {
        pair::match_pair(&images, cylinder, settings, tilt_votes)
    })?;
    Ok(PyPairMotion::new(py, motion))
}

impl PyPairMotion {
    /// The crate's pair motion as Python sees it.
    pub(super) fn new(py: Python<'_>, motion: pair::PairMotion) -> Self {
        let cells =
            Array2::from_shape_fn((motion.cells.len(), 2), |(i, j)| motion.cells[i][j] as i64);
        PyPairMotion {
            transform: matrix_to_numpy(py, &motion.transform).unbind(),
            source: points_to_numpy(py, &motion.source).unbind(),
            target: points_to_numpy(py, &motion.target).unbind(),
            cells: cells.into_pyarray(py).unbind(),
            inliers: Array1::from_vec(motion.inliers).into_pyarray(py).unbind(),
            num_inliers: motion.num_inliers,
            inlier_votes: motion.inlier_votes,
        }
    }
}
