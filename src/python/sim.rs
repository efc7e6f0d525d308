//! Bindings of the simulator's ray casting: `RayScene` from numpy arrays of primitive parameters,
//! casting arbitrary rays or a full LiDAR revolution with the GIL released.

use nalgebra::{Matrix3, Matrix4, Point3, Vector3};
use numpy::ndarray::{Array1, Array2, ArrayView2};
use numpy::{
    IntoPyArray, PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3, PyReadonlyArrayDyn,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use super::convert::{count, Int};

use crate::raycast::{Ellipsoid, Hit, OrientedBox, Primitive, Scene, Triangle, VerticalCylinder};

use super::pool::run;

type CastResult<'py, D> = (
    Bound<'py, numpy::PyArray<f64, D>>,
    Bound<'py, numpy::PyArray<i64, D>>,
    Bound<'py, numpy::PyArray<f32, D>>,
);

fn value_error(argument: &str, reason: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(format!("{argument}: {reason}"))
}

fn check_columns(
    argument: &str,
    array: &ArrayView2<'_, f64>,
    columns: usize,
    layout: &str,
) -> PyResult<()> {
    if array.ncols() != columns {
        return Err(value_error(
            argument,
            format!(
                "expected shape (N, {columns}) [{layout}], got {:?}",
                array.shape()
            ),
        ));
    }
    Ok(())
}

/// A static scene of analytic primitives with a BVH, for LiDAR ray casting.
///
/// Primitives are numbered in the order triangles, boxes, cylinders, ellipsoids (each in its array's row
/// order); `cast`/`cast_scan` return that number for every hit (−1 for a miss), so per-primitive labels
/// and albedos are plain numpy look-ups.
#[pyclass(module = "dmlo_rs._dmlo_rs", frozen)]
pub struct RayScene {
    scene: Scene,
}

#[pymethods]
impl RayScene {
    /// `triangles` (N,3,3) vertices; `boxes` (N,15) centre xyz, row-major 3×3 rotation whose columns are
    /// the box axes, half extents xyz; `cylinders` (N,5) base centre xyz, height, radius (vertical axis);
    /// `ellipsoids` (N,6) centre xyz, radii xyz (world-axis aligned). All float64 metres.
    #[new]
    #[pyo3(signature = (triangles=None, boxes=None, cylinders=None, ellipsoids=None))]
    fn new(
        py: Python<'_>,
        triangles: Option<PyReadonlyArray3<'_, f64>>,
        boxes: Option<PyReadonlyArray2<'_, f64>>,
        cylinders: Option<PyReadonlyArray2<'_, f64>>,
        ellipsoids: Option<PyReadonlyArray2<'_, f64>>,
    ) -> PyResult<Self> {
        let mut primitives = Vec::new();
        if let Some(triangles) = &triangles {
            let t = triangles.as_array();
            if t.shape()[1] != 3 || t.shape()[2] != 3 {
                return Err(value_error(
                    "triangles",
                    format!("expected shape (N, 3, 3), got {:?}", t.shape()),
                ));
            }
            for tri in t.outer_iter() {
                let v = |k: usize| Point3::new(tri[[k, 0]], tri[[k, 1]], tri[[k, 2]]);
                primitives.push(Primitive::Triangle(Triangle {
                    vertices: [v(0), v(1), v(2)],
                }));
            }
        }
        if let Some(boxes) = &boxes {
            let b = boxes.as_array();
            check_columns(
                "boxes",
                &b,
                15,
                "centre xyz, rotation row-major 9, half extents xyz",
            )?;
            for row in b.outer_iter() {
                primitives.push(Primitive::Box(OrientedBox {
                    center: Point3::new(row[0], row[1], row[2]),
                    rotation: Matrix3::from_row_slice(
                        &row.iter().copied().skip(3).take(9).collect::<Vec<_>>(),
                    ),
                    half_extents: Vector3::new(row[12], row[13], row[14]),
                }));
            }
        }
        if let Some(cylinders) = &cylinders {
            let c = cylinders.as_array();
            check_columns("cylinders", &c, 5, "base centre xyz, height, radius")?;
            for row in c.outer_iter() {
                primitives.push(Primitive::Cylinder(VerticalCylinder {
                    base: Point3::new(row[0], row[1], row[2]),
                    height: row[3],
                    radius: row[4],
                }));
            }
        }
        if let Some(ellipsoids) = &ellipsoids {
            let e = ellipsoids.as_array();
            check_columns("ellipsoids", &e, 6, "centre xyz, radii xyz")?;
            for row in e.outer_iter() {
                primitives.push(Primitive::Ellipsoid(Ellipsoid {
                    center: Point3::new(row[0], row[1], row[2]),
                    radii: Vector3::new(row[3], row[4], row[5]),
                }));
            }
        }
        let scene = run(py, None, || Scene::new(primitives))?;
        Ok(Self { scene })
    }

    /// Number of primitives.
    fn __len__(&self) -> usize {
        self.scene.len()
    }

