#![forbid(unsafe_code)]
//! [`CylinderConfig`]: the geometry of a cylinder image and Φ, Φ⁻¹ for single points.

use nalgebra::{Point3, Vector3};

use super::floor_fast;
use crate::error::{Error, Result};

/// The most cells (`height × width`) a cylinder image may have: far above any LiDAR's grid (KITTI's is
/// 64 × 1792), and small enough that the images, index maps and per-thread buffers of one projection
/// fit in memory, so a mistyped resolution or size is refused by name instead of failing an allocation.
pub const MAX_IMAGE_CELLS: usize = 1 << 26;

/// Geometry of a cylinder image: angular resolutions, vertical field of view and the centred crop.
///
/// Angles are in degrees. `height × width` is the produced (cropped) image; the crop is centred in the
/// full grid (rounded towards the top/left when the margin is odd). See the module docs for the exact
/// angle of every cell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CylinderConfig {
    /// Elevation of the top of the field of view, degrees (KITTI HDL-64E: +2.0).
    pub fov_up_deg: f64,
    /// Elevation of the bottom of the field of view, degrees (KITTI HDL-64E: −24.9).
    pub fov_down_deg: f64,
    /// Vertical angular resolution Δφ, degrees per row.
    pub vertical_resolution_deg: f64,
    /// Horizontal angular resolution Δθ, degrees per column.
    pub horizontal_resolution_deg: f64,
    /// Rows of the produced (cropped) image.
    pub height: usize,
    /// Columns of the produced (cropped) image.
    pub width: usize,
}

impl CylinderConfig {
    /// The paper's KITTI setting (§IV-B): HDL-64E, Δφ = 0.4°, Δθ = 0.2°, +2.0°…−24.9° → full grid
    /// 68 × 1801, cropped at the centre to the network input 64 × 1792.
    pub fn kitti() -> Self {
        CylinderConfig {
            fov_up_deg: 2.0,
            fov_down_deg: -24.9,
            vertical_resolution_deg: 0.4,
            horizontal_resolution_deg: 0.2,
            height: 64,
            width: 1792,
        }
    }

    /// The paper's Argoverse setting: Δφ = 0.3° within a 20° vertical field of view, Δθ = 0.2°.
    ///
    /// Argoverse sweeps are given in the ego-vehicle frame (origin on the ground), where the two
    /// VLP-32 cover mostly −5°…+15° of elevation, so that is the chosen band: full grid 68 × 1801,
    /// cropped to 64 × 1792.
    pub fn argoverse() -> Self {
        CylinderConfig {
            fov_up_deg: 15.0,
            fov_down_deg: -5.0,
            vertical_resolution_deg: 0.3,
            horizontal_resolution_deg: 0.2,
            height: 64,
            width: 1792,
        }
    }

    fn top_index(&self) -> i64 {
        (self.fov_up_deg / self.vertical_resolution_deg).round() as i64
    }

    fn half_columns(&self) -> i64 {
        (180.0 / self.horizontal_resolution_deg).round() as i64
    }

    /// Rows of the full (uncropped) grid.
    pub fn full_height(&self) -> usize {
        let bottom = (self.fov_down_deg / self.vertical_resolution_deg).round() as i64;
        (self.top_index() - bottom + 1).max(0) as usize
    }

    /// Columns of the full (uncropped) grid: `2·round(180°/Δθ) + 1`.
    pub fn full_width(&self) -> usize {
        (2 * self.half_columns() + 1).max(0) as usize
    }

    /// Full-grid rows removed above the crop.
    pub fn crop_top(&self) -> usize {
        self.full_height().saturating_sub(self.height) / 2
    }

    /// Full-grid columns removed left of the crop.
    pub fn crop_left(&self) -> usize {
        self.full_width().saturating_sub(self.width) / 2
    }

    /// `row₀`: the (cropped) row whose centre has elevation 0°.
    pub fn row_of_zero_elevation(&self) -> f64 {
        (self.top_index() - self.crop_top() as i64) as f64
    }

    /// `col₀`: the (cropped) column whose centre has azimuth 0° (straight ahead, +x).
    pub fn col_of_zero_azimuth(&self) -> f64 {
        (self.half_columns() - self.crop_left() as i64) as f64
    }

    /// True when the image covers the whole circle of azimuth (no columns cropped away beyond the
    /// duplicated ±180° column), so that column coordinates wrap with period `360°/Δθ`.
    pub fn wraps_azimuth(&self) -> bool {
        self.width as f64 * self.horizontal_resolution_deg >= 360.0 - 1e-9
    }

    /// Columns per full turn, `360°/Δθ` (the period of the column coordinate).
    pub fn columns_per_turn(&self) -> f64 {
        360.0 / self.horizontal_resolution_deg
    }

    /// The period of the image's cell columns when it covers 360° ([`Self::wraps_azimuth`]):
    /// `round(360°/Δθ)`, so that column `c` and `c + P` are the same direction and the cells either
    /// side of the azimuth seam are neighbours (KITTI's full 1801-column grid: 1800). `None` for a
    /// cropped image, whose edges are not neighbours.
    pub fn column_period(&self) -> Option<usize> {
        self.wraps_azimuth()
            .then(|| self.columns_per_turn().round() as usize)
    }

