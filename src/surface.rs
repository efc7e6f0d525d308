#![forbid(unsafe_code)]
//! How much a match can say about the horizontal motion: the tilt of the surface it lies on.
//!
//! The network finds where a cell went by what its neighbourhood looks like. On a level surface (the
//! road) a LiDAR's rings look the same from scan to scan, wherever the car drove: a ring point's match
//! is sure across the surface (its height) but not along it, and at speed the rings lock, every road
//! match reporting no motion at all. Point to point, such matches still agree on a motion and can
//! outvote the few informative ones (a feature-poor highway: road, guard rails and a few posts). A
//! match's vote in RANSAC's score is therefore scaled by the horizontal part of its surface normal
//! ([`horizontal_votes`]): 1 on a wall, ≈ 0 on the road. The refit still solves on every inlier, road
//! matches included, which fix the height, roll and pitch.
//!
//! The normal of a cell comes from its virtual points (Φ⁻¹ at the cell centres, Eq. 4) and its nearer
//! neighbour along each image axis (the nearer in 3D, so that a depth edge on one side does not bend
//! it); "level" is relative to the sensor's z axis (up, by the crate's convention).

use nalgebra::Vector3;

use crate::error::{Error, Result};
use crate::ground_truth::check_range_image;
use crate::projection::CylinderConfig;

/// The unit normal of the surface at a cell of a range image, `None` when the cell or both of its
/// neighbours along either image axis are empty (or the three points are collinear).
pub fn surface_normal(
    range: &[f32],
    config: &CylinderConfig,
    row: usize,
    col: usize,
) -> Option<Vector3<f64>> {
    let (height, width) = (config.height, config.width);
    let at = |r: usize, c: usize| -> Option<Vector3<f64>> {
        let value = range[r * width + c];
        (value > 0.0).then(|| {
            config
                .unproject(r as f64, c as f64, value as f64)
                .coords
        })
    };
    let centre = at(row, col)?;
    let period = config.column_period();
    let column = |offset: isize| -> Option<usize> {
        let c = col as isize + offset;
        let c = period.map_or(c, |p| c.rem_euclid(p as isize));
        (0..width as isize).contains(&c).then_some(c as usize)
    };
    let nearer = |a: Option<Vector3<f64>>, b: Option<Vector3<f64>>| -> Option<Vector3<f64>> {
        let (a, b) = (a.map(|p| p - centre), b.map(|p| p - centre));
        match (a, b) {
            (Some(a), Some(b)) => Some(if a.norm_squared() <= b.norm_squared() { a } else { b }),
            (a, b) => a.or(b),
        }
    };
    let along_row = nearer(
        column(-1).and_then(|c| at(row, c)),
        column(1).and_then(|c| at(row, c)),
    )?;
    let along_column = nearer(
        row.checked_sub(1).and_then(|r| at(r, col)),
        (row + 1 < height).then(|| at(row + 1, col)).flatten(),
    )?;
    let normal = along_row.cross(&along_column);
    let length = normal.norm();
    (length > 0.0 && length.is_finite()).then(|| normal / length)
}

