#![forbid(unsafe_code)]
//! Ray casting for the LiDAR simulator: a [`Scene`] of analytic primitives (triangles, oriented boxes,
//! vertical cylinders, axis-aligned ellipsoids) behind a bounding volume hierarchy, cast with rayon.
//!
//! The acceleration structure is our own binned-SAH BVH (`bvh`) rather than a crate such as `parry3d`:
//! the simulator needs only "closest hit along a ray" over four primitive kinds, and a ~200-line BVH over
//! `f64` geometry keeps the crate's dependency tree small, is exact at the kilometre coordinates of a long
//! drive (world frames are not re-centred), and casts a 64 × 2083 scan in tens of milliseconds.
//!
//! A scene knows only geometry. Callers keep per-primitive attributes (semantic class, instance id,
//! albedo) in arrays indexed by [`Hit::primitive`], the primitive's position in the list given to
//! [`Scene::new`].
//!
//! Results do not depend on the number of threads: every ray is an independent pure computation.

mod bvh;
mod primitives;

use nalgebra::{Matrix4, Point3, Vector3};
use rayon::prelude::*;

pub use primitives::{Ellipsoid, OrientedBox, Primitive, Triangle, VerticalCylinder};

use crate::{Error, Result};

/// Most rays one scan may have (64 × 2083 is 133k).
pub const MAX_SCAN_RAYS: usize = 20_000_000;

/// The closest surface a ray met.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance from the ray origin along the unit direction, in metres.
    pub range: f64,
    /// Index of the primitive hit, in the order given to [`Scene::new`].
    pub primitive: u32,
    /// `|cos|` of the angle between the ray and the surface normal (1 = head-on, 0 = grazing).
    pub cos_incidence: f64,
}

/// A static set of primitives with a BVH over them, ready for ray casting.
#[derive(Debug, Clone)]
pub struct Scene {
    primitives: Vec<Primitive>,
    /// The primitives in BVH leaf order, so a leaf's primitives are contiguous in memory.
    slots: Vec<Primitive>,
    bvh: bvh::Bvh,
}

impl Scene {
    /// Validates the primitives (finite values, positive sizes, orthonormal box rotations, non-degenerate
    /// triangles) and builds the BVH. An empty scene is allowed: every ray misses.
    pub fn new(primitives: Vec<Primitive>) -> Result<Self> {
        for (index, primitive) in primitives.iter().enumerate() {
            primitive.validate().map_err(|reason| {
                Error::invalid(
                    "primitives",
                    format!("primitive {index} ({}): {reason}", primitive.kind()),
                )
            })?;
        }
        if primitives.len() > u32::MAX as usize {
            return Err(Error::invalid(
                "primitives",
                "more than 2^32 - 1 primitives",
            ));
        }
        let bounds: Vec<_> = primitives.iter().map(Primitive::bounds).collect();
        let bvh = bvh::Bvh::build(&bounds);
        let slots = bvh
            .order()
            .iter()
            .map(|&i| primitives[i as usize])
            .collect();
        Ok(Self {
            primitives,
            slots,
            bvh,
        })
    }

    /// Number of primitives.
    pub fn len(&self) -> usize {
        self.primitives.len()
    }

    /// Whether the scene has no primitive.
    pub fn is_empty(&self) -> bool {
        self.primitives.is_empty()
    }

    /// The primitives in their original order.
    pub fn primitives(&self) -> &[Primitive] {
        &self.primitives
    }

    /// Closest hit of one ray within `(0, max_range]`; `direction` must be a unit vector (not checked
    /// here: the batch methods normalise and validate).
    pub fn cast_ray(
        &self,
        origin: &Point3<f64>,
        direction: &Vector3<f64>,
        max_range: f64,
    ) -> Option<Hit> {
        self.cast_ray_with(&mut Vec::new(), origin, direction, max_range)
    }

    /// [`Scene::cast_ray`] reusing a traversal stack (saves an allocation per ray in batches).
    fn cast_ray_with(
        &self,
        stack: &mut Vec<(u32, f64)>,
        origin: &Point3<f64>,
        direction: &Vector3<f64>,
        max_range: f64,
    ) -> Option<Hit> {
        let slots = &self.slots;
        let (range, slot) =
            self.bvh
                .closest(stack, origin, direction, max_range, |slot, t_max| {
                    slots[slot].intersect(origin, direction, t_max)
                })?;
        let point = origin + direction * range;
        let normal = slots[slot].normal_at(&point);
        let primitive = self.bvh.order()[slot];
        Some(Hit {
            range,
            primitive,
            cos_incidence: normal.dot(direction).abs().min(1.0),
        })
    }

    /// Casts one ray per `(origin, direction)` pair in parallel. Directions are normalised; a zero or
    /// non-finite direction or origin, or a mismatch in lengths, is an error.
    pub fn cast(
        &self,
        origins: &[Point3<f64>],
        directions: &[Vector3<f64>],
        max_range: f64,
    ) -> Result<Vec<Option<Hit>>> {
        check_max_range(max_range)?;
        if origins.len() != directions.len() {
            return Err(Error::invalid(
                "directions",
                format!(
                    "{} directions for {} origins",
                    directions.len(),
                    origins.len()
                ),
            ));
        }
        if let Some(i) = origins
            .iter()
            .position(|o| !o.coords.iter().all(|v| v.is_finite()))
        {
            return Err(Error::invalid("origins", format!("row {i} is not finite")));
        }
        let mut units = Vec::with_capacity(directions.len());
        for (i, d) in directions.iter().enumerate() {
            let norm = d.norm();
            if !norm.is_finite() || norm < 1e-12 {
                return Err(Error::invalid(
                    "directions",
                    format!("row {i} is zero or not finite"),
                ));
            }
            units.push(d / norm);
        }
        Ok(origins
            .par_iter()
            .zip(units.par_iter())
            .with_min_len(256)
            .map_init(Vec::new, |stack, (o, d)| {
                self.cast_ray_with(stack, o, d, max_range)
            })
            .collect())
    }

