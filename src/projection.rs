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

use std::sync::{Arc, Mutex};

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

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
    /// Finite points dropped because they fall outside the cropped image, sit at the origin, or lie
    /// farther than a float32 range can hold (coordinates near `f32::MAX`).
    pub num_out_of_view: usize,
}

impl Projection {
    /// Number of non-empty cells.
    pub fn num_valid(&self) -> usize {
        self.index.iter().filter(|&&i| i >= 0).count()
    }
}

/// Cells and ranges of a block of points (`NO_CELL` outside the image or at the origin, `NON_FINITE`
/// for NaN/Inf values).
struct Located {
    cells: [u32; BLOCK],
    ranges: [f32; BLOCK],
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

// ---- exact cell lookup without arctangents -------------------------------------------------------
//
// The definition of a point's cell is the libm formula `⌊origin − atan2(·,·)·cells_per_radian + ½⌋`
// per axis (module docs). Instead of evaluating it, a point is compared with the cell *boundaries*:
// boundary k (k = 0 ..= cells) is the angle at which the formula reaches k, and the cell is (number of
// boundaries the point is at or past) − 1. A table over a cheap monotone *key* of the point (float32
// `z/‖p‖` for the elevation; for the azimuth the "diamond angle" `y/(|x|+|y|)` continued to (−2, 2])
// says how many boundaries every point of its bin passes, and names the one boundary (if any) the bin
// cannot settle; that one is tested exactly in float64 without trigonometry: `z − ‖p‖·sin β ≤ 0` for
// the elevation, the sign of the cross product with the boundary's direction `(cos α, sin α)` for the
// azimuth.
//
// Identity with the formula: a bin settles a boundary only when it lies `KEY_MARGIN` (key units, which
// are never more than radians) beyond the bin, more than the float32 key's error, so the point is
// ≥ 1e-5 rad clear of it; the exact test decides only when the point is `BOUNDARY_MARGIN` = 1e-11 rad
// clear. The formula's own rounding (atan2, products, sums) and the tables' move a boundary by less
// than 1e-14 rad, so every decided comparison is the formula's. Undecided points (≈ 1 in 10⁸ real
// ones; adversarial ones on a boundary), the poles, points within 1e-30 m of the origin or beyond
// 1e18 m, and boundaries within `EDGE_GUARD` of the poles or of ±180° get the formula itself.

/// Points closer than this (radians) to a tested boundary get the libm formula.
const BOUNDARY_MARGIN: f64 = 1e-11;

/// A bin settles a boundary only when it is this far (key units) from the bin: covers the float32
/// key's error (≤ 1e-6 for keys within ±2, including the bin computation).
const KEY_MARGIN: f64 = 1e-5;

/// A key this far (key units) from its bin's unsettled boundary settles the comparison in float32:
/// above the float32 keys' error (≤ 5e-7, with the boundary key's rounding), so the point is
/// ≥ 3e-6 rad from the boundary.
const FAST_KEY_MARGIN: f32 = 4e-6;

/// Boundaries within this many radians of the poles (elevation) or of ±180° (azimuth) are left to
/// the libm formula; boundaries farther beyond them are passed by every point or by none.
const EDGE_GUARD: f64 = 1e-6;

/// Points per block: the keys of a block are computed in vectorisable loops first.
const BLOCK: usize = 64;

/// The libm formula for one axis: the cell index, or −1 when negative (outside the image anyway).
#[inline(never)]
fn exact_cell(origin: f64, y: f64, x: f64, cells_per_radian: f64) -> i64 {
    let shifted = origin - y.atan2(x) * cells_per_radian + 0.5;
    if shifted < 0.0 {
        -1
    } else {
        // Huge values saturate, which is outside the image just the same.
        shifted.floor() as i64
    }
}

/// One bin of a [`BinTable`]: every point in it passes `passed` (padded) boundaries for sure, plus
/// the bin's unsettled boundary when the point's key is ≤ `test_key`, the boundary's key in float32
/// (−∞ when the bin has none; NaN when it cannot be decided this way).
#[derive(Clone, Copy)]
struct Bin {
    passed: u32,
    test_key: f32,
}

/// Uniform bins over the key range `[lowest, lowest + span]` of one axis.
struct BinTable {
    bins: Vec<Bin>,
    /// Per bin, the padded index of the boundary its exact test compares with.
    tests: Vec<u32>,
    lowest: f32,
    bins_per_unit: f32,
}

impl BinTable {
    /// `keys[m]`: key of padded boundary `m`, non-increasing; a point passes it when its own key is
    /// ≤ (up to the margins). `never` and `undecidable` are the indices of the boundaries tested when
    /// a bin holds no unsettled boundary (passed by none) or more than one (always undecided);
    /// `exact[m]` says whether boundary m has an exact test (not edge-guarded).
    fn new(
        keys: &[f64],
        exact: &[bool],
        lowest: f64,
        highest: f64,
        never: usize,
        undecidable: usize,
    ) -> Self {
        let spacing = keys
            .windows(2)
            .filter(|w| w[0].is_finite() && w[1].is_finite())
            .map(|w| w[0] - w[1])
            .filter(|&d| d > 0.0)
            .fold(f64::INFINITY, f64::min);
        let span = highest - lowest;
        // Bins of half the closest spacing leave at most one boundary unsettled per bin (when the
        // spacing exceeds 4·KEY_MARGIN; closer boundaries just make their bins undecidable).
        let bins = (span / (0.5 * spacing))
            .ceil()
            .clamp(16.0, (1 << 16) as f64) as usize;
        let bin_width = span / bins as f64;
        let (bins, tests) = (0..bins)
            .map(|bin| {
                let lower = lowest + bin as f64 * bin_width;
                let upper = lower + bin_width;
                let passed = keys.partition_point(|&key| key >= upper + KEY_MARGIN);
                let unsettled = keys.partition_point(|&key| key >= lower - KEY_MARGIN) - passed;
                let test = match unsettled {
                    0 => never,
                    1 => passed,
                    _ => undecidable,
                };
                let test_key = if test == never {
                    f32::NEG_INFINITY
                } else if test == undecidable || !exact[test] {
                    f32::NAN
                } else {
                    keys[test] as f32
                };
                let bin = Bin {
                    passed: passed as u32,
                    test_key,
                };
                (bin, test as u32)
            })
            .unzip();
        BinTable {
            bins,
            tests,
            lowest: lowest as f32,
            bins_per_unit: (1.0 / bin_width) as f32,
        }
    }