/// Per reference cell `[row, col]`: the weight of its match's vote for a horizontal motion, the
/// horizontal part of the surface normal `√(n_x² + n_y²)` (the sine of the surface's tilt), at least
/// `floor`. A cell whose normal cannot be told (no neighbours) keeps the full vote, 1.
pub fn horizontal_votes(
    range: &[f32],
    config: &CylinderConfig,
    cells: &[[usize; 2]],
    floor: f64,
) -> Result<Vec<f64>> {
    check_range_image("range", range, config)?;
    if !(0.0..=1.0).contains(&floor) {
        return Err(Error::invalid(
            "floor",
            format!("must lie in [0, 1], got {floor}"),
        ));
    }
    cells
        .iter()
        .map(|&[row, col]| {
            if row >= config.height || col >= config.width {
                return Err(Error::invalid(
                    "cells",
                    format!(
                        "[{row}, {col}] lies outside the {}x{} image",
                        config.height, config.width
                    ),
                ));
            }
            Ok(surface_normal(range, config, row, col)
                .map_or(1.0, |n| (n.x * n.x + n.y * n.y).sqrt().max(floor)))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The range image of the plane `n·p = d` seen from the origin (cells whose ray misses it in front
    /// stay empty).
    fn plane_image(config: &CylinderConfig, normal: Vector3<f64>, d: f64) -> Vec<f32> {
        let mut range = vec![0.0f32; config.height * config.width];
        for row in 0..config.height {
            for col in 0..config.width {
                let ray = config.unproject(row as f64, col as f64, 1.0).coords;
                let along = normal.dot(&ray);
                if along.abs() > 1e-9 && d / along > 0.0 && d / along < 80.0 {
                    range[row * config.width + col] = (d / along) as f32;
                }
            }
        }
        range
    }

    fn cells_of(range: &[f32], width: usize) -> Vec<[usize; 2]> {
        (0..range.len())
            .filter(|&i| range[i] > 0.0)
            .map(|i| [i / width, i % width])
            .collect()
    }

    #[test]
    fn the_road_has_no_horizontal_vote_and_a_wall_a_full_one() {
        let config = CylinderConfig::kitti();
        let road = plane_image(&config, Vector3::z(), -1.73);
        let votes = horizontal_votes(&road, &config, &cells_of(&road, config.width), 0.0).unwrap();
        assert!(!votes.is_empty());
        assert!(votes.iter().all(|&v| v < 1e-3), "max {:?}", votes.iter().cloned().fold(0.0, f64::max));

        let wall = plane_image(&config, Vector3::new(0.6, 0.8, 0.0), 12.0);
        let votes = horizontal_votes(&wall, &config, &cells_of(&wall, config.width), 0.0).unwrap();
        assert!(!votes.is_empty());
        assert!(votes.iter().all(|&v| (v - 1.0).abs() < 1e-6));
    }

    #[test]
    fn a_tilted_plane_votes_the_sine_of_its_tilt() {
        let config = CylinderConfig::kitti();
        let tilt = 30f64.to_radians();
        let normal = Vector3::new(tilt.sin(), 0.0, tilt.cos());
        let ramp = plane_image(&config, normal, -3.0);
        // Cells at the edge of the plane's image have no neighbour to tell the normal by.
        let cells: Vec<[usize; 2]> = cells_of(&ramp, config.width)
            .into_iter()
            .filter(|&[r, c]| surface_normal(&ramp, &config, r, c).is_some())
            .collect();
        let votes = horizontal_votes(&ramp, &config, &cells, 0.0).unwrap();
        assert!(!votes.is_empty());
        let worst = votes.iter().map(|v| (v - tilt.sin()).abs()).fold(0.0, f64::max);
        assert!(worst < 1e-3, "{worst}");
    }

    #[test]
    fn the_normal_follows_the_nearer_neighbour_across_a_depth_edge() {
        let config = CylinderConfig::kitti();
        let mut wall = plane_image(&config, Vector3::x(), 10.0);
        let (row, col) = (30, config.width / 2);
        // Something far behind on the left and far in front above the cell.
        wall[row * config.width + col - 1] = 60.0;
        wall[(row - 1) * config.width + col] = 2.0;
        let normal = surface_normal(&wall, &config, row, col).unwrap();
        assert!((normal.x.abs() - 1.0).abs() < 1e-6, "{normal:?}");
    }

    #[test]
    fn unknown_normals_keep_the_full_vote_and_the_floor_holds() {
        let config = CylinderConfig::kitti();
        let mut range = vec![0.0f32; config.height * config.width];
        range[10 * config.width + 100] = 5.0; // a lone point
        let votes = horizontal_votes(&range, &config, &[[10, 100]], 0.0).unwrap();
        assert_eq!(votes, vec![1.0]);
        let road = plane_image(&config, Vector3::z(), -1.73);
        let votes = horizontal_votes(&road, &config, &cells_of(&road, config.width), 0.05).unwrap();
        assert!(votes.iter().all(|&v| (v - 0.05).abs() < 1e-3));
    }

    #[test]
    fn bad_arguments_are_named() {
        let config = CylinderConfig::kitti();
        let range = vec![0.0f32; config.height * config.width];
        let err = horizontal_votes(&range, &config, &[[config.height, 0]], 0.0).unwrap_err();
        assert!(err.to_string().starts_with("cells:"), "{err}");
        let err = horizontal_votes(&range, &config, &[], 1.5).unwrap_err();
        assert!(err.to_string().starts_with("floor:"), "{err}");
        let err = horizontal_votes(&range[1..], &config, &[], 0.0).unwrap_err();
        assert!(err.to_string().starts_with("range:"), "{err}");
    }
}
