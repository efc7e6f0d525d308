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
//! The normal of a cell is that of the plane through the scan's own points around it (within a radius
//! in 3D, so that what lies across a depth edge does not bend it). The scan's points, not the virtual
//! ones at the cell centres (Eq. 4): a real sensor's lasers sit off the image's even grid of
//! elevations, each by its own angle (some rows of the grid stay empty), and near the car that alone
//! tilts the virtual road by tens of degrees from row to row. "Level" is relative to the sensor's z axis (up, by the crate's
//! convention).

use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::projection::CylinderConfig;

/// The image of a scan's points: per cell of `config`'s image, row-major, the x, y, z of the point the
/// projection kept there, NaN for an empty cell (`3·height·width` values).
pub fn check_cell_points(points: &[f32], config: &CylinderConfig) -> Result<()> {
    let cells = config.height * config.width;
    if points.len() != 3 * cells {
        return Err(Error::invalid(
            "points",
            format!(
                "has {} values, the config's {}x{} image needs 3 per cell ({})",
                points.len(),
                config.height,
                config.width,
                3 * cells
            ),
        ));
    }
    if let Some(i) = points.iter().position(|v| v.is_infinite()) {
        return Err(Error::invalid(
            "points",
            format!("value {i} is infinite (NaN marks an empty cell)"),
        ));
    }
    Ok(())
}

/// The point of cell (`row`, `col`) of a point image `width` cells wide, `None` where it is empty.
fn point_at(points: &[f32], width: usize, row: usize, col: usize) -> Option<Vector3<f64>> {
    let i = 3 * (row * width + col);
    let p = Vector3::new(points[i] as f64, points[i + 1] as f64, points[i + 2] as f64);
    p.iter().all(|v| v.is_finite()).then_some(p)
}

/// An error naming `cells` when `[row, col]` lies outside `config`'s image.
fn check_cell(row: usize, col: usize, config: &CylinderConfig) -> Result<()> {
    if row >= config.height || col >= config.width {
        return Err(Error::invalid(
            "cells",
            format!(
                "[{row}, {col}] lies outside the {}x{} image",
                config.height, config.width
            ),
        ));
    }
    Ok(())
}

/// An error naming `name` when `value` lies outside [0, 1] (NaN included).
fn check_unit_interval(value: f64, name: &'static str) -> Result<()> {
    if !(0.0..=1.0).contains(&value) {
        return Err(Error::invalid(
            name,
            format!("must lie in [0, 1], got {value}"),
        ));
    }
    Ok(())
}

/// The neighbourhood of a cell, first (near): rows searched above and below (a real sensor's lasers
/// leave some rows of an even elevation grid empty) and its radius, this many metres or this fraction of
/// the cell's range, whichever is larger.
const NEAR: Neighbourhood = Neighbourhood {
    rows: 3,
    min_radius: 0.5,
    radius_per_range: 0.1,
};
/// … and when that holds one ring only (far from the sensor, the road's rings lie metres apart).
const WIDE: Neighbourhood = Neighbourhood {
    rows: 8,
    min_radius: 1.0,
    radius_per_range: 0.3,
};
/// Columns searched either side, at most (near the sensor a column is a centimetre wide).
const MAX_COLUMNS_AROUND: usize = 24;
/// The fewest points that make a plane.
const MIN_NEIGHBOURS: usize = 6;
/// A neighbourhood whose second spread is below this fraction of its first is a line (one ring, one
/// edge): it has no one normal.
const MIN_FLATNESS: f64 = 0.01;

struct Neighbourhood {
    rows: usize,
    min_radius: f64,
    radius_per_range: f64,
}

/// The unit normal of the surface at a cell of a scan's point image (see [`check_cell_points`]): the
/// direction of least spread of the points within a radius of the cell's (0.5 m, or a tenth of its
/// range beyond 5 m), searched three rows up and down and as many columns either side as the radius
/// spans, so that several rings of the road take part; where that finds one ring only, within three
/// tenths of the range and eight rows. `None` for an empty cell, too few neighbours, or neighbours
/// along a line.
pub fn surface_normal(
    points: &[f32],
    config: &CylinderConfig,
    row: usize,
    col: usize,
) -> Option<Vector3<f64>> {
    plane_normal(points, config, row, col, &NEAR)
        .or_else(|| plane_normal(points, config, row, col, &WIDE))
}

