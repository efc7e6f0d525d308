#![forbid(unsafe_code)]
//! Decoding the network's output into 3D point pairs (paper §III-C, §III-D step 1).
//!
//! For every reference cell `c_r` with a range, a confidence ≥ the threshold and no exclusion mark:
//! `p'_r = Φ⁻¹(c_r, D_r)` (the virtual point at the cell centre) and, with the predicted location
//! `ĉ_t = c_r + flow`, `p̂_t = Φ⁻¹(ĉ_t, D_t(ĉ_t))`. The target range is sampled at the sub-pixel location
//! without blending across depth edges: bilinear when the 4 surrounding cells are all valid and their
//! ranges agree (spread ≤ `max_relative_range_spread` × the smallest), otherwise the range of the
//! nearest valid one of them. Matches whose `ĉ_t` leaves the image (or, for a 360° image, whose
//! columns wrap) are handled like the ground truth: wrapped when the image is a full circle, dropped
//! when the crop loses them.

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::ground_truth::check_range_image;
use crate::nms::SuppressionGrid;
use crate::projection::{floor_fast, CylinderConfig};

/// Thresholds of [`decode_matches`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DecodeConfig {
    /// Cells with a lower confidence are dropped.
    pub min_confidence: f32,
    /// Bilinear range sampling only when `max − min ≤ this × min` over the 4 neighbours.
    pub max_relative_range_spread: f32,
}

impl Default for DecodeConfig {
    fn default() -> Self {
        DecodeConfig {
            min_confidence: 0.0,
            max_relative_range_spread: 0.1,
        }
    }
}

/// Decoded matches, one entry per kept reference cell, in row-major cell order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DecodedMatches {
    /// Virtual reference points `p'_r` (cell centres), reference frame.
    pub source: Vec<Point3<f64>>,
    /// Predicted target points `p̂_t`, target frame.
    pub target: Vec<Point3<f64>>,
    /// The network's confidence of each match.
    pub confidence: Vec<f32>,
    /// Reference cell `[row, col]` of each match.
    pub cells: Vec<[usize; 2]>,
}

impl DecodedMatches {
    fn with_capacity(n: usize) -> Self {
        DecodedMatches {
            source: Vec::with_capacity(n),
            target: Vec::with_capacity(n),
            confidence: Vec::with_capacity(n),
            cells: Vec::with_capacity(n),
        }
    }

    /// Number of matches.
    pub fn len(&self) -> usize {
        self.confidence.len()
    }

    /// True when no cell survived.
    pub fn is_empty(&self) -> bool {
        self.confidence.is_empty()
    }
}

/// Samples the range image at a continuous location (see the module docs); `None` when no valid cell
/// surrounds it or it lies outside the image. `col` must already be wrapped for 360° images.
pub fn sample_range(
    range: &[f32],
    row: f64,
    col: f64,
    config: &CylinderConfig,
    max_relative_spread: f32,
) -> Option<f64> {
    let (height, width) = (config.height as i64, config.width as i64);
    config.cell_of(row, col)?;
    let (r0, c0) = (floor_fast(row), floor_fast(col));
    let (fr, fc) = (row - r0, col - c0);
    let (r0, c0) = (r0 as i64, c0 as i64);
    let period = config.columns_per_turn().round() as i64;
    let wraps = config.wraps_azimuth();
    let at = |r: i64, c: i64| -> f32 {
        let c = if wraps { c.rem_euclid(period) } else { c };
        if r < 0 || r >= height || c < 0 || c >= width {
            0.0
        } else {
            range[(r * width + c) as usize]
        }
    };
    let corners = [
        (at(r0, c0), (1.0 - fr) * (1.0 - fc), fr * fr + fc * fc),
        (
            at(r0, c0 + 1),
            (1.0 - fr) * fc,
            fr * fr + (1.0 - fc) * (1.0 - fc),
        ),
        (
            at(r0 + 1, c0),
            fr * (1.0 - fc),
            (1.0 - fr) * (1.0 - fr) + fc * fc,
        ),
        (
            at(r0 + 1, c0 + 1),
            fr * fc,
            (1.0 - fr) * (1.0 - fr) + (1.0 - fc) * (1.0 - fc),
        ),
    ];
    let all_valid = corners.iter().all(|c| c.0 > 0.0);
    if all_valid {
        let lo = corners.iter().map(|c| c.0).fold(f32::INFINITY, f32::min);
        let hi = corners.iter().map(|c| c.0).fold(0.0, f32::max);
        if hi - lo <= max_relative_spread * lo {
            return Some(corners.iter().map(|c| c.0 as f64 * c.1).sum());
        }
    }
    // Nearest valid corner (ties: the first in row-major order).
    corners
        .iter()
        .filter(|c| c.0 > 0.0)
        .min_by(|a, b| a.2.total_cmp(&b.2))
        .map(|c| c.0 as f64)
}