    /// The bin of a key: `⌊(key − lowest)·bins_per_unit⌋` clamped to the table, up to rounding at bin
    /// edges (which `KEY_MARGIN` covers). Any key, even NaN, lands in some bin (callers only trust
    /// bins of finite keys). Branch-free float32 arithmetic that vectorises: the clamped position
    /// minus ½ is rounded to an integer by adding 2²³, whose float32 bits then hold it.
    #[inline(always)]
    fn index(&self, key: f32) -> u32 {
        const TWO_POW_23: f32 = 8_388_608.0;
        let position = (key - self.lowest) * self.bins_per_unit;
        let highest = self.bins.len() as f32 - 0.5;
        let position = if position < highest {
            position
        } else {
            highest
        };
        // NaN fails the comparison and goes to bin 0.
        let position = if position >= 0.5 { position } else { 0.5 };
        (position - 0.5 + TWO_POW_23).to_bits() - TWO_POW_23.to_bits()
    }

    #[inline(always)]
    fn bin(&self, index: u32) -> Bin {
        self.bins[index as usize]
    }

    #[inline(always)]
    fn test(&self, index: u32) -> usize {
        self.tests[index as usize] as usize
    }
}

/// One padded azimuth boundary: the point `(x, y)` passes it when
/// `cos·y − sin·x + beyond[y < 0]·(|x| + |y|) ≤ 0`. `beyond` is 0 where the cross product decides
/// (point and boundary in the same half-plane of y's sign, so less than π apart), ∓∞ where the
/// half-plane alone does; NaN everywhere makes the test undecided.
#[derive(Clone, Copy)]
struct AzimuthBoundary {
    cos: f64,
    sin: f64,
    beyond: [f64; 2],
}

impl AzimuthBoundary {
    const ALWAYS: Self = AzimuthBoundary {
        cos: 0.0,
        sin: 0.0,
        beyond: [f64::NEG_INFINITY; 2],
    };
    const NEVER: Self = AzimuthBoundary {
        cos: 0.0,
        sin: 0.0,
        beyond: [f64::INFINITY; 2],
    };
    const UNDECIDABLE: Self = AzimuthBoundary {
        cos: f64::NAN,
        sin: f64::NAN,
        beyond: [f64::NAN; 2],
    };
}

/// Monotone stand-in for the azimuth `atan2(y, x)` on (−π, π]: `y/(|x|+|y|)` in the right
/// half-plane, continued to (−2, 2] on the left.
#[inline(always)]
fn pseudo_azimuth(x: f32, y: f32) -> f32 {
    let q = y / (x.abs() + y.abs());
    if x >= 0.0 {
        q
    } else {
        2.0f32.copysign(y) - q
    }
}

/// Everything `project_flat` needs to find a point's cell quickly and exactly.
struct CellLocator {
    row0: f64,
    col0: f64,
    rows_per_radian: f64,
    cols_per_radian: f64,
    height: usize,
    width: usize,
    /// `sin β` of the padded elevation boundaries: +∞ (passed by all), boundaries 0 ..= height,
    /// −∞ (passed by none), NaN (undecidable).
    elevation_sines: Vec<f64>,
    elevation_bins: BinTable,
    /// Padded azimuth boundaries, in the same layout.
    azimuth: Vec<AzimuthBoundary>,
    azimuth_bins: BinTable,
}

impl CellLocator {
    fn new(config: &CylinderConfig) -> Self {
        use std::f64::consts::{FRAC_PI_2, PI};
        let row0 = config.row_of_zero_elevation();
        let col0 = config.col_of_zero_azimuth();
        let rows_per_radian = 1.0 / config.vertical_resolution_deg.to_radians();
        let cols_per_radian = 1.0 / config.horizontal_resolution_deg.to_radians();
        let (height, width) = (config.height, config.width);

        // Boundary k of an axis: the angle at which `origin − angle·cells_per_radian + ½ = k`.
        let mut elevation_sines = vec![f64::INFINITY];
        let mut elevation_keys = vec![f64::INFINITY];
        for k in 0..=height {
            let beta = (row0 + 0.5 - k as f64) / rows_per_radian;
            let (sine, key) = if beta >= FRAC_PI_2 + EDGE_GUARD {
                (f64::INFINITY, f64::INFINITY)
            } else if beta <= -FRAC_PI_2 - EDGE_GUARD {
                (f64::NEG_INFINITY, f64::NEG_INFINITY)
            } else if beta.abs() > FRAC_PI_2 - EDGE_GUARD {
                (f64::NAN, 1.0f64.copysign(beta))
            } else {
                (beta.sin(), beta.sin())
            };
            elevation_sines.push(sine);
            elevation_keys.push(key);
        }
        elevation_sines.extend([f64::NEG_INFINITY, f64::NAN]);
        elevation_keys.extend([f64::NEG_INFINITY, f64::NEG_INFINITY]);
        let exact: Vec<bool> = elevation_sines.iter().map(|s| !s.is_nan()).collect();
        let elevation_bins =
            BinTable::new(&elevation_keys, &exact, -1.0, 1.0, height + 2, height + 3);

        let mut azimuth = vec![AzimuthBoundary::ALWAYS];
        let mut azimuth_keys = vec![f64::INFINITY];
        for k in 0..=width {
            let alpha = (col0 + 0.5 - k as f64) / cols_per_radian;
            let (boundary, key) = if alpha >= PI + EDGE_GUARD {
                (AzimuthBoundary::ALWAYS, f64::INFINITY)
            } else if alpha <= -PI - EDGE_GUARD {
                (AzimuthBoundary::NEVER, f64::NEG_INFINITY)
            } else if alpha.abs() > PI - EDGE_GUARD {
                (AzimuthBoundary::UNDECIDABLE, 2.0f64.copysign(alpha))
            } else {
                let (sin, cos) = alpha.sin_cos();
                // y ≥ 0 means an azimuth in [0, π], y < 0 one in (−π, 0): in the boundary's own
                // half-plane the cross product decides, in the other one the boundary's sign does.
                let beyond = if alpha > 0.0 {
                    [0.0, f64::NEG_INFINITY]
                } else {
                    [f64::INFINITY, 0.0]
                };
                // The key in float64 (the points' is float32; KEY_MARGIN covers the difference).
                let q = sin / (cos.abs() + sin.abs());
                let key = if cos >= 0.0 {
                    q
                } else {
                    2.0f64.copysign(sin) - q
                };
                (AzimuthBoundary { cos, sin, beyond }, key)
            };
            azimuth.push(boundary);
            azimuth_keys.push(key);
        }
        azimuth.extend([AzimuthBoundary::NEVER, AzimuthBoundary::UNDECIDABLE]);
        azimuth_keys.extend([f64::NEG_INFINITY, f64::NEG_INFINITY]);
        let exact: Vec<bool> = azimuth.iter().map(|b| !b.cos.is_nan()).collect();
        let azimuth_bins = BinTable::new(&azimuth_keys, &exact, -2.0, 2.0, width + 2, width + 3);

        CellLocator {
            row0,
            col0,
            rows_per_radian,
            cols_per_radian,
            height,
            width,
            elevation_sines,
            elevation_bins,
            azimuth,
            azimuth_bins,
        }
    }

