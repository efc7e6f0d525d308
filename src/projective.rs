#![forbid(unsafe_code)]
//! Projective point-to-plane ICP on scans' point images: the alignment of a pair that barely moved.
//!
//! NDT compares a scan with the normal distributions of a map's voxels. Between two scans a few
//! centimetres apart the reference's ground rings lie where the target's own would if the car stood
//! still, so NDT holds a creeping pair together; and its voxels leave millimetres of bias even for a scan
//! aligned with itself. A point's distance to the plane of the reference's surface has neither fault:
//! along the road a ring point slides freely, and a scan aligned with itself has every residual exactly
//! zero. The correspondences come from the projection (SuMa's projective association: each target
//! point, moved into the reference frame, meets the reference cell it falls in), so no search structure
//! is needed; they hold while the pair moved less than the cells' spacing on the surfaces.

use nalgebra::{
    Isometry3, Matrix6, Point3, SymmetricEigen, Translation3, UnitQuaternion, Vector3, Vector6,
};
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::projection::{point_cells, CylinderConfig};
use crate::surface::check_cell_points;

/// Settings of [`point_to_plane`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PointToPlaneConfig {
    /// Gauss–Newton rounds at most.
    pub iterations: usize,
    /// Correspondences farther apart than this (metres) are not the same surface.
    pub max_distance: f64,
    /// Residuals beyond this (metres) weigh less (Huber).
    pub huber: f64,
    /// Directions of a step with less than this fraction of the best one's information keep the
    /// estimate (a bare plane fixes only its normal).
    pub min_information: f64,
    /// A neighbour whose range differs from the cell's by more than this fraction lies across a depth
    /// edge: no normal there.
    pub edge_range_ratio: f64,
}

impl Default for PointToPlaneConfig {
    fn default() -> Self {
        Self {
            iterations: 10,
            max_distance: 0.3,
            huber: 0.02,
            min_information: 1e-5,
            edge_range_ratio: 0.1,
        }
    }
}

impl PointToPlaneConfig {
    pub fn validate(&self) -> Result<()> {
        if self.iterations == 0 {
            return Err(Error::invalid("iterations", "must be at least 1, got 0"));
        }
        for (name, value) in [
            ("max_distance", self.max_distance),
            ("huber", self.huber),
            ("edge_range_ratio", self.edge_range_ratio),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err(Error::invalid(
                    name,
                    format!("must be a positive number, got {value}"),
                ));
            }
        }
        if !(0.0..1.0).contains(&self.min_information) {
            return Err(Error::invalid(
                "min_information",
                format!("must lie in [0, 1), got {}", self.min_information),
            ));
        }
        Ok(())
    }
}

fn cell_point(points: &[f32], cell: usize) -> Option<Vector3<f64>> {
    let p = &points[3 * cell..3 * cell + 3];
    p[0].is_finite()
        .then(|| Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])))
}

/// The unit normal of the surface at each cell of a point image (see [`check_cell_points`]), from its
/// four neighbours (columns wrap round, rows do not): the cross product of the horizontal and the
/// vertical difference. None where a neighbour is missing or lies across a depth edge
/// (`edge_range_ratio`).
pub fn surface_normals(
    points: &[f32],
    config: &CylinderConfig,
    edge_range_ratio: f64,
) -> Result<Vec<Option<Vector3<f64>>>> {
    check_cell_points(points, config)?;
    let (height, width) = (config.height, config.width);
    Ok((0..height * width)
        .into_par_iter()
        .map(|cell| {
            let (row, col) = (cell / width, cell % width);
            let centre = cell_point(points, cell)?;
            if row == 0 || row + 1 == height {
                return None;
            }
            let right = cell_point(points, row * width + (col + 1) % width)?;
            let left = cell_point(points, row * width + (col + width - 1) % width)?;
            let below = cell_point(points, cell + width)?;
            let above = cell_point(points, cell - width)?;
            let range = centre.norm();
            if [right, left, below, above]
                .iter()
                .any(|n| (n.norm() - range).abs() >= edge_range_ratio * range)
            {
                return None;
            }
            let normal = (right - left).cross(&(below - above));
            let length = normal.norm();
            (length > 0.0).then(|| normal / length)
        })
        .collect())
}