    /// Casts a full revolution of a spinning LiDAR at `pose` (`T_world_lidar`, a rigid 4×4 transform):
    /// one ray per (beam, azimuth column), row-major `elevations_deg.len() × azimuth_count`, in the
    /// directions of [`scan_directions`]. All rays start at the sensor origin at the same instant (no
    /// motion distortion within a sweep).
    pub fn cast_scan(
        &self,
        pose: &Matrix4<f64>,
        elevations_deg: &[f64],
        azimuth_count: usize,
        max_range: f64,
    ) -> Result<Vec<Option<Hit>>> {
        self.cast_scan_per_column(
            std::slice::from_ref(pose),
            elevations_deg,
            azimuth_count,
            max_range,
        )
    }

    /// [`Scene::cast_scan`] with one pose per azimuth column (`column_poses.len() == azimuth_count`), for a
    /// sensor that moves while it spins (motion distortion); a single pose is used for every column.
    pub fn cast_scan_per_column(
        &self,
        column_poses: &[Matrix4<f64>],
        elevations_deg: &[f64],
        azimuth_count: usize,
        max_range: f64,
    ) -> Result<Vec<Option<Hit>>> {
        check_max_range(max_range)?;
        if column_poses.len() != 1 && column_poses.len() != azimuth_count {
            return Err(Error::invalid(
                "pose",
                format!(
                    "need 1 or azimuth_count = {azimuth_count} poses, got {}",
                    column_poses.len()
                ),
            ));
        }
        for pose in column_poses {
            check_rigid(pose)?;
        }
        let local = scan_directions(elevations_deg, azimuth_count)?;
        let frames: Vec<(nalgebra::Matrix3<f64>, Point3<f64>)> = column_poses
            .iter()
            .map(|p| {
                (
                    p.fixed_view::<3, 3>(0, 0).into_owned(),
                    Point3::from(p.fixed_view::<3, 1>(0, 3).into_owned()),
                )
            })
            .collect();
        Ok(local
            .par_iter()
            .enumerate()
            .with_min_len(256)
            .map_init(Vec::new, |stack, (i, d)| {
                let (rotation, origin) = &frames[if frames.len() == 1 {
                    0
                } else {
                    i % azimuth_count
                }];
                let world = (rotation * d).normalize();
                self.cast_ray_with(stack, origin, &world, max_range)
            })
            .collect())
    }
}

/// Unit ray directions in the LiDAR frame (x forward, y left, z up) for a spinning sensor, row-major
/// `elevations_deg.len() × azimuth_count`: row `i` has elevation `elevations_deg[i]`, column `j` has
/// azimuth `θ_j = 180° − 360°·j / azimuth_count` (column 0 looks backwards, the sweep runs clockwise
/// seen from above, as a Velodyne spins, passing straight ahead at the middle column).
pub fn scan_directions(elevations_deg: &[f64], azimuth_count: usize) -> Result<Vec<Vector3<f64>>> {
    if elevations_deg.is_empty() {
        return Err(Error::invalid("elevations_deg", "is empty"));
    }
    if let Some(i) = elevations_deg
        .iter()
        .position(|e| !e.is_finite() || e.abs() >= 90.0)
    {
        return Err(Error::invalid(
            "elevations_deg",
            format!("entry {i} is not finite or not in (-90, 90)"),
        ));
    }
    if azimuth_count == 0 {
        return Err(Error::invalid("azimuth_count", "must be positive"));
    }
    // A guard against typos such as an extra zero or two: a real sensor has well under a million rays.
    if elevations_deg.len().saturating_mul(azimuth_count) > MAX_SCAN_RAYS {
        return Err(Error::invalid(
            "azimuth_count",
            format!(
                "{} beams × {azimuth_count} columns exceeds {MAX_SCAN_RAYS} rays",
                elevations_deg.len()
            ),
        ));
    }
    let mut directions = Vec::with_capacity(elevations_deg.len() * azimuth_count);
    for elevation in elevations_deg {
        let (sin_e, cos_e) = elevation.to_radians().sin_cos();
        for j in 0..azimuth_count {
            let azimuth =
                std::f64::consts::PI - std::f64::consts::TAU * j as f64 / azimuth_count as f64;
            let (sin_a, cos_a) = azimuth.sin_cos();
            directions.push(Vector3::new(cos_e * cos_a, cos_e * sin_a, sin_e));
        }
    }
    Ok(directions)
}

fn check_max_range(max_range: f64) -> Result<()> {
    if !(max_range.is_finite() && max_range > 0.0) {
        return Err(Error::invalid(
            "max_range",
            format!("must be positive and finite, got {max_range}"),
        ));
    }
    Ok(())
}

fn check_rigid(pose: &Matrix4<f64>) -> Result<()> {
    if !pose.iter().all(|v| v.is_finite()) {
        return Err(Error::invalid("pose", "has non-finite entries"));
    }
    let rotation = pose.fixed_view::<3, 3>(0, 0);
    let error = (rotation.transpose() * rotation - nalgebra::Matrix3::identity())
        .abs()
        .max();
    let bottom_ok =
        (pose[(3, 0)].abs() + pose[(3, 1)].abs() + pose[(3, 2)].abs() + (pose[(3, 3)] - 1.0).abs())
            < 1e-9;
    if error > 1e-6 || rotation.determinant() < 0.0 || !bottom_ok {
        return Err(Error::invalid(
            "pose",
            "is not a rigid transform (orthonormal rotation, last row 0 0 0 1)",
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests;