    /// `(cell or NO_CELL, range)` of a finite point, by the libm formula alone.
    #[inline(never)]
    fn exact(&self, x: f64, y: f64, z: f64) -> (u32, f32) {
        let range = (x * x + y * y + z * z).sqrt();
        // At the origin, or farther than a float32 range can say (finite coordinates near f32::MAX):
        // out of view rather than an infinite range in the image.
        if range == 0.0 || !(range as f32).is_finite() {
            return (NO_CELL, 0.0);
        }
        let row = exact_cell(self.row0, z, (x * x + y * y).sqrt(), self.rows_per_radian);
        let col = exact_cell(self.col0, y, x, self.cols_per_radian);
        (self.cell(row, col), range as f32)
    }

    #[inline(always)]
    fn cell(&self, row: i64, col: i64) -> u32 {
        if row < 0 || col < 0 || row >= self.height as i64 || col >= self.width as i64 {
            NO_CELL
        } else {
            (row as usize * self.width + col as usize) as u32
        }
    }

    /// The padded count of elevation boundaries passed, by the bin's float64 test; `None` when the
    /// point is within `BOUNDARY_MARGIN` of it.
    #[inline(never)]
    fn exact_row_count(&self, bin: u32, z: f64, range: f64) -> Option<i64> {
        let passed = self.elevation_bins.bin(bin).passed as i64;
        let side = z - range * self.elevation_sines[self.elevation_bins.test(bin)];
        (side.abs() > BOUNDARY_MARGIN * range).then_some(passed + (side <= 0.0) as i64)
    }

    /// Like [`Self::exact_row_count`] for the azimuth.
    #[inline(never)]
    fn exact_col_count(&self, bin: u32, x: f64, y: f64) -> Option<i64> {
        let passed = self.azimuth_bins.bin(bin).passed as i64;
        let b = &self.azimuth[self.azimuth_bins.test(bin)];
        let norm1 = x.abs() + y.abs();
        let side = b.cos * y - b.sin * x + b.beyond[y.is_sign_negative() as usize] * norm1;
        (side.abs() > BOUNDARY_MARGIN * norm1).then_some(passed + (side <= 0.0) as i64)
    }

