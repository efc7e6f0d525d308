#![forbid(unsafe_code)]
//! Cylinder encoding Φ (paper Eq. 1) and its inverse Φ⁻¹ (Eq. 4).
//!
//! # Grid coordinates
//!
//! A [`CylinderConfig`] describes a *full* grid that covers the vertical field of view and 360° of
//! azimuth, and a centred *crop* of it (the image that is actually produced). All row/column
//! coordinates in this crate are coordinates of the **cropped** image, and are continuous: an integer
//! `(row, col)` is the centre of a cell, and the cell covers `[row − ½, row + ½) × [col − ½, col + ½)`.
//!
//! With `Δφ`, `Δθ` the vertical and horizontal resolutions, a (sub-pixel) location `(row, col)` stands
//! for exactly the angles
//!
//! ```text
//! elevation φ(row) = (row₀ − row) · Δφ        row₀ = round(fov_up / Δφ) − crop_top
//! azimuth   θ(col) = (col₀ − col) · Δθ        col₀ = round(180° / Δθ)  − crop_left
//! ```
//!
//! so row 0 is the highest elevation and the column grows clockwise seen from above (azimuth
//! decreasing: the image reads left to right as the sensor sees the world; forward `+x` is the centre
//! column of a centred crop). Conversely Φ maps a point to `row = row₀ − atan2(z, √(x²+y²))/Δφ` and
//! `col = col₀ − atan2(y, x)/Δθ`, and a point falls in the cell `(⌊row + ½⌋, ⌊col + ½⌋)`. These are the
//! paper's `h = φ/Δφ`, `w = θ/Δθ` (Eq. 1, 4) shifted and with the column axis flipped.
//!
//! The full grid has `round(fov_up/Δφ) − round(fov_down/Δφ) + 1` rows and `2·round(180°/Δθ) + 1`
//! columns (the paper's 68 × 1801 for KITTI: the first and last full columns both look backwards, at
//! +180° and −180°).

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use crate::error::{Error, Result};

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

/// A scan's cylinder image (row-major `height × width` arrays) and what was dropped.
#[derive(Debug, Clone, PartialEq)]
pub struct Projection {
    /// Rows of the image.
    pub height: usize,
    /// Columns of the image.
    pub width: usize,
    /// Range ‖p‖ of the closest point in each cell, metres; 0 for an empty cell.
    pub range: Vec<f32>,
    /// Reflectance of that point; 0 for an empty cell (and for points given without reflectance).
    pub reflectance: Vec<f32>,
    /// Index (in the input) of that point; −1 for an empty cell.
    pub index: Vec<i64>,
    /// Points dropped because a coordinate (or the reflectance) is NaN or infinite.
    pub num_non_finite: usize,
    /// Finite points dropped because they fall outside the cropped image or sit at the origin.
    pub num_out_of_view: usize,
}

impl Projection {
    /// Number of non-empty cells.
    pub fn num_valid(&self) -> usize {
        self.index.iter().filter(|&&i| i >= 0).count()
    }
}

/// Sentinel for "this point lands in no cell".
const NO_CELL: u32 = u32::MAX;
/// Sentinel for "this point is NaN/Inf".
const NON_FINITE: u32 = u32::MAX - 1;

/// `x.floor()` without a libm call on baseline x86-64 (which lacks an inline rounding instruction);
/// NaN and huge values go to `floor` itself.
#[inline(always)]
pub(crate) fn floor_fast(x: f64) -> f64 {
    if x.is_nan() || x.abs() >= 4.5e15 {
        return x.floor();
    }
    let truncated = (x as i64) as f64;
    if truncated > x {
        truncated - 1.0
    } else {
        truncated
    }
}

/// Bound on the error of [`atan2_lanes`], radians: the series is cut after the u¹³ term for |u| ≤
/// tan(π/8), so the first omitted term is below 0.4143¹⁵/15 = 1.3e-7; 1e-6 leaves room for rounding.
const ATAN_ERROR_BOUND: f64 = 1e-6;