/// Decodes per-cell network output into 3D matches. Images are row-major `config.height × width`:
/// `flow` is `2 × H × W` (Δrow then Δcol, pixels), `confidence` `H × W`, `exclude` (optional) `H × W`
/// with true for cells to leave out (e.g. moving objects). Parallel over rows in the caller's pool;
/// the output order (row-major) does not depend on the thread count.
pub fn decode_matches(
    ref_range: &[f32],
    tgt_range: &[f32],
    flow: &[f32],
    confidence: &[f32],
    exclude: Option<&[bool]>,
    config: &CylinderConfig,
    decode: &DecodeConfig,
) -> Result<DecodedMatches> {
    let decoder = Decoder::new(
        ref_range, tgt_range, flow, confidence, exclude, config, decode,
    )?;
    let (height, width) = (config.height, config.width);
    let per_row: Vec<DecodedMatches> = (0..height)
        .into_par_iter()
        .map(|row| {
            let mut out = DecodedMatches::with_capacity(width);
            for col in 0..width {
                if decoder.is_candidate(row * width + col) {
                    decoder.decode_into(row, col, &mut out);
                }
            }
            out
        })
        .collect();
    let mut all = DecodedMatches::with_capacity(per_row.iter().map(DecodedMatches::len).sum());
    for part in per_row {
        all.source.extend(part.source);
        all.target.extend(part.target);
        all.confidence.extend(part.confidence);
        all.cells.extend(part.cells);
    }
    Ok(all)
}

/// [`decode_matches`] followed by [`crate::nms::nms_wrapping`] with `radius`, `top_n` and the
/// config's [`column_period`](CylinderConfig::column_period) (a 360° image suppresses across the
/// azimuth seam, a cropped one does not), fused: candidate cells are visited in NMS order (confidence
/// descending, then cell index) and only those that survive suppression are decoded; a cell that
/// cannot be decoded is skipped without suppressing its neighbours. The result is exactly that of
/// decoding everything and then running NMS on the decoded matches, best first, at a cost that grows
/// with `top_n` instead of the image size.
#[allow(clippy::too_many_arguments)]
pub fn select_matches(
    ref_range: &[f32],
    tgt_range: &[f32],
    flow: &[f32],
    confidence: &[f32],
    exclude: Option<&[bool]>,
    config: &CylinderConfig,
    decode: &DecodeConfig,
    radius: usize,
    top_n: usize,
) -> Result<DecodedMatches> {
    let decoder = Decoder::new(
        ref_range, tgt_range, flow, confidence, exclude, config, decode,
    )?;
    let (height, width) = (config.height, config.width);
    let mut candidates: Vec<u32> = (0..(height * width) as u32)
        .filter(|&cell| decoder.is_candidate(cell as usize))
        .collect();
    let better = |a: &u32, b: &u32| {
        confidence[*b as usize]
            .total_cmp(&confidence[*a as usize])
            .then(a.cmp(b))
    };
    let mut out = DecodedMatches::with_capacity(top_n.min(candidates.len()));
    let mut suppressed = match config.column_period() {
        Some(period) => SuppressionGrid::new(height, period, true),
        None => SuppressionGrid::new(height, width, false),
    };
    // Sort only as many candidates as are likely needed (each kept match suppresses at most
    // (2r+1)² − 1 others; undecodable ones need more), then the rest if they run out.
    let mut sorted = 0;
    let mut batch = top_n
        .saturating_mul((2 * radius + 1).pow(2))
        .saturating_mul(2)
        .max(64);
    let mut next = 0;
    while out.len() < top_n && next < candidates.len() {
        if next == sorted {
            let end = sorted.saturating_add(batch).min(candidates.len());
            if end < candidates.len() {
                candidates[sorted..].select_nth_unstable_by(end - sorted, better);
            }
            candidates[sorted..end].sort_unstable_by(better);
            sorted = end;
            batch = batch.saturating_mul(2);
        }
        let cell = candidates[next] as usize;
        next += 1;
        let (row, col) = (cell / width, cell % width);
        if suppressed.is_suppressed(row, col) {
            continue;
        }
        if !decoder.decode_into(row, col, &mut out) {
            continue;
        }
        suppressed.suppress_around(row, col, radius);
    }
    Ok(out)
}