    /// `(cell, range)` of every point of a block of at most [`BLOCK`] points (`NO_CELL` outside the
    /// image or at the origin, `NON_FINITE` for NaN/Inf values), written to `out`. The arithmetic
    /// runs in loops over the block that vectorise, with the table reads between them.
    fn locate_block(&self, points: &[f32], channels: usize, out: &mut Located) {
        // Separate code for each point layout: the loops below then know their stride.
        if channels == 4 {
            self.locate_block_of::<4>(points, out)
        } else {
            self.locate_block_of::<3>(points, out)
        }
    }

    #[inline(always)]
    fn locate_block_of<const CHANNELS: usize>(&self, points: &[f32], out: &mut Located) {
        let channels = CHANNELS;
        let n = points.len() / CHANNELS;
        let mut xyz = [[0.0f32; BLOCK]; 3];
        let mut reflectance_finite = [1u32; BLOCK];
        if n == BLOCK {
            // A full block: fixed trip count and stride, so the loads can be shuffled into lanes.
            let points = &points[..BLOCK * CHANNELS];
            for i in 0..BLOCK {
                let p = &points[i * CHANNELS..i * CHANNELS + CHANNELS];
                (xyz[0][i], xyz[1][i], xyz[2][i]) = (p[0], p[1], p[2]);
                if CHANNELS == 4 {
                    reflectance_finite[i] = p[3].is_finite() as u32;
                }
            }
        } else {
            for (i, p) in points.chunks_exact(CHANNELS).enumerate() {
                (xyz[0][i], xyz[1][i], xyz[2][i]) = (p[0], p[1], p[2]);
                if CHANNELS == 4 {
                    reflectance_finite[i] = p[3].is_finite() as u32;
                }
            }
        }
        let [xs, ys, zs] = &xyz;
        // Ranges in float64 (the output's exact value), keys and bins in float32 (four lanes).
        let ranges32 = &mut out.ranges;
        for i in 0..BLOCK {
            let (x, y, z) = (xs[i] as f64, ys[i] as f64, zs[i] as f64);
            ranges32[i] = (x * x + y * y + z * z).sqrt() as f32;
        }
        let mut row_keys = [0.0f32; BLOCK];
        let mut col_keys = [0.0f32; BLOCK];
        let mut row_bins = [0u32; BLOCK];
        let mut col_bins = [0u32; BLOCK];
        // 0/1 flags as u32: whole lanes, no packing of booleans.
        let mut ordinary = [0u32; BLOCK];
        for i in 0..BLOCK {
            let (x, y, z, range) = (xs[i], ys[i], zs[i], ranges32[i]);
            row_keys[i] = z / range;
            col_keys[i] = pseudo_azimuth(x, y);
            row_bins[i] = self.elevation_bins.index(row_keys[i]);
            col_bins[i] = self.azimuth_bins.index(col_keys[i]);
            // The keys are trustworthy for normal float32 values without overflow and a direction
            // in the plane; anything else, including NaN/Inf (whose range fails the comparisons),
            // goes to the formula.
            ordinary[i] = ((range < 1e18) & (range > 1e-30) & (x.abs() + y.abs() > 0.0)) as u32
                & reflectance_finite[i];
        }
        let mut row_bin = [Bin {
            passed: 0,
            test_key: 0.0,
        }; BLOCK];
        let mut col_bin = row_bin;
        for i in 0..BLOCK {
            row_bin[i] = self.elevation_bins.bin(row_bins[i]);
            col_bin[i] = self.azimuth_bins.bin(col_bins[i]);
        }
        // Padded counts from the keys alone, settled when the key is `FAST_KEY_MARGIN` clear of the
        // bin's unsettled boundary (almost always).
        let mut settled = [0u32; BLOCK];
        // Cells fit u32 (checked by `project_flat`); counts stay far below 2³¹.
        let (height, width) = (self.height as i32, self.width as i32);
        for i in 0..BLOCK {
            let (row_key, col_key) = (row_keys[i], col_keys[i]);
            let (rb, cb) = (row_bin[i], col_bin[i]);
            let row = rb.passed as i32 + (row_key <= rb.test_key) as i32 - 2;
            let col = cb.passed as i32 + (col_key <= cb.test_key) as i32 - 2;
            let inside = (row >= 0) & (col >= 0) & (row < height) & (col < width);
            let cell = (row as u32)
                .wrapping_mul(width as u32)
                .wrapping_add(col as u32);
            out.cells[i] = if inside { cell } else { NO_CELL };
            settled[i] = ordinary[i]
                & ((row_key - rb.test_key).abs() > FAST_KEY_MARGIN) as u32
                & ((col_key - cb.test_key).abs() > FAST_KEY_MARGIN) as u32;
        }
        // Most blocks are settled throughout: one vectorised check instead of a branch per point.
        if settled.iter().fold(1, |all, &s| all & s) == 0 {
            for i in 0..n {
                if settled[i] == 0 {
                    let p = &points[i * channels..(i + 1) * channels];
                    (out.cells[i], out.ranges[i]) = self.locate_slowly(p, row_bins[i], col_bins[i]);
                }
            }
        }
    }