/// Points per lane group of the vectorised arctangent.
const LANES: usize = 8;

/// `atan2(y, x)` within [`ATAN_ERROR_BOUND`] for a group of points, with libm's quadrants and signs
/// (also of −0): the octant reduced to |u| ≤ tan(π/8) by `atan t = π/4 + atan((t−1)/(t+1))` (one
/// division either way), then the odd Taylor series; written branch-free.
#[inline(always)]
fn atan2_lanes(y: &[f64; LANES], x: &[f64; LANES]) -> [f64; LANES] {
    let mut out = [0.0; LANES];
    for l in 0..LANES {
        let (ax, ay) = (x[l].abs(), y[l].abs());
        let steep = ay > ax;
        let (num, den) = if steep { (ax, ay) } else { (ay, ax) };
        let big = num > (std::f64::consts::SQRT_2 - 1.0) * den;
        let top = if big { num - den } else { num };
        let bottom = if big { num + den } else { den };
        // 0/0 at the origin gives NaN, which `cell_index` hands to libm.
        let u = top / bottom;
        let u2 = u * u;
        let series = 1.0
            - u2 * (1.0 / 3.0
                - u2 * (1.0 / 5.0
                    - u2 * (1.0 / 7.0 - u2 * (1.0 / 9.0 - u2 * (1.0 / 11.0 - u2 * (1.0 / 13.0))))));
        let octant = if big {
            std::f64::consts::FRAC_PI_4
        } else {
            0.0
        } + u * series;
        let angle = if steep {
            std::f64::consts::FRAC_PI_2 - octant
        } else {
            octant
        };
        // x = −0 only matters together with y = ±0 (the origin, handled by libm).
        let angle = if x[l] < 0.0 {
            std::f64::consts::PI - angle
        } else {
            angle
        };
        // The angle is ≥ 0 here; y's sign (also of −0, as libm) decides the half-plane.
        out[l] = angle.copysign(y[l]);
    }
    out
}

/// `⌊origin − atan2(y, x)·cells_per_radian + ½⌋`, exactly as with libm's `atan2`: the fast arctangent
/// `fast` (within [`ATAN_ERROR_BOUND`]) decides the cell unless it lies too close to a cell boundary to
/// be sure (or is NaN), when libm decides. Negative results (outside the image anyway) come back as −1.
#[inline(always)]
fn cell_index(origin: f64, fast: f64, y: f64, x: f64, cells_per_radian: f64) -> f64 {
    let shifted = origin - fast * cells_per_radian + 0.5;
    let margin = ATAN_ERROR_BOUND * cells_per_radian + 1e-9;
    if shifted >= margin {
        // Truncation is floor for non-negative values and, unlike `floor`, needs no libm call on
        // baseline x86-64.
        let cell = (shifted as i64) as f64;
        let fraction = shifted - cell;
        if fraction > margin && fraction < 1.0 - margin {
            return cell;
        }
    } else if shifted < -margin {
        return -1.0;
    }
    let exact = origin - y.atan2(x) * cells_per_radian + 0.5;
    if exact < 0.0 {
        -1.0
    } else {
        exact.floor()
    }
}