/// Checked inputs of a decode and the per-cell work shared by [`decode_matches`] and
/// [`select_matches`].
struct Decoder<'a> {
    ref_range: &'a [f32],
    tgt_range: &'a [f32],
    d_rows: &'a [f32],
    d_cols: &'a [f32],
    confidence: &'a [f32],
    exclude: Option<&'a [bool]>,
    config: &'a CylinderConfig,
    decode: &'a DecodeConfig,
    directions: DirectionTable,
}

impl<'a> Decoder<'a> {
    fn new(
        ref_range: &'a [f32],
        tgt_range: &'a [f32],
        flow: &'a [f32],
        confidence: &'a [f32],
        exclude: Option<&'a [bool]>,
        config: &'a CylinderConfig,
        decode: &'a DecodeConfig,
    ) -> Result<Self> {
        config.validate()?;
        check_range_image("ref_range", ref_range, config)?;
        check_range_image("tgt_range", tgt_range, config)?;
        let (height, width) = (config.height, config.width);
        let cells = height * width;
        if flow.len() != 2 * cells {
            return Err(Error::invalid(
                "flow",
                format!("has {} values, need 2 x {height} x {width}", flow.len()),
            ));
        }
        if confidence.len() != cells {
            return Err(Error::invalid(
                "confidence",
                format!("has {} values, need {height} x {width}", confidence.len()),
            ));
        }
        if let Some(mask) = exclude {
            if mask.len() != cells {
                return Err(Error::invalid(
                    "mask",
                    format!("has {} values, need {height} x {width}", mask.len()),
                ));
            }
        }
        if decode.min_confidence.is_nan() {
            return Err(Error::invalid("min_confidence", "is NaN"));
        }
        if !(decode.max_relative_range_spread.is_finite()
            && decode.max_relative_range_spread >= 0.0)
        {
            return Err(Error::invalid(
                "max_relative_range_spread",
                "must be finite and >= 0",
            ));
        }
        let (d_rows, d_cols) = flow.split_at(cells);
        Ok(Decoder {
            ref_range,
            tgt_range,
            d_rows,
            d_cols,
            confidence,
            exclude,
            config,
            decode,
            directions: DirectionTable::new(config),
        })
    }

    /// A cell with a range, enough confidence (NaN fails), no exclusion mark and a finite flow.
    #[inline]
    fn is_candidate(&self, cell: usize) -> bool {
        let confident = self.confidence[cell] >= self.decode.min_confidence;
        self.ref_range[cell] > 0.0
            && confident
            && !self.exclude.is_some_and(|m| m[cell])
            && self.d_rows[cell].is_finite()
            && self.d_cols[cell].is_finite()
    }