    /// Closest hit of each ray (`origins`, `directions`: (N,3) float64; directions are normalised) within
    /// `max_range` metres. Returns `(ranges float64 (N,), primitive int64 (N,), cos_incidence float32 (N,))`;
    /// a miss has range `inf`, primitive −1 and cos 0.
    fn cast<'py>(
        &self,
        py: Python<'py>,
        origins: PyReadonlyArray2<'py, f64>,
        directions: PyReadonlyArray2<'py, f64>,
        max_range: f64,
    ) -> PyResult<CastResult<'py, numpy::Ix1>> {
        let o = origins.as_array();
        let d = directions.as_array();
        check_columns("origins", &o, 3, "x y z")?;
        check_columns("directions", &d, 3, "x y z")?;
        let origins: Vec<Point3<f64>> = o
            .outer_iter()
            .map(|r| Point3::new(r[0], r[1], r[2]))
            .collect();
        let directions: Vec<Vector3<f64>> = d
            .outer_iter()
            .map(|r| Vector3::new(r[0], r[1], r[2]))
            .collect();
        let hits = run(py, None, || {
            self.scene.cast(&origins, &directions, max_range)
        })?;
        let (ranges, primitives, cosines) = unzip_hits(&hits);
        Ok((
            Array1::from(ranges).into_pyarray(py),
            Array1::from(primitives).into_pyarray(py),
            Array1::from(cosines).into_pyarray(py),
        ))
    }

    /// One LiDAR revolution from `pose` (4×4 float64 `T_world_lidar`, or (azimuth_count,4,4) with one pose
    /// per column for a sensor moving during the sweep): rays of elevation
    /// `elevations_deg[i]` (row i) and azimuth `180° − 360°·j/azimuth_count` (column j) in the LiDAR frame.
    /// Returns `(ranges float64 (H,W), primitive int64 (H,W), cos_incidence float32 (H,W))`, misses as in `cast`.
    fn cast_scan<'py>(
        &self,
        py: Python<'py>,
        pose: PyReadonlyArrayDyn<'py, f64>,
        elevations_deg: PyReadonlyArray1<'py, f64>,
        azimuth_count: Int,
        max_range: f64,
    ) -> PyResult<CastResult<'py, numpy::Ix2>> {
        let azimuth_count = count("azimuth_count", azimuth_count)?;
        let p = pose.as_array();
        let poses: Vec<Matrix4<f64>> = match p.shape() {
            [4, 4] => vec![Matrix4::from_fn(|r, c| p[[r, c]])],
            [n, 4, 4] => (0..*n)
                .map(|k| Matrix4::from_fn(|r, c| p[[k, r, c]]))
                .collect(),
            shape => {
                return Err(value_error(
                    "pose",
                    format!("expected shape (4, 4) or (azimuth_count, 4, 4), got {shape:?}"),
                ));
            }
        };
        let elevations: Vec<f64> = elevations_deg.as_array().iter().copied().collect();
        let rows = elevations.len();
        let hits = run(py, None, || {
            self.scene
                .cast_scan_per_column(&poses, &elevations, azimuth_count, max_range)
        })?;
        let (ranges, primitives, cosines) = unzip_hits(&hits);
        let shape = (rows, azimuth_count);
        let reshape = |e: numpy::ndarray::ShapeError| value_error("azimuth_count", e);
        Ok((
            Array2::from_shape_vec(shape, ranges)
                .map_err(reshape)?
                .into_pyarray(py),
            Array2::from_shape_vec(shape, primitives)
                .map_err(reshape)?
                .into_pyarray(py),
            Array2::from_shape_vec(shape, cosines)
                .map_err(reshape)?
                .into_pyarray(py),
        ))
    }
}

fn unzip_hits(hits: &[Option<Hit>]) -> (Vec<f64>, Vec<i64>, Vec<f32>) {
    let mut ranges = Vec::with_capacity(hits.len());
    let mut primitives = Vec::with_capacity(hits.len());
    let mut cosines = Vec::with_capacity(hits.len());
    for hit in hits {
        match hit {
            Some(h) => {
                ranges.push(h.range);
                primitives.push(i64::from(h.primitive));
                cosines.push(h.cos_incidence as f32);
            }
            None => {
                ranges.push(f64::INFINITY);
                primitives.push(-1);
                cosines.push(0.0);
            }
        }
    }
    (ranges, primitives, cosines)
}

/// Unit ray directions (H·W, 3) float64 in the LiDAR frame of a `cast_scan` with the same arguments,
/// row-major (row = beam, column = azimuth step).
#[pyfunction]
fn lidar_scan_directions<'py>(
    py: Python<'py>,
    elevations_deg: PyReadonlyArray1<'py, f64>,
    azimuth_count: Int,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let azimuth_count = count("azimuth_count", azimuth_count)?;
    let elevations: Vec<f64> = elevations_deg.as_array().iter().copied().collect();
    let directions = crate::raycast::scan_directions(&elevations, azimuth_count)?;
    let flat: Vec<f64> = directions.iter().flat_map(|d| [d.x, d.y, d.z]).collect();
    Ok(Array2::from_shape_vec((directions.len(), 3), flat)
        .map_err(|e| value_error("elevations_deg", e))?
        .into_pyarray(py))
}

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<RayScene>()?;
    m.add_function(wrap_pyfunction!(lidar_scan_directions, m)?)?;
    Ok(())
}