/// Φ (Eq. 1) for a whole scan: every cell keeps its closest point (ties: the lower input index).
///
/// `points` is a flat row-major array of `N × channels` values, `channels` = 3 (x, y, z) or 4 (x, y, z,
/// reflectance). Points with a NaN/Inf value are dropped and counted; so are points outside the
/// cropped image. Runs in the caller's rayon pool.
pub fn project_flat(
    points: &[f32],
    channels: usize,
    config: &CylinderConfig,
) -> Result<Projection> {
    config.validate()?;
    if channels != 3 && channels != 4 {
        return Err(Error::invalid(
            "points",
            format!("need 3 or 4 values per point, got {channels}"),
        ));
    }
    if points.len() % channels != 0 {
        return Err(Error::invalid(
            "points",
            format!("length {} is not a multiple of {channels}", points.len()),
        ));
    }
    let (height, width) = (config.height, config.width);
    if height * width >= NON_FINITE as usize {
        return Err(Error::invalid("config", "image too large"));
    }
    let row0 = config.row_of_zero_elevation();
    let col0 = config.col_of_zero_azimuth();
    let rows_per_radian = 1.0 / config.vertical_resolution_deg.to_radians();
    let cols_per_radian = 1.0 / config.horizontal_resolution_deg.to_radians();

    // Pass 1 (parallel): every point's cell and range. Pass 2 (serial, cheap): closest point per cell.
    let locate_point = |p: &[f32], elevation: f64, azimuth: f64| -> (u32, f32) {
        if !p.iter().all(|v| v.is_finite()) {
            return (NON_FINITE, 0.0);
        }
        let (x, y, z) = (p[0] as f64, p[1] as f64, p[2] as f64);
        let horizontal_sq = x * x + y * y;
        let range = (horizontal_sq + z * z).sqrt();
        if range == 0.0 {
            return (NO_CELL, 0.0);
        }
        let row = cell_index(row0, elevation, z, horizontal_sq.sqrt(), rows_per_radian);
        let col = cell_index(col0, azimuth, y, x, cols_per_radian);
        if row < 0.0 || col < 0.0 || row >= height as f64 || col >= width as f64 {
            return (NO_CELL, 0.0);
        }
        ((row as usize * width + col as usize) as u32, range as f32)
    };
    // Lanes of points: the arctangents of a lane are branch-free and vectorise; the cell logic
    // (and the rare exact fallback) stays scalar.
    let mut located = vec![(NO_CELL, 0.0f32); points.len() / channels];
    located
        .par_chunks_mut(LANES)
        .zip(points.par_chunks(LANES * channels))
        .with_min_len(512)
        .for_each(|(out, chunk)| {
            let mut xs = [1.0f64; LANES];
            let mut ys = [0.0f64; LANES];
            let mut zs = [0.0f64; LANES];
            let mut horizontal = [1.0f64; LANES];
            for (l, p) in chunk.chunks_exact(channels).enumerate() {
                let (x, y, z) = (p[0] as f64, p[1] as f64, p[2] as f64);
                (xs[l], ys[l], zs[l]) = (x, y, z);
                horizontal[l] = (x * x + y * y).sqrt();
            }
            let elevation = atan2_lanes(&zs, &horizontal);
            let azimuth = atan2_lanes(&ys, &xs);
            for (l, p) in chunk.chunks_exact(channels).enumerate() {
                out[l] = locate_point(p, elevation[l], azimuth[l]);
            }
        });

    let mut projection = Projection {
        height,
        width,
        range: vec![0.0; height * width],
        reflectance: vec![0.0; height * width],
        index: vec![-1; height * width],
        num_non_finite: 0,
        num_out_of_view: 0,
    };
    for (i, &(cell, range)) in located.iter().enumerate() {
        match cell {
            NON_FINITE => projection.num_non_finite += 1,
            NO_CELL => projection.num_out_of_view += 1,
            cell => {
                let cell = cell as usize;
                if projection.index[cell] < 0 || range < projection.range[cell] {
                    projection.range[cell] = range;
                    projection.index[cell] = i as i64;
                }
            }
        }
    }
    if channels == 4 {
        for (reflectance, &index) in projection.reflectance.iter_mut().zip(&projection.index) {
            if index >= 0 {
                *reflectance = points[index as usize * 4 + 3];
            }
        }
    }
    Ok(projection)
}

/// Φ (Eq. 1) for a scan of `x, y, z, reflectance` points; see [`project_flat`].
pub fn project(points: &[[f32; 4]], config: &CylinderConfig) -> Result<Projection> {
    project_flat(points.as_flattened(), 4, config)
}