    /// Checks every field; all functions taking a config call this first.
    pub fn validate(&self) -> Result<()> {
        let finite_positive = |v: f64| v.is_finite() && v > 0.0;
        if !finite_positive(self.vertical_resolution_deg) {
            return Err(Error::invalid(
                "vertical_resolution_deg",
                format!(
                    "must be finite and > 0, got {}",
                    self.vertical_resolution_deg
                ),
            ));
        }
        if !finite_positive(self.horizontal_resolution_deg)
            || self.horizontal_resolution_deg > 180.0
        {
            return Err(Error::invalid(
                "horizontal_resolution_deg",
                format!(
                    "must be finite, > 0 and <= 180, got {}",
                    self.horizontal_resolution_deg
                ),
            ));
        }
        if !(self.fov_up_deg.is_finite() && self.fov_down_deg.is_finite())
            || self.fov_up_deg > 90.0
            || self.fov_down_deg < -90.0
            || self.fov_up_deg <= self.fov_down_deg
        {
            return Err(Error::invalid(
                "fov_up_deg",
                format!(
                    "need -90 <= fov_down_deg < fov_up_deg <= 90, got fov_up_deg={} fov_down_deg={}",
                    self.fov_up_deg, self.fov_down_deg
                ),
            ));
        }
        // Resolutions so fine that the full grid's rows or columns overflow the index arithmetic (or
        // exceed any image the crate may allocate) describe no sensor: refuse them before counting.
        let full_rows = (self.fov_up_deg - self.fov_down_deg) / self.vertical_resolution_deg;
        if full_rows > MAX_IMAGE_CELLS as f64 {
            return Err(Error::invalid(
                "vertical_resolution_deg",
                format!(
                    "gives {full_rows:.3e} rows over the field of view, more than the {MAX_IMAGE_CELLS} \
                     cells an image may have; got {}",
                    self.vertical_resolution_deg
                ),
            ));
        }
        let full_columns = 360.0 / self.horizontal_resolution_deg;
        if full_columns > MAX_IMAGE_CELLS as f64 {
            return Err(Error::invalid(
                "horizontal_resolution_deg",
                format!(
                    "gives {full_columns:.3e} columns over 360°, more than the {MAX_IMAGE_CELLS} cells \
                     an image may have; got {}",
                    self.horizontal_resolution_deg
                ),
            ));
        }
        if self.height == 0 || self.height > self.full_height() {
            return Err(Error::invalid(
                "height",
                format!(
                    "must be in 1..={} (the full grid's rows), got {}",
                    self.full_height(),
                    self.height
                ),
            ));
        }
        if self.width == 0 || self.width > self.full_width() {
            return Err(Error::invalid(
                "width",
                format!(
                    "must be in 1..={} (the full grid's columns), got {}",
                    self.full_width(),
                    self.width
                ),
            ));
        }
        if self.height as f64 * self.width as f64 > MAX_IMAGE_CELLS as f64 {
            return Err(Error::invalid(
                "height * width",
                format!(
                    "{} * {} cells, more than the {MAX_IMAGE_CELLS} (2^26) an image may have",
                    self.height, self.width
                ),
            ));
        }
        Ok(())
    }

    /// Φ for one point: its continuous `(row, col)` in the cropped image (not range-checked; may lie
    /// outside the image). `None` for the origin, whose direction is undefined.
    pub fn locate(&self, point: &Point3<f64>) -> Option<(f64, f64)> {
        let horizontal = (point.x * point.x + point.y * point.y).sqrt();
        if horizontal == 0.0 && point.z == 0.0 {
            return None;
        }
        let elevation = point.z.atan2(horizontal).to_degrees();
        let azimuth = point.y.atan2(point.x).to_degrees();
        Some((
            self.row_of_zero_elevation() - elevation / self.vertical_resolution_deg,
            self.col_of_zero_azimuth() - azimuth / self.horizontal_resolution_deg,
        ))
    }

    /// The cell `(row, col)` containing a continuous location, if inside the cropped image.
    pub fn cell_of(&self, row: f64, col: f64) -> Option<(usize, usize)> {
        let r = floor_fast(row + 0.5);
        let c = floor_fast(col + 0.5);
        if r >= 0.0 && c >= 0.0 && r < self.height as f64 && c < self.width as f64 {
            Some((r as usize, c as usize))
        } else {
            None
        }
    }

    /// Φ⁻¹ (Eq. 4): the point at `range` metres in the direction of the continuous location
    /// `(row, col)` (a cell centre when both are integers).
    pub fn unproject(&self, row: f64, col: f64, range: f64) -> Point3<f64> {
        let elevation =
            ((self.row_of_zero_elevation() - row) * self.vertical_resolution_deg).to_radians();
        let azimuth =
            ((self.col_of_zero_azimuth() - col) * self.horizontal_resolution_deg).to_radians();
        let (sin_el, cos_el) = elevation.sin_cos();
        let (sin_az, cos_az) = azimuth.sin_cos();
        Point3::from(Vector3::new(cos_el * cos_az, cos_el * sin_az, sin_el) * range)
    }
}