    /// [`Self::locate_block`] for a point whose keys did not settle its cell: the float64 tests,
    /// and the formula for what they cannot decide (or for unusual points).
    #[inline(never)]
    fn locate_slowly(&self, p: &[f32], row_bin: u32, col_bin: u32) -> (u32, f32) {
        if !p.iter().all(|v| v.is_finite()) {
            return (NON_FINITE, 0.0);
        }
        let (x32, y32, z32) = (p[0], p[1], p[2]);
        let (x, y, z) = (x32 as f64, y32 as f64, z32 as f64);
        let range = (x * x + y * y + z * z).sqrt();
        let usual = range < 1e18 && range as f32 > 1e-30 && x32.abs() + y32.abs() > 0.0;
        if !usual {
            return self.exact(x, y, z);
        }
        let row = match self.exact_row_count(row_bin, z, range) {
            Some(m) => m - 2,
            None => exact_cell(self.row0, z, (x * x + y * y).sqrt(), self.rows_per_radian),
        };
        let col = match self.exact_col_count(col_bin, x, y) {
            Some(m) => m - 2,
            None => exact_cell(self.col0, y, x, self.cols_per_radian),
        };
        (self.cell(row, col), range as f32)
    }
}

/// `points` must be a flat array of whole points of 3 (x, y, z) or 4 (… reflectance) values.
fn check_flat_points(points: &[f32], channels: usize) -> Result<()> {
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
    Ok(())
}

/// Φ (Eq. 1) for a whole scan: every cell keeps its closest point (ties: the lower input index).
///
/// `points` is a flat row-major array of `N × channels` values, `channels` = 3 (x, y, z) or 4 (x, y, z,
/// reflectance), `N < 2³¹ − 1`. Points with a NaN/Inf value are dropped and counted; so are points
/// outside the cropped image. A point's cell is exactly the float64 formula
/// `⌊row₀ − atan2(z, √(x²+y²))·(1/Δφ) + ½⌋`, `⌊col₀ − atan2(y, x)·(1/Δθ) + ½⌋` (libm `atan2`, angles in
/// radians), found without evaluating it (see the comment above `BOUNDARY_MARGIN`). Runs in the
/// caller's rayon pool; the result does not depend on the number of threads.
pub fn project_flat(
    points: &[f32],
    channels: usize,
    config: &CylinderConfig,
) -> Result<Projection> {
    config.validate()?;
    check_flat_points(points, channels)?;
    let (height, width) = (config.height, config.width);
    // Below 2³¹ cells, the lookup's 32-bit arithmetic is exact (that is already a 32 GiB image).
    if height * width >= i32::MAX as usize {
        return Err(Error::invalid(
            "config",
            format!("image too large: {height} x {width} cells, at most 2^31 - 1"),
        ));
    }
    let locator = cached_locator(config);
    if points.len() / channels >= i32::MAX as usize {
        return Err(Error::invalid(
            "points",
            format!(
                "{} points, at most 2^31 - 2 supported",
                points.len() / channels
            ),
        ));
    }
    // One piece per thread, each filling its own buffer of closest points; buffers merge by `min`,
    // which does not depend on the order, so the result is the same for any number of threads.
    let threads = rayon::current_num_threads().max(1);
    let blocks = (points.len() / channels).div_ceil(BLOCK);
    let piece = blocks.div_ceil(threads).max(1) * BLOCK * channels;
    let fill = |first: usize, points: &[f32]| {
        let mut image = ClosestPoints::new(height * width);
        let mut located = Located {
            cells: [NO_CELL; BLOCK],
            ranges: [0.0; BLOCK],
        };
        for (block, points) in points.chunks(BLOCK * channels).enumerate() {
            locator.locate_block(points, channels, &mut located);
            image.add(first + block * BLOCK, &located, points.len() / channels);
        }
        image
    };
    let image = if threads == 1 || points.len() <= piece {
        fill(0, points)
    } else {
        points
            .par_chunks(piece)
            .enumerate()
            .map(|(k, points)| fill(k * piece / channels, points))
            .reduce_with(ClosestPoints::merge)
            .unwrap_or_else(|| ClosestPoints::new(height * width))
    };
    Ok(image.finish(points, channels, height, width))
}

/// The running closest point of every cell as one `u64` per cell: the range's float32 bits above the
/// point's index, so that the smaller key is the closer point and, at equal range, the lower index —
/// exactly the rule "closest, ties to the lower index" — and adding a point is a `min`. One spare
/// cell at the end takes the points outside the image, so adding needs no branch. The buffer is kept
/// per thread between calls (no fresh pages to fault in each time).
struct ClosestPoints {
    best: Vec<u64>,
    num_non_finite: usize,
    num_out_of_view: usize,
}

thread_local! {
    static BEST_BUFFER: std::cell::RefCell<Vec<u64>> = const { std::cell::RefCell::new(Vec::new()) };
}

impl ClosestPoints {
    const EMPTY: u64 = u64::MAX;