// `!(most > 0.0)` also refuses a NaN eigenvalue, which `most <= 0.0` would let through.
#[allow(clippy::neg_cmp_op_on_partial_ord)]
fn plane_normal(
    points: &[f32],
    config: &CylinderConfig,
    row: usize,
    col: usize,
    around: &Neighbourhood,
) -> Option<Vector3<f64>> {
    let (height, width) = (config.height, config.width);
    let at = |r: usize, c: usize| point_at(points, width, r, c);
    let centre = at(row, col)?;
    let radius = around
        .min_radius
        .max(around.radius_per_range * centre.norm());
    let column_width = centre.norm() * config.horizontal_resolution_deg.to_radians();
    let columns = ((radius / column_width).ceil() as usize).clamp(1, MAX_COLUMNS_AROUND) as isize;
    let period = config.column_period();
    let column = |offset: isize| -> Option<usize> {
        let c = col as isize + offset;
        let c = period.map_or(c, |p| c.rem_euclid(p as isize));
        (0..width as isize).contains(&c).then_some(c as usize)
    };
    let mut sum = Vector3::zeros();
    let mut outer = Matrix3::zeros();
    let mut count = 0usize;
    for r in row.saturating_sub(around.rows)..(row + around.rows + 1).min(height) {
        for offset in -columns..=columns {
            let Some(p) = column(offset).and_then(|c| at(r, c)) else {
                continue;
            };
            let d = p - centre; // relative to the centre: no cancellation far from the sensor
            if d.norm_squared() <= radius * radius {
                sum += d;
                outer += d * d.transpose();
                count += 1;
            }
        }
    }
    if count < MIN_NEIGHBOURS {
        return None;
    }
    let mean = sum / count as f64;
    let covariance = outer / count as f64 - mean * mean.transpose();
    let eigen = SymmetricEigen::new(covariance);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eigen.eigenvalues[a].total_cmp(&eigen.eigenvalues[b]));
    let [least, middle, most] = order.map(|k| eigen.eigenvalues[k]);
    if !(most > 0.0) || middle < MIN_FLATNESS * most || !least.is_finite() {
        return None;
    }
    let normal = eigen.eigenvectors.column(order[0]).into_owned();
    let length = normal.norm();
    (length > 0.0 && length.is_finite()).then(|| normal / length)
}

/// Per reference cell `[row, col]`: the weight of its match's vote for a horizontal motion, the
/// horizontal part of the surface normal `√(n_x² + n_y²)` (the sine of the surface's tilt) in the
/// reference scan's point image `points` ([`check_cell_points`]), at least `floor`. A cell whose normal
/// cannot be told (no neighbours) keeps the full vote, 1.
pub fn horizontal_votes(
    points: &[f32],
    config: &CylinderConfig,
    cells: &[[usize; 2]],
    floor: f64,
) -> Result<Vec<f64>> {
    check_cell_points(points, config)?;
    check_unit_interval(floor, "floor")?;
    // Each cell's plane fit reads a few hundred neighbours: a thousand matches are worth the pool.
    cells
        .par_iter()
        .map(|&[row, col]| {
            check_cell(row, col, config)?;
            Ok(surface_normal(points, config, row, col)
                .map_or(1.0, |n| (n.x * n.x + n.y * n.y).sqrt().max(floor)))
        })
        .collect()
}

/// Rows searched up and down a column for the next ring's point (a real sensor's lasers leave some
/// rows of an even elevation grid empty).
const RING_ROWS: usize = 4;