    /// Decodes a candidate cell and appends the match; false when the target range is unavailable.
    #[inline]
    fn decode_into(&self, row: usize, col: usize, out: &mut DecodedMatches) -> bool {
        let cell = row * self.config.width + col;
        let row_t = row as f64 + self.d_rows[cell] as f64;
        let mut col_t = col as f64 + self.d_cols[cell] as f64;
        if self.config.wraps_azimuth() {
            let period = self.config.columns_per_turn();
            col_t = (col_t + 0.5).rem_euclid(period) - 0.5;
        }
        let Some(range_t) = sample_range(
            self.tgt_range,
            row_t,
            col_t,
            self.config,
            self.decode.max_relative_range_spread,
        ) else {
            return false;
        };
        let range = self.ref_range[cell] as f64;
        out.source.push(Point3::from(
            self.directions.at(row as f64, col as f64) * range,
        ));
        out.target
            .push(Point3::from(self.directions.at(row_t, col_t) * range_t));
        out.confidence.push(self.confidence[cell]);
        out.cells.push([row, col]);
        true
    }
}

/// Unit directions of Φ⁻¹ without trigonometric calls per point: sines and cosines tabulated at the
/// integer rows and columns of the image (one cell of margin), corrected to the sub-pixel location by
/// the angle-addition formulas with a short series for the remainder (|δ| ≤ half a cell; series error
/// < 1e-16). Locations off the table fall back to `sin_cos`.
struct DirectionTable {
    row0: f64,
    col0: f64,
    d_phi: f64,
    d_theta: f64,
    /// `(sin, cos)` of the elevation of rows −1 ..= height.
    rows: Vec<(f64, f64)>,
    /// `(sin, cos)` of the azimuth of columns −1 ..= width.
    cols: Vec<(f64, f64)>,
}

impl DirectionTable {
    fn new(config: &CylinderConfig) -> Self {
        let row0 = config.row_of_zero_elevation();
        let col0 = config.col_of_zero_azimuth();
        let d_phi = config.vertical_resolution_deg.to_radians();
        let d_theta = config.horizontal_resolution_deg.to_radians();
        DirectionTable {
            row0,
            col0,
            d_phi,
            d_theta,
            rows: (-1..=config.height as i64)
                .map(|r| ((row0 - r as f64) * d_phi).sin_cos())
                .collect(),
            cols: (-1..=config.width as i64)
                .map(|c| ((col0 - c as f64) * d_theta).sin_cos())
                .collect(),
        }
    }

    /// sin and cos of `base + fraction·step` from the exact `(sin, cos)` of `base`.
    #[inline(always)]
    fn rotate(base: (f64, f64), fraction: f64, step: f64) -> (f64, f64) {
        let (sin_base, cos_base) = base;
        let delta = fraction * step;
        let d2 = delta * delta;
        let sin_delta = delta * (1.0 - d2 / 6.0 * (1.0 - d2 / 20.0 * (1.0 - d2 / 42.0)));
        let cos_delta = 1.0 - d2 / 2.0 * (1.0 - d2 / 12.0 * (1.0 - d2 / 30.0));
        (
            sin_base * cos_delta + cos_base * sin_delta,
            cos_base * cos_delta - sin_base * sin_delta,
        )
    }

    /// `(sin, cos)` of the angle at continuous index `x` (angle = (origin − x)·step).
    #[inline(always)]
    fn lookup(table: &[(f64, f64)], origin: f64, x: f64, step: f64) -> (f64, f64) {
        let nearest = floor_fast(x + 0.5);
        let slot = nearest + 1.0;
        let base = if slot >= 0.0 && (slot as usize) < table.len() {
            table[slot as usize]
        } else {
            ((origin - nearest) * step).sin_cos()
        };
        // The angle falls as the index grows: angle = base_angle − (x − nearest)·step.
        Self::rotate(base, nearest - x, step)
    }

    fn at(&self, row: f64, col: f64) -> Vector3<f64> {
        let (sin_el, cos_el) = Self::lookup(&self.rows, self.row0, row, self.d_phi);
        let (sin_az, cos_az) = Self::lookup(&self.cols, self.col0, col, self.d_theta);
        Vector3::new(cos_el * cos_az, cos_el * sin_az, sin_el)
    }
}

#[cfg(test)]
mod tests;