    fn new(cells: usize) -> Self {
        let mut best = BEST_BUFFER.with(|buffer| std::mem::take(&mut *buffer.borrow_mut()));
        best.clear();
        best.resize(cells + 1, Self::EMPTY);
        ClosestPoints {
            best,
            num_non_finite: 0,
            num_out_of_view: 0,
        }
    }

    /// Adds points `first, first + 1, …` (indices below `i32::MAX`, checked by the caller).
    #[inline]
    fn add(&mut self, first: usize, located: &Located, n: usize) {
        let spare = self.best.len() - 1;
        let (mut non_finite, mut out_of_view) = (0, 0);
        for (i, (&cell, &range)) in located.cells[..n]
            .iter()
            .zip(&located.ranges[..n])
            .enumerate()
        {
            non_finite += (cell == NON_FINITE) as usize;
            out_of_view += (cell == NO_CELL) as usize;
            let slot = &mut self.best[(cell as usize).min(spare)];
            *slot = (*slot).min(((range.to_bits() as u64) << 32) | (first + i) as u64);
        }
        self.num_non_finite += non_finite;
        self.num_out_of_view += out_of_view;
    }

    /// Combines the closest points of two sets of points.
    fn merge(mut self, other: Self) -> Self {
        for (mine, theirs) in self.best.iter_mut().zip(&other.best) {
            *mine = (*mine).min(*theirs);
        }
        self.num_non_finite += other.num_non_finite;
        self.num_out_of_view += other.num_out_of_view;
        other.recycle();
        self
    }

    /// Keeps the buffer for the next call on this thread, unless it is huge (then memory matters
    /// more than page faults).
    fn recycle(mut self) {
        const KEEP_AT_MOST: usize = 1 << 22; // cells: 32 MiB
        let best = std::mem::take(&mut self.best);
        if best.capacity() <= KEEP_AT_MOST {
            BEST_BUFFER.with(|buffer| *buffer.borrow_mut() = best);
        }
    }

