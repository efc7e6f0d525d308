//! Bindings of the moving-object network's images and rule (`odometry::moving`), for `dmlo.Odometry`'s
//! detector and its training: one implementation with the crate's odometry.

use numpy::{IntoPyArray, PyArray1, PyArray2};
use pyo3::prelude::*;

use crate::odometry::moving;

use super::convert::{floats, image_array, scan_points, shape_error};
use super::pool::run;
use super::projection::PyCylinderConfig;

/// Two float32 images.
type Images<'py> = (Bound<'py, PyArray2<f32>>, Bound<'py, PyArray2<f32>>);

/// The moving-object network's two input images of a scan: the range of each cell's kept point (Eq. 1)
/// and its height z, both `[H, W]` float32 with 0 where a cell is empty. `points`: N×4 (x, y, z,
/// reflectance) float32.
#[pyfunction]
#[pyo3(signature = (points, config))]
fn moving_network_images<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    config: &PyCylinderConfig,
) -> PyResult<Images<'py>> {
    let (array, columns) = scan_points(points)?;
    if columns != 4 {
        return Err(shape_error(
            "points",
            "N×4 (x, y, z, reflectance)",
            array.shape(),
        ));
    }
    let data = array.f32_data();
    let data: &[f32] = &data;
    let cylinder = config.inner;
    let (range, height) = run(py, None, || {
        moving::network_images(data, columns, &cylinder)
    })?;
    let (h, w) = (cylinder.height, cylinder.width);
    Ok((
        image_array(h, w, range)?.into_pyarray(py),
        image_array(h, w, height)?.into_pyarray(py),
    ))
}

/// The points (one flag each) in cells whose moving probability (`[H, W]` of `config`'s image, the
/// network's answer) exceeds `threshold` (compared in float32); points outside the image, at the origin or
/// non-finite are not flagged. `points`: N×3 or N×4 float32 → bool array of N.
#[pyfunction]
#[pyo3(signature = (points, probability, config, threshold))]
fn flagged_points<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    probability: &Bound<'py, PyAny>,
    config: &PyCylinderConfig,
    threshold: f64,
) -> PyResult<Bound<'py, PyArray1<bool>>> {
    let (array, columns) = scan_points(points)?;
    let probability = floats("probability", probability)?;
    let cylinder = config.inner;
    let expected = [cylinder.height, cylinder.width];
    if probability.shape() != expected {
        let wanted = format!("{} × {} (the image)", cylinder.height, cylinder.width);
        return Err(shape_error("probability", &wanted, probability.shape()));
    }
    let (data, probability) = (array.f32_data(), probability.f32_data());
    let (data, probability): (&[f32], &[f32]) = (&data, &probability);
    let flags = run(py, None, || {
        moving::flagged_points(data, columns, probability, &cylinder, threshold)
    })?;
    Ok(flags.into_pyarray(py))
}

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(moving_network_images, m)?)?;
    m.add_function(wrap_pyfunction!(flagged_points, m)?)?;
    Ok(())
}