/// Φ⁻¹ (Eq. 4) for many locations: `rows[i], cols[i]` (continuous, cropped-image coordinates) at
/// `ranges[i]` metres → points. Errors on mismatched lengths or non-finite input.
pub fn unproject_many(
    rows: &[f64],
    cols: &[f64],
    ranges: &[f64],
    config: &CylinderConfig,
) -> Result<Vec<Point3<f64>>> {
    config.validate()?;
    if cols.len() != rows.len() {
        return Err(Error::invalid(
            "cols",
            format!("length {} differs from rows' {}", cols.len(), rows.len()),
        ));
    }
    if ranges.len() != rows.len() {
        return Err(Error::invalid(
            "ranges",
            format!("length {} differs from rows' {}", ranges.len(), rows.len()),
        ));
    }
    for (name, values) in [("rows", rows), ("cols", cols), ("ranges", ranges)] {
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(
                name,
                format!("element {i} is not finite ({})", values[i]),
            ));
        }
    }
    Ok(rows
        .iter()
        .zip(cols)
        .zip(ranges)
        .map(|((&row, &col), &range)| config.unproject(row, col, range))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn fast_arctangent_stays_within_its_bound_and_keeps_libm_signs() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let fast = |y: f64, x: f64| atan2_lanes(&[y; LANES], &[x; LANES])[LANES - 1];
        for _ in 0..200_000 {
            let (y, x) = (
                rng.random_range(-100.0..100.0),
                rng.random_range(-100.0..100.0),
            );
            assert!((fast(y, x) - f64::atan2(y, x)).abs() < ATAN_ERROR_BOUND / 4.0);
        }
        for (y, x) in [
            (0.0, -1.0),
            (-0.0, -1.0),
            (0.0, 1.0),
            (-0.0, 1.0),
            (1.0, 0.0),
            (-1.0, -0.0),
        ] {
            assert!((fast(y, x) - f64::atan2(y, x)).abs() < 1e-12, "({y}, {x})");
            assert_eq!(
                fast(y, x).is_sign_negative(),
                f64::atan2(y, x).is_sign_negative()
            );
        }
        // The origin has no direction: NaN, which `cell_index` hands to libm.
        assert!(fast(0.0, 0.0).is_nan());
        assert_eq!(cell_index(3.0, f64::NAN, 0.0, 0.0, 143.0), 3.0);
    }

    #[test]
    fn fast_floor_equals_floor() {
        for x in [
            -2.5,
            -1.0,
            -0.5,
            -0.0,
            0.0,
            0.3,
            1.0,
            1.5,
            1e15,
            -1e15 - 0.5,
            1e300,
            f64::INFINITY,
        ] {
            assert_eq!(floor_fast(x), x.floor(), "{x}");
        }
        assert!(floor_fast(f64::NAN).is_nan());
    }

    #[test]
    fn kitti_preset_matches_the_paper() {
        let config = CylinderConfig::kitti();
        assert_eq!((config.full_height(), config.full_width()), (68, 1801));
        assert_eq!((config.height, config.width), (64, 1792));
        assert_eq!((config.crop_top(), config.crop_left()), (2, 4));
        // Row 0 is the highest elevation: +2.0° top beam → full row 0, cropped row −2 → +1.2° at row 0.
        assert_eq!(config.row_of_zero_elevation(), 3.0);
        assert_eq!(config.col_of_zero_azimuth(), 896.0);
        assert!(!config.wraps_azimuth());
        let argoverse = CylinderConfig::argoverse();
        assert_eq!(
            (argoverse.full_height(), argoverse.full_width()),
            (68, 1801)
        );
        argoverse.validate().unwrap();
    }

    #[test]
    fn cell_centres_stand_for_the_documented_angles() {
        let config = CylinderConfig::kitti();
        // Straight ahead at zero elevation: column col₀, row row₀.
        let (row, col) = config.locate(&Point3::new(10.0, 0.0, 0.0)).unwrap();
        assert_eq!((row, col), (3.0, 896.0));
        // Looking left (+y) is azimuth +90° → 450 columns to the left of forward.
        let (_, col) = config.locate(&Point3::new(0.0, 5.0, 0.0)).unwrap();
        assert!((col - (896.0 - 450.0)).abs() < 1e-9);
        // Upwards is a lower row.
        let (row, _) = config.locate(&Point3::new(10.0, 0.0, 1.0)).unwrap();
        assert!(row < 3.0);
    }

    #[test]
    fn round_trip_stays_within_the_cells_angular_bound() {
        let config = CylinderConfig::kitti();
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let points: Vec<[f32; 4]> = (0..20_000)
            .map(|_| {
                let azimuth = rng.random_range(-180.0f64..180.0).to_radians();
                let elevation = rng.random_range(-24.0f64..1.2).to_radians();
                let range = rng.random_range(1.0f64..80.0);
                [
                    (range * elevation.cos() * azimuth.cos()) as f32,
                    (range * elevation.cos() * azimuth.sin()) as f32,
                    (range * elevation.sin()) as f32,
                    rng.random::<f32>(),
                ]
            })
            .collect();
        let projection = project(&points, &config).unwrap();
        let half_diagonal = (config.vertical_resolution_deg.powi(2)
            + config.horizontal_resolution_deg.powi(2))
        .sqrt()
            / 2.0;
        let mut checked = 0;
        for cell in 0..projection.index.len() {
            let index = projection.index[cell];
            if index < 0 {
                continue;
            }
            let (row, col) = (cell / config.width, cell % config.width);
            let p = points[index as usize];
            let original = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            let back = config
                .unproject(row as f64, col as f64, projection.range[cell] as f64)
                .coords;
            assert!((back.norm() - original.norm()).abs() < 1e-4);
            let angle = original.angle(&back).to_degrees();
            assert!(
                angle <= half_diagonal + 1e-4,
                "angle {angle} beyond {half_diagonal}"
            );
            assert_eq!(projection.reflectance[cell], p[3]);
            checked += 1;
        }
        assert!(checked > 10_000);
    }

    #[test]
    fn closest_point_wins_and_bad_points_are_counted() {
        let config = CylinderConfig::kitti();
        let points = [
            [10.0, 0.0, 0.0, 0.1],
            [5.0, 0.0, 0.0, 0.2],
            [7.0, 0.0, 0.0, 0.3],
            [f32::NAN, 0.0, 0.0, 0.0],
            [1.0, 0.0, f32::INFINITY, 0.0],
            [0.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 10.0, 0.0],  // straight up: outside the field of view
            [-10.0, 0.0, 0.0, 0.0], // straight back: cropped away
        ];
        let projection = project(&points, &config).unwrap();
        assert_eq!(projection.num_non_finite, 2);
        assert_eq!(projection.num_out_of_view, 3);
        assert_eq!(projection.num_valid(), 1);
        let cell = 3 * config.width + 896;
        assert_eq!(projection.index[cell], 1);
        assert_eq!(projection.range[cell], 5.0);
        assert_eq!(projection.reflectance[cell], 0.2);
    }

    #[test]
    fn empty_scan_gives_an_empty_image_and_bad_configs_are_rejected() {
        let config = CylinderConfig::kitti();
        let projection = project(&[], &config).unwrap();
        assert_eq!(projection.num_valid(), 0);
        assert!(projection.range.iter().all(|&r| r == 0.0));
        let too_wide = CylinderConfig {
            width: 1802,
            ..config
        };
        assert!(matches!(
            too_wide.validate(),
            Err(Error::InvalidArgument {
                argument: "width",
                ..
            })
        ));
        let bad = CylinderConfig {
            vertical_resolution_deg: 0.0,
            ..config
        };
        assert!(bad.validate().is_err());
        assert!(project_flat(&[1.0; 10], 4, &config).is_err());
        assert!(project_flat(&[1.0; 10], 5, &config).is_err());
    }

    #[test]
    fn unproject_many_checks_its_input() {
        let config = CylinderConfig::kitti();
        let points = unproject_many(&[3.0], &[896.0], &[2.0], &config).unwrap();
        assert!((points[0] - Point3::new(2.0, 0.0, 0.0)).norm() < 1e-12);
        assert!(unproject_many(&[3.0], &[], &[2.0], &config).is_err());
        assert!(unproject_many(&[3.0], &[1.0], &[f64::NAN], &config).is_err());
    }
}