    /// The images (`points`, `channels` per point, supply the reflectance of the kept points).
    fn finish(self, points: &[f32], channels: usize, height: usize, width: usize) -> Projection {
        let cells = height * width;
        // Separate passes: the first two vectorise.
        let best = &self.best[..cells];
        let range = best
            .iter()
            .map(|&key| {
                let bits = (key >> 32) as u32;
                if bits == u32::MAX {
                    0.0
                } else {
                    f32::from_bits(bits)
                }
            })
            .collect();
        // Indices are below 2³¹ (checked by `project_flat`), and EMPTY's low half is −1 as i32.
        let index: Vec<i64> = best.iter().map(|&key| key as u32 as i32 as i64).collect();
        let reflectance = if channels == 4 {
            index
                .iter()
                .map(|&i| {
                    if i >= 0 {
                        points[i as usize * 4 + 3]
                    } else {
                        0.0
                    }
                })
                .collect()
        } else {
            vec![0.0; cells]
        };
        let (num_non_finite, num_out_of_view) = (self.num_non_finite, self.num_out_of_view);
        self.recycle();
        Projection {
            height,
            width,
            range,
            reflectance,
            index,
            num_non_finite,
            num_out_of_view,
        }
    }
}

/// Tables of the most recent config, reused while calls keep the same config (building them costs
/// about a tenth of projecting a scan).
fn cached_locator(config: &CylinderConfig) -> Arc<CellLocator> {
    static CACHE: Mutex<Option<(CylinderConfig, Arc<CellLocator>)>> = Mutex::new(None);
    // A poisoned cache only means another thread panicked while holding it; the data is replaced.
    let mut cache = CACHE
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    match &*cache {
        Some((cached, locator)) if cached == config => Arc::clone(locator),
        _ => {
            let locator = Arc::new(CellLocator::new(config));
            *cache = Some((*config, Arc::clone(&locator)));
            locator
        }
    }
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

/// The previous implementation (a vectorised arctangent per axis, libm within its error of a cell
/// boundary), kept as the reference the table-based lookup must reproduce bit for bit.
#[cfg(test)]
mod reference {
    use rayon::prelude::*;

    use super::{CylinderConfig, Projection, NON_FINITE, NO_CELL};
    use crate::error::{Error, Result};

    /// Bound on the error of [`atan2_lanes`], radians: the series is cut after the u¹³ term for |u| ≤
    /// tan(π/8), so the first omitted term is below 0.4143¹⁵/15 = 1.3e-7; 1e-6 leaves room for rounding.
    pub(super) const ATAN_ERROR_BOUND: f64 = 1e-6;

    /// Points per lane group of the vectorised arctangent.
    pub(super) const LANES: usize = 8;

    /// `atan2(y, x)` within [`ATAN_ERROR_BOUND`] for a group of points, with libm's quadrants and signs
    /// (also of −0): the octant reduced to |u| ≤ tan(π/8) by `atan t = π/4 + atan((t−1)/(t+1))` (one
    /// division either way), then the odd Taylor series; written branch-free.
    #[inline(always)]
    pub(super) fn atan2_lanes(y: &[f64; LANES], x: &[f64; LANES]) -> [f64; LANES] {
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
                        - u2 * (1.0 / 7.0
                            - u2 * (1.0 / 9.0 - u2 * (1.0 / 11.0 - u2 * (1.0 / 13.0))))));
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
    pub(super) fn cell_index(origin: f64, fast: f64, y: f64, x: f64, cells_per_radian: f64) -> f64 {
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

    /// The previous `project_flat` (fast arctangents, libm near boundaries), unchanged.
    ///
    /// `points` is a flat row-major array of `N × channels` values, `channels` = 3 (x, y, z) or 4 (x, y, z,
    /// reflectance). Points with a NaN/Inf value are dropped and counted; so are points outside the
    /// cropped image. Runs in the caller's rayon pool.
    pub(super) fn project_flat(
        points: &[f32],
        channels: usize,
        config: &CylinderConfig,
    ) -> Result<Projection> {
        config.validate()?;
        super::check_flat_points(points, channels)?;
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
            // Unlike the previous version: beyond a float32 range is out of view, not an infinite range.
            if range == 0.0 || !(range as f32).is_finite() {
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
}

#[cfg(test)]
mod tests {
    use super::reference::{atan2_lanes, cell_index, ATAN_ERROR_BOUND, LANES};
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

    /// Runs both implementations in a one-thread and a three-thread pool (the two code paths) and
    /// requires identical images, indices and counts.
    fn assert_same_as_reference(points: &[f32], channels: usize, config: &CylinderConfig) {
        let expected = reference::project_flat(points, channels, config).unwrap();
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let got = pool
                .install(|| project_flat(points, channels, config))
                .unwrap();
            if got != expected {
                let differing: Vec<usize> = (0..got.index.len())
                    .filter(|&c| got.index[c] != expected.index[c])
                    .take(5)
                    .collect();
                panic!(
                    "{config:?}, {threads} threads: cells {differing:?} differ (got {:?}, expected \
                     {:?}); counts {:?} vs {:?}",
                    differing.iter().map(|&c| got.index[c]).collect::<Vec<_>>(),
                    differing.iter().map(|&c| expected.index[c]).collect::<Vec<_>>(),
                    (got.num_non_finite, got.num_out_of_view),
                    (expected.num_non_finite, expected.num_out_of_view),
                );
            }
        }
    }

    fn read_scan(path: &std::path::Path) -> Option<Vec<f32>> {
        let bytes = std::fs::read(path).ok()?;
        Some(
            bytes
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect(),
        )
    }

    /// Configs with every kind of edge: the presets, the full 360° grid (1801 and 1800 columns),
    /// fields of view reaching the poles, coarse and odd resolutions (a boundary within 1e-6 rad of
    /// ±180°), tiny crops.
    fn edge_configs() -> Vec<CylinderConfig> {
        let kitti = CylinderConfig::kitti();
        vec![
            kitti,
            CylinderConfig::argoverse(),
            CylinderConfig {
                height: 68,
                width: 1801,
                ..kitti
            },
            CylinderConfig {
                width: 1800,
                ..kitti
            },
            CylinderConfig {
                fov_up_deg: 90.0,
                fov_down_deg: -90.0,
                vertical_resolution_deg: 1.0,
                horizontal_resolution_deg: 1.0,
                height: 181,
                width: 361,
            },
            CylinderConfig {
                fov_up_deg: 89.9,
                fov_down_deg: -89.7,
                vertical_resolution_deg: 0.7,
                horizontal_resolution_deg: 360.0 / 901.0,
                height: 200,
                width: 901,
            },
            CylinderConfig {
                fov_up_deg: 30.0,
                fov_down_deg: -30.0,
                vertical_resolution_deg: 7.0,
                horizontal_resolution_deg: 45.0,
                height: 9,
                width: 9,
            },
            CylinderConfig {
                fov_up_deg: 10.0,
                fov_down_deg: -10.0,
                vertical_resolution_deg: 20.0,
                horizontal_resolution_deg: 180.0,
                height: 2,
                width: 3,
            },
            CylinderConfig {
                height: 1,
                width: 1,
                ..kitti
            },
        ]
    }

    /// Points on and within a few float32 steps of every cell boundary and corner of `config`, plus
    /// the poles, the origin, ±0 and the ±180° ray, huge, tiny and non-finite values.
    fn adversarial_points(config: &CylinderConfig, rng: &mut ChaCha8Rng) -> Vec<f32> {
        let row0 = config.row_of_zero_elevation();
        let col0 = config.col_of_zero_azimuth();
        let d_phi = config.vertical_resolution_deg.to_radians();
        let d_theta = config.horizontal_resolution_deg.to_radians();
        let rows: Vec<f64> = (-1..=config.height as i64 + 1)
            .map(|k| (row0 + 0.5 - k as f64) * d_phi)
            .collect();
        let cols: Vec<f64> = (-1..=config.width as i64 + 1)
            .map(|k| (col0 + 0.5 - k as f64) * d_theta)
            .collect();
        let nudge = |v: f32, steps: i32| -> f32 {
            let mut v = v;
            for _ in 0..steps.abs() {
                v = if steps > 0 {
                    v.next_up()
                } else {
                    v.next_down()
                };
            }
            v
        };
        let mut points = Vec::new();
        let push = |p: [f32; 3], points: &mut Vec<f32>| {
            points.extend_from_slice(&[p[0], p[1], p[2], 0.5]);
        };
        for _ in 0..4000 {
            // A boundary of one axis (or both), random position along the other, a few ulps off.
            let elevation = if rng.random_bool(0.5) {
                rows[rng.random_range(0..rows.len())]
            } else {
                rng.random_range(-1.6..1.6)
            };
            let azimuth = if rng.random_bool(0.7) {
                cols[rng.random_range(0..cols.len())]
            } else {
                rng.random_range(-3.2..3.2)
            };
            let range = [1e-3, 0.7, 13.0, 80.0, 1e6][rng.random_range(0..5)];
            let (se, ce) = f64::sin_cos(elevation);
            let (sa, ca) = f64::sin_cos(azimuth);
            let base = [
                (range * ce * ca) as f32,
                (range * ce * sa) as f32,
                (range * se) as f32,
            ];
            for _ in 0..3 {
                let p = [
                    nudge(base[0], rng.random_range(-2..=2)),
                    nudge(base[1], rng.random_range(-2..=2)),
                    nudge(base[2], rng.random_range(-2..=2)),
                ];
                push(p, &mut points);
            }
        }
        let specials = [
            0.0f32,
            -0.0,
            1.0,
            -1.0,
            1e-45,
            -1e-45,
            1e-38,
            3e38,
            -3e38,
            1e19,
            f32::MAX,
            f32::MIN_POSITIVE,
        ];
        for &x in &specials {
            for &y in &specials {
                for &z in &specials {
                    push([x, y, z], &mut points);
                }
            }
        }
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            push([bad, 1.0, 1.0], &mut points);
            push([1.0, bad, 1.0], &mut points);
            push([1.0, 1.0, bad], &mut points);
            points.extend_from_slice(&[1.0, 1.0, 1.0, bad]);
        }
        // Duplicates and equal ranges in one cell: the tie rule.
        for _ in 0..3 {
            push([5.0, 0.01, -0.3], &mut points);
            push([5.0, -0.01, -0.3], &mut points);
        }
        points
    }

    #[test]
    fn table_lookup_equals_the_arctangent_reference_on_adversarial_points() {
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        for config in edge_configs() {
            config.validate().unwrap();
            let points = adversarial_points(&config, &mut rng);
            assert_same_as_reference(&points, 4, &config);
            let xyz: Vec<f32> = points
                .chunks_exact(4)
                .flat_map(|p| [p[0], p[1], p[2]])
                .collect();
            assert_same_as_reference(&xyz, 3, &config);
        }
    }

    #[test]
    fn table_lookup_equals_the_arctangent_reference_on_real_scans() {
        let data = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data");
        let scans: Vec<Vec<f32>> = [
            "kitti_raw_static/0000000000.bin",
            "kitti_raw_static/0000000005.bin",
            "semantickitti_08_pair/000720.bin",
            "semantickitti_08_pair/001500.bin",
        ]
        .iter()
        .filter_map(|name| read_scan(&data.join(name)))
        .collect();
        if scans.is_empty() {
            eprintln!("no KITTI scans under {}: skipped", data.display());
            return;
        }
        for scan in &scans {
            for config in edge_configs() {
                assert_same_as_reference(scan, 4, &config);
            }
        }
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
        assert_eq!(config.column_period(), None);
        let full = CylinderConfig {
            height: 68,
            width: 1801,
            ..config
        };
        assert_eq!(full.column_period(), Some(1800));
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
        // Images too large to allocate are refused by the validation, naming the setting, before any
        // function allocates them.
        let huge = CylinderConfig {
            fov_up_deg: 0.5,
            fov_down_deg: -0.5,
            vertical_resolution_deg: 0.001,
            horizontal_resolution_deg: 1e-4,
            height: 1000,
            width: 3_600_000,
        };
        let too_many_cells = Err(Error::InvalidArgument {
            argument: "height * width",
            reason: "1000 * 3600000 cells, more than the 67108864 (2^26) an image may have".into(),
        });
        assert_eq!(huge.validate(), too_many_cells);
        assert!(matches!(
            project_flat(&[], 4, &huge),
            Err(Error::InvalidArgument {
                argument: "height * width",
                ..
            })
        ));
        let wide = CylinderConfig {
            horizontal_resolution_deg: 1e-5,
            width: 30_000_000,
            ..config
        };
        assert!(matches!(
            wide.validate(),
            Err(Error::InvalidArgument {
                argument: "height * width",
                ..
            })
        ));
        for (vertical, horizontal, at_fault) in [
            (0.4, 1e-9, "horizontal_resolution_deg"),
            (1e-300, 0.2, "vertical_resolution_deg"),
            (0.4, 5e-324, "horizontal_resolution_deg"),
        ] {
            let fine = CylinderConfig {
                vertical_resolution_deg: vertical,
                horizontal_resolution_deg: horizontal,
                ..config
            };
            assert!(
                matches!(fine.validate(), Err(Error::InvalidArgument { argument, .. }) if argument == at_fault),
                "{vertical} x {horizontal}: {:?}",
                fine.validate()
            );
        }
        // Up to the cap, a large image is fine.
        let largest = CylinderConfig {
            horizontal_resolution_deg: 0.01,
            width: 36_001,
            height: 64,
            ..config
        };
        largest.validate().unwrap();
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