/// `T_tgt_ref` refined by projective point-to-plane ICP of the `target` point image's points against the
/// `reference` point image (both see [`check_cell_points`], their own sensor frames), from `start`.
///
/// Each round moves the target's points into the reference frame, finds the reference cell each falls in
/// ([`point_cells`]) and solves the small motion that brings them onto the planes of those cells
/// (Gauss–Newton, Huber weights); directions with too little information keep the estimate. `None` when
/// the first round finds fewer than six correspondences.
pub fn point_to_plane(
    reference: &[f32],
    target: &[f32],
    cylinder: &CylinderConfig,
    start: &Isometry3<f64>,
    config: &PointToPlaneConfig,
) -> Result<Option<Isometry3<f64>>> {
    config.validate()?;
    check_cell_points(target, cylinder)?;
    let normals = surface_normals(reference, cylinder, config.edge_range_ratio)?;
    let points: Vec<Vector3<f64>> = (0..cylinder.height * cylinder.width)
        .filter_map(|cell| cell_point(target, cell))
        .collect();
    let mut pose = start.inverse(); // the target's pose in the reference frame
    let mut moved = vec![0.0_f32; 3 * points.len()];
    for round in 0..config.iterations {
        // A point, not a vector: the translation applies.
        let placed: Vec<Vector3<f64>> = points
            .par_iter()
            .map(|p| pose.transform_point(&Point3::from(*p)).coords)
            .collect();
        for (out, p) in moved.chunks_exact_mut(3).zip(&placed) {
            out.copy_from_slice(&[p.x as f32, p.y as f32, p.z as f32]);
        }
        let cells = point_cells(&moved, 3, cylinder)?;
        let (information, gradient, count) = placed
            .par_iter()
            .zip(cells.par_iter())
            .filter_map(|(q, &cell)| {
                let cell = usize::try_from(cell).ok()?;
                let normal = normals[cell]?;
                let offset = q - cell_point(reference, cell)?;
                if offset.norm() >= config.max_distance {
                    return None;
                }
                let residual = normal.dot(&offset);
                let weight = config.huber / residual.abs().max(config.huber);
                let rotation = q.cross(&normal);
                let jacobian = Vector6::new(
                    rotation.x, rotation.y, rotation.z, normal.x, normal.y, normal.z,
                );
                Some((
                    jacobian * jacobian.transpose() * weight,
                    jacobian * (weight * residual),
                    1_usize,
                ))
            })
            .reduce(
                || (Matrix6::zeros(), Vector6::zeros(), 0),
                |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2),
            );
        if count < 6 {
            if round == 0 {
                return Ok(None);
            }
            break;
        }
        let eigen = SymmetricEigen::new(information);
        let largest = eigen.eigenvalues.max();
        let mut step = Vector6::zeros();
        for (i, &value) in eigen.eigenvalues.iter().enumerate() {
            if value > config.min_information * largest && value > 0.0 {
                let direction = eigen.eigenvectors.column(i);
                step -= direction * (direction.dot(&gradient) / value);
            }
        }
        let rotation = Vector3::new(step[0], step[1], step[2]);
        let translation = Vector3::new(step[3], step[4], step[5]);
        let increment = Isometry3::from_parts(
            Translation3::from(translation),
            UnitQuaternion::from_scaled_axis(rotation),
        );
        pose = increment * pose;
        if translation.norm() < 1e-7 && rotation.norm() < 1e-8 {
            break;
        }
    }
    Ok(Some(pose.inverse()))
}

#[cfg(test)]
mod tests;