/// Per cell `[row, col]` of a scan's point image `points` ([`check_cell_points`]): whether it lies on an
/// upright surface, told without a plane fit: the segment to the nearest point of its column above or
/// below (within [`RING_ROWS`] rows) rises at least as steeply as a surface whose normal's horizontal
/// part is `min_sine` (the sine of the segment's elevation, as [`horizontal_votes`] gives the sine of
/// the surface's tilt). Either side counts, so the lowest row of a wall, whose neighbour below lies on
/// the road in front of it, still counts as upright; an empty cell, or one with no neighbour in its
/// column, counts as upright too, as an unknown normal keeps the full vote. Far from the sensor the
/// road's rings lie metres apart at one height and a wall's centimetres apart above each other, so the one
/// segment tells them where [`horizontal_votes`] reads hundreds of neighbours a cell (and, with its
/// neighbourhood a tenth of the range wide, calls the foot of a far wall or a post level with the road).
pub fn steep_to_next_ring(
    points: &[f32],
    config: &CylinderConfig,
    cells: &[[usize; 2]],
    min_sine: f64,
) -> Result<Vec<bool>> {
    check_cell_points(points, config)?;
    check_unit_interval(min_sine, "min_sine")?;
    let (height, width) = (config.height, config.width);
    let at = |r: usize, c: usize| point_at(points, width, r, c);
    let steep = |from: &Vector3<f64>, to: &Vector3<f64>| {
        let d = to - from;
        d.z.abs() >= min_sine * d.norm()
    };
    cells
        .iter()
        .map(|&[row, col]| {
            check_cell(row, col, config)?;
            let Some(centre) = at(row, col) else {
                return Ok(true);
            };
            let above = (row.saturating_sub(RING_ROWS)..row)
                .rev()
                .find_map(|r| at(r, col));
            let below = (row + 1..(row + RING_ROWS + 1).min(height)).find_map(|r| at(r, col));
            let neighbours = [above, below];
            Ok(neighbours.iter().all(Option::is_none)
                || neighbours.iter().flatten().any(|p| steep(&centre, p)))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const EMPTY: [f32; 3] = [f32::NAN; 3];

    /// The point image of the plane `n·p = d` seen from the origin, each point at its cell's centre
    /// angles (cells whose ray misses it within 80 m stay empty).
    fn plane_image(config: &CylinderConfig, normal: Vector3<f64>, d: f64) -> Vec<[f32; 3]> {
        let mut image = vec![EMPTY; config.height * config.width];
        for row in 0..config.height {
            for col in 0..config.width {
                let ray = config.unproject(row as f64, col as f64, 1.0).coords;
                let along = normal.dot(&ray);
                if along.abs() > 1e-9 && d / along > 0.0 && d / along < 80.0 {
                    let p = ray * (d / along);
                    image[row * config.width + col] = [p.x as f32, p.y as f32, p.z as f32];
                }
            }
        }
        image
    }

    fn flat(image: &[[f32; 3]]) -> Vec<f32> {
        image.iter().flatten().copied().collect()
    }

    /// The cells whose normal can be told (the edges of a plane's image have too few neighbours, its
    /// far rows a ring each), and that they are most of the plane's cells.
    fn cells_with_normals(image: &[[f32; 3]], config: &CylinderConfig) -> Vec<[usize; 2]> {
        let points = flat(image);
        let occupied: Vec<[usize; 2]> = (0..image.len())
            .filter(|&i| !image[i][0].is_nan())
            .map(|i| [i / config.width, i % config.width])
            .collect();
        let cells: Vec<[usize; 2]> = occupied
            .iter()
            .copied()
            .filter(|&[r, c]| surface_normal(&points, config, r, c).is_some())
            .collect();
        assert!(
            2 * cells.len() > occupied.len(),
            "{} of {}",
            cells.len(),
            occupied.len()
        );
        cells
    }

    /// The votes of the cells of `image` whose normal can be told.
    fn votes_where_told(image: &[[f32; 3]], config: &CylinderConfig, floor: f64) -> Vec<f64> {
        horizontal_votes(
            &flat(image),
            config,
            &cells_with_normals(image, config),
            floor,
        )
        .unwrap()
    }

    #[test]
    fn the_road_has_no_horizontal_vote_and_a_wall_a_full_one() {
        let config = CylinderConfig::kitti();
        let road = plane_image(&config, Vector3::z(), -1.73);
        let votes = votes_where_told(&road, &config, 0.0);
        assert!(!votes.is_empty());
        assert!(votes.iter().all(|&v| v < 1e-3));

        let wall = plane_image(&config, Vector3::new(0.6, 0.8, 0.0), 12.0);
        let votes = votes_where_told(&wall, &config, 0.0);
        assert!(!votes.is_empty());
        assert!(votes.iter().all(|&v| (v - 1.0).abs() < 1e-6));
    }

    #[test]
    fn the_road_stays_level_when_the_lasers_sit_off_the_grid() {
        // Each row's laser a different fraction of a row off its cell centre, as a real sensor's: the
        // scan's own points still lie on the road.
        let config = CylinderConfig::kitti();
        let mut road = vec![EMPTY; config.height * config.width];
        for row in 0..config.height {
            let offset = 0.45 * ((row * 7 % 11) as f64 / 10.0 - 0.5);
            for col in 0..config.width {
                let ray = config
                    .unproject(row as f64 + offset, col as f64, 1.0)
                    .coords;
                if ray.z < -1e-3 && -1.73 / ray.z < 80.0 {
                    let p = ray * (-1.73 / ray.z);
                    road[row * config.width + col] = [p.x as f32, p.y as f32, p.z as f32];
                }
            }
        }
        let votes = votes_where_told(&road, &config, 0.0);
        assert!(!votes.is_empty());
        assert!(votes.iter().all(|&v| v < 1e-3));
    }

    #[test]
    fn a_tilted_plane_votes_the_sine_of_its_tilt() {
        let config = CylinderConfig::kitti();
        let tilt = 30f64.to_radians();
        let ramp = plane_image(&config, Vector3::new(tilt.sin(), 0.0, tilt.cos()), -3.0);
        let votes = votes_where_told(&ramp, &config, 0.0);
        let worst = votes
            .iter()
            .map(|v| (v - tilt.sin()).abs())
            .fold(0.0, f64::max);
        assert!(worst < 1e-3, "{worst}");
    }

    #[test]
    fn what_lies_across_a_depth_edge_does_not_bend_the_normal() {
        let config = CylinderConfig::kitti();
        let mut wall = plane_image(&config, Vector3::x(), 10.0);
        let (row, col) = (30, config.width / 2);
        // A pole 3 m in front of the wall, just left of the cell, and the wall's cells above it gone.
        for r in row - 3..=row + 3 {
            for c in col - 4..col {
                let p = config.unproject(r as f64, c as f64, 3.0);
                wall[r * config.width + c] = [p.x as f32, p.y as f32, p.z as f32];
            }
            wall[(row - 3) * config.width + col + 2] = [f32::NAN; 3];
        }
        let normal = surface_normal(&flat(&wall), &config, row, col).unwrap();
        assert!((normal.x.abs() - 1.0).abs() < 1e-6, "{normal:?}");
    }

    #[test]
    fn a_single_ring_has_no_normal() {
        let config = CylinderConfig::kitti();
        let mut ring = vec![EMPTY; config.height * config.width];
        let row = 50;
        for col in 0..config.width {
            let ray = config.unproject(row as f64, col as f64, 1.0).coords;
            let p = ray * (-1.73 / ray.z);
            ring[row * config.width + col] = [p.x as f32, p.y as f32, p.z as f32];
        }
        assert_eq!(surface_normal(&flat(&ring), &config, row, 900), None);
    }

    #[test]
    fn unknown_normals_keep_the_full_vote_and_the_floor_holds() {
        let config = CylinderConfig::kitti();
        let mut lone = vec![EMPTY; config.height * config.width];
        lone[10 * config.width + 100] = [5.0, 0.0, 0.0];
        let votes = horizontal_votes(&flat(&lone), &config, &[[10, 100]], 0.0).unwrap();
        assert_eq!(votes, vec![1.0]);
        let road = plane_image(&config, Vector3::z(), -1.73);
        let votes = votes_where_told(&road, &config, 0.05);
        assert!(votes.iter().all(|&v| (v - 0.05).abs() < 1e-3));
    }

    #[test]
    fn bad_arguments_are_named() {
        let config = CylinderConfig::kitti();
        let mut points = vec![f32::NAN; 3 * config.height * config.width];
        let err = horizontal_votes(&points, &config, &[[config.height, 0]], 0.0).unwrap_err();
        assert!(err.to_string().starts_with("cells:"), "{err}");
        let err = horizontal_votes(&points, &config, &[], 1.5).unwrap_err();
        assert!(err.to_string().starts_with("floor:"), "{err}");
        let err = horizontal_votes(&points[1..], &config, &[], 0.0).unwrap_err();
        assert!(err.to_string().starts_with("points:"), "{err}");
        points[7] = f32::INFINITY;
        let err = horizontal_votes(&points, &config, &[], 0.0).unwrap_err();
        assert!(err.to_string().starts_with("points:"), "{err}");
    }

    /// The occupied cells of an image and whether [`steep_to_next_ring`] calls each upright.
    fn steep_cells(image: &[[f32; 3]], config: &CylinderConfig) -> Vec<([usize; 2], bool)> {
        let cells: Vec<[usize; 2]> = (0..image.len())
            .filter(|&i| !image[i][0].is_nan())
            .map(|i| [i / config.width, i % config.width])
            .collect();
        let steep = steep_to_next_ring(&flat(image), config, &cells, 0.5).unwrap();
        cells.into_iter().zip(steep).collect()
    }

    #[test]
    fn the_next_ring_tells_the_road_and_a_gentle_ramp_from_a_wall() {
        let config = CylinderConfig::kitti();
        for (normal, d, upright) in [
            (Vector3::z(), -1.73, false),
            (Vector3::new(0.6, 0.8, 0.0), 12.0, true),
            (
                Vector3::new(20f64.to_radians().sin(), 0.0, 20f64.to_radians().cos()),
                -2.0,
                false,
            ),
        ] {
            let image = plane_image(&config, normal, d);
            // The cells alone in their column within four rows count as upright whatever the surface.
            let lone = |[row, col]: [usize; 2]| {
                (row.saturating_sub(RING_ROWS)..(row + RING_ROWS + 1).min(config.height))
                    .filter(|&r| r != row)
                    .all(|r| image[r * config.width + col][0].is_nan())
            };
            let told: Vec<bool> = steep_cells(&image, &config)
                .into_iter()
                .filter(|&(cell, _)| !lone(cell))
                .map(|(_, steep)| steep)
                .collect();
            assert!(told.len() > 1000, "{normal:?}: {} cells", told.len());
            assert!(told.iter().all(|&steep| steep == upright), "{normal:?}");
        }
        let mut lone = vec![EMPTY; config.height * config.width];
        lone[10 * config.width + 100] = [5.0, 0.0, 0.0];
        assert_eq!(steep_cells(&lone, &config), vec![([10, 100], true)]);
    }

    #[test]
    fn the_lowest_ring_on_a_wall_is_upright_and_the_road_before_it_is_not() {
        // A wall 20 m ahead across the road: the ring below the wall's lowest lies on the road metres
        // nearer at nearly its height, the ring above on the wall.
        let config = CylinderConfig::kitti();
        let road = plane_image(&config, Vector3::z(), -1.73);
        let wall = plane_image(&config, Vector3::x(), 20.0);
        let scene: Vec<[f32; 3]> = road
            .iter()
            .zip(&wall)
            .map(|(r, w)| {
                if w[0].is_nan() || (!r[0].is_nan() && r[0] < w[0]) {
                    *r
                } else {
                    *w
                }
            })
            .collect();
        let col = (0..config.width)
            .min_by_key(|&c| {
                let ray = config.unproject(0.0, c as f64, 1.0).coords;
                (ray.y.atan2(ray.x).abs() * 1e6) as i64
            })
            .unwrap();
        let column: Vec<([usize; 2], bool)> = steep_cells(&scene, &config)
            .into_iter()
            .filter(|&([_, c], _)| c == col)
            .collect();
        let lowest_on_wall = column
            .iter()
            .rposition(|&([row, c], _)| (scene[row * config.width + c][0] - 20.0).abs() < 1e-3)
            .unwrap();
        assert!(column[lowest_on_wall].1);
        assert!(!column[lowest_on_wall + 1].1, "the road's farthest ring");
        assert!(column[..lowest_on_wall].iter().all(|&(_, steep)| steep));
        assert!(column[lowest_on_wall + 2..]
            .iter()
            .all(|&(_, steep)| !steep));
    }

    #[test]
    fn bad_arguments_of_the_ring_test_are_named() {
        let config = CylinderConfig::kitti();
        let points = vec![f32::NAN; 3 * config.height * config.width];
        let err = steep_to_next_ring(&points, &config, &[[0, config.width]], 0.5).unwrap_err();
        assert!(err.to_string().starts_with("cells:"), "{err}");
        let err = steep_to_next_ring(&points, &config, &[], -0.1).unwrap_err();
        assert!(err.to_string().starts_with("min_sine:"), "{err}");
        let err = steep_to_next_ring(&points[3..], &config, &[], 0.5).unwrap_err();
        assert!(err.to_string().starts_with("points:"), "{err}");
    }
}
