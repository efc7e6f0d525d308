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

mod config;
mod image;
mod locate;
/// The previous implementation (a vectorised arctangent per axis, libm within its error of a cell
/// boundary), kept as the reference the table-based lookup must reproduce bit for bit.
#[cfg(test)]
mod reference;
#[cfg(test)]
mod tests;

pub use config::{CylinderConfig, MAX_IMAGE_CELLS};
pub use image::{point_cells, project, project_flat, unproject_many, Projection};

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
