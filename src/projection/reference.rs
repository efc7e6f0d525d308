use rayon::prelude::*;

use super::image::check_flat_points;
use super::locate::{NON_FINITE, NO_CELL};
use super::{CylinderConfig, Projection};
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
    check_flat_points(points, channels)?;
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
