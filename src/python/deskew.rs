//! Bindings of the motion compensation of a spinning sensor's sweep.

use numpy::ndarray::Array1;
use numpy::{IntoPyArray, PyArray1, PyArray2};
use pyo3::prelude::*;

use super::convert::{image_array, scan_points, transform, vector_f64, Int};
use super::pool::{run, threads};

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(sweep_times, m)?)?;
    m.add_function(wrap_pyfunction!(deskew, m)?)?;
    Ok(())
}

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
