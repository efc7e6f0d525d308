#![forbid(unsafe_code)]
//! Flow coherence: confidence lowered where a match disagrees with its neighbours (beyond the paper).
//!
//! The network's confidence Q* ranks the matches poorly: of the 1000 kept after NMS only about a fifth
//! lie within a pixel of the truth. The scene, though, moves rigidly, so over a few cells the true flow
//! changes smoothly, while a wrong match usually jumps away from its neighbours. Each cell's confidence
//! is multiplied by `exp(−d / scale_px)`, `d` the distance (pixels) of its flow from the median flow of
//! the `(2r+1)²` cells around it. The median is separable, as in image processing's fast median filters:
//! per component, first the median down each column of the window (over the cells with a range and a
//! finite flow), then the median of those column medians across the window. An exact 25-cell median
//! costs 43 ms a frame at 64×1792 on one core; this ~6 ms, with the same pair errors.

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::ground_truth::{check_non_negative_image, check_range_image};
use crate::projection::CylinderConfig;

/// Settings of [`coherent_confidence`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CoherenceConfig {
    /// Neighbourhood radius r in cells: the median runs over a `(2r+1) × (2r+1)` window.
    pub radius: usize,
    /// Flow distance (pixels) from the neighbourhood median that divides the confidence by e.
    pub scale_px: f32,
}

impl Default for CoherenceConfig {
    fn default() -> Self {
        CoherenceConfig {
            radius: 2,
            scale_px: 0.5,
        }
    }
}

/// Largest radius [`coherent_confidence`] accepts: a window's column fits a small stack buffer.
pub const MAX_RADIUS: usize = 15;

fn median_of_3(a: f32, b: f32, c: f32) -> f32 {
    a.min(b).max(a.max(b).min(c))
}

/// Median of a non-empty slice (the mean of the two middle values for an even length), reordering it.
/// Up to 5 values (the default radius's windows, full or partial at empty cells) take branch-free
/// min/max networks, which are most of the cost of the whole weighting; longer ones sort.
fn median(values: &mut [f32]) -> f32 {
    match *values {
        [a] => a,
        [a, b] => 0.5 * (a.min(b) + a.max(b)),
        [a, b, c] => median_of_3(a, b, c),
        // The two middle values of four: the larger of the pairs' minima and the smaller of their maxima.
        [a, b, c, d] => 0.5 * (a.min(b).max(c.min(d)) + a.max(b).min(c.max(d))),
        [a, b, c, d, e] => median_of_3(a.min(b).max(c.min(d)), a.max(b).min(c.max(d)), e),
        _ => {
            values.sort_unstable_by(f32::total_cmp);
            let middle = values.len() / 2;
            if values.len() % 2 == 1 {
                values[middle]
            } else {
                0.5 * (values[middle - 1] + values[middle])
            }
        }
    }
}

/// The confidence of every cell weighted by the coherence of its flow with its neighbours' (module
/// docs). Images are row-major `config.height × width`: `flow` `2 × H × W` (Δrow then Δcol, pixels),
/// `confidence` and `reference` (the reference range image; 0 = empty) `H × W`. Rows do not wrap;
/// columns wrap round the azimuth seam when the image covers 360°. Cells without a range, and cells
/// whose flow is not finite, get 0. Parallel over rows in the caller's pool.
pub fn coherent_confidence(
    flow: &[f32],
    confidence: &[f32],
    reference: &[f32],
    config: &CylinderConfig,
    coherence: &CoherenceConfig,
) -> Result<Vec<f32>> {
    config.validate()?;
    check_range_image("reference", reference, config)?;
    check_non_negative_image(
        "confidence",
        confidence,
        config,
        "confidences must be finite and >= 0",
    )?;
    let cells = config.height * config.width;
    if flow.len() != 2 * cells {
        return Err(Error::invalid(
            "flow",
            format!("has {} values, expected 2 x {cells}", flow.len()),
        ));
    }
    if !(coherence.scale_px.is_finite() && coherence.scale_px > 0.0) {
        return Err(Error::invalid(
            "scale_px",
            format!("must be finite and > 0, got {}", coherence.scale_px),
        ));
    }
    if coherence.radius > MAX_RADIUS {
        return Err(Error::invalid(
            "radius",
            format!("must be at most {MAX_RADIUS}, got {}", coherence.radius),
        ));
    }
    let (height, width, radius) = (config.height, config.width, coherence.radius);
    let (flow_rows, flow_cols) = flow.split_at(cells);
    let usable = |cell: usize| {
        reference[cell] > 0.0 && flow_rows[cell].is_finite() && flow_cols[cell].is_finite()
    };

    // Pass 1: the median of each component down the column segment rows r−radius … r+radius; NaN where
    // the segment holds no usable cell.
    let mut column_medians = vec![[f32::NAN; 2]; cells];
    column_medians
        .par_chunks_mut(width)
        .enumerate()
        .for_each(|(row, out_row)| {
            let (first, last) = (row.saturating_sub(radius), (row + radius).min(height - 1));
            let mut buffer = [[0.0f32; 2 * MAX_RADIUS + 1]; 2];
            for (col, out_cell) in out_row.iter_mut().enumerate() {
                let mut count = 0;
                for r in first..=last {
                    let cell = r * width + col;
                    if usable(cell) {
                        buffer[0][count] = flow_rows[cell];
                        buffer[1][count] = flow_cols[cell];
                        count += 1;
                    }
                }
                if count > 0 {
                    let [rows, cols] = &mut buffer;
                    *out_cell = [median(&mut rows[..count]), median(&mut cols[..count])];
                }
            }
        });

    // Pass 2: the median of the column medians across columns c−radius … c+radius (wrapping on a full
    // circle), and the weight of the cell's own flow against it.
    let period = config.column_period();
    let mut out = vec![0.0f32; cells];
    out.par_chunks_mut(width)
        .enumerate()
        .for_each(|(row, out_row)| {
            let mut buffer = [[0.0f32; 2 * MAX_RADIUS + 1]; 2];
            let row_medians = &column_medians[row * width..][..width];
            for (col, out_cell) in out_row.iter_mut().enumerate() {
                let cell = row * width + col;
                if !usable(cell) {
                    continue;
                }
                let mut count = 0;
                let mut gather = |c: usize| {
                    let [median_row, median_col] = row_medians[c];
                    if !median_row.is_nan() {
                        buffer[0][count] = median_row;
                        buffer[1][count] = median_col;
                        count += 1;
                    }
                };
                if col >= radius && col + radius < width {
                    // Away from the image's sides no column wraps or falls off: no modulo per neighbour.
                    (col - radius..=col + radius).for_each(&mut gather);
                } else {
                    for c in col as i64 - radius as i64..=col as i64 + radius as i64 {
                        match period {
                            Some(period) => gather(c.rem_euclid(period as i64) as usize),
                            None if c < 0 || c >= width as i64 => {}
                            None => gather(c as usize),
                        }
                    }
                }
                // The cell's own column always holds a usable cell (itself), so count ≥ 1.
                let [rows, cols] = &mut buffer;
                let centre = (median(&mut rows[..count]), median(&mut cols[..count]));
                // Pixel distances: `hypot`'s overflow guard buys nothing here and costs a libm call.
                let (d_row, d_col) = (flow_rows[cell] - centre.0, flow_cols[cell] - centre.1);
                let distance = (d_row * d_row + d_col * d_col).sqrt();
                *out_cell = confidence[cell] * (-distance / coherence.scale_px).exp();
            }
        });
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(height: usize, width: usize, full_circle: bool) -> CylinderConfig {
        let mut config = CylinderConfig {
            height,
            width,
            ..CylinderConfig::kitti()
        };
        if full_circle {
            config.horizontal_resolution_deg = 360.0 / width as f64;
        }
        config
    }

    #[test]
    fn the_median_networks_agree_with_sorting() {
        // Every ordering of a few values with ties, for each length a network handles, and a longer one.
        let mut state = 7u64;
        let mut next = || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
            ((state >> 33) % 7) as f32 - 3.0
        };
        for length in 1..=7 {
            for _ in 0..500 {
                let mut values: Vec<f32> = (0..length).map(|_| next()).collect();
                let mut sorted = values.clone();
                sorted.sort_by(f32::total_cmp);
                let middle = length / 2;
                let expected = if length % 2 == 1 {
                    sorted[middle]
                } else {
                    0.5 * (sorted[middle - 1] + sorted[middle])
                };
                assert_eq!(median(&mut values), expected, "{sorted:?}");
            }
        }
    }

    #[test]
    fn a_uniform_flow_keeps_the_confidence_and_an_outlier_loses_it() {
        let config = grid(5, 8, false);
        let cells = 40;
        let mut flow = vec![1.5f32; cells];
        flow.extend(vec![-3.0f32; cells]);
        flow[2 * 8 + 3] += 2.0; // the row flow of cell (2, 3) jumps by 2 px
        let confidence = vec![0.8f32; cells];
        let reference = vec![10.0f32; cells];
        let out = coherent_confidence(
            &flow,
            &confidence,
            &reference,
            &config,
            &CoherenceConfig::default(),
        )
        .unwrap();
        assert!((out[0] - 0.8).abs() < 1e-6 && (out[39] - 0.8).abs() < 1e-6);
        assert!((out[2 * 8 + 3] - 0.8 * (-4.0f32).exp()).abs() < 1e-6);
    }

    #[test]
    fn columns_wrap_only_on_a_full_circle_and_empty_cells_get_zero() {
        let cells = 3 * 8;
        let mut flow = vec![0.0f32; 2 * cells];
        for row in 0..3 {
            flow[row * 8] = 1.0; // columns 0 and 7, neighbours across the seam, flow alike
            flow[row * 8 + 7] = 1.0;
        }
        let mut reference = vec![5.0f32; cells];
        reference[8 + 4] = 0.0;
        let coherence = CoherenceConfig {
            radius: 1,
            scale_px: 1.0,
        };
        let confidence = vec![1.0f32; cells];
        let cropped = grid(3, 8, false);
        let wrapped = grid(3, 8, true);
        let a = coherent_confidence(&flow, &confidence, &reference, &cropped, &coherence).unwrap();
        let b = coherent_confidence(&flow, &confidence, &reference, &wrapped, &coherence).unwrap();
        assert_eq!(a[8 + 4], 0.0);
        // Cell (1, 0) cropped: columns 0–1, row flows 1,1,1,0,0,0 → median 0.5; wrapped: column 7 joins
        // (six ones, three zeros) → median 1, its own flow.
        assert!((a[8] - (-0.5f32).exp()).abs() < 1e-6);
        assert!((b[8] - 1.0).abs() < 1e-6);
        // The top row has no row above: cell (0, 0) cropped sees rows 0–1 only (1,1,0,0 → 0.5).
        assert!((a[0] - (-0.5f32).exp()).abs() < 1e-6);
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0]), 2.5);
        // The min/max networks against sorting, on every sequence of values 0…n−1 (all orders, all ties).
        for n in [3u32, 5] {
            for code in 0..n.pow(n) {
                let mut values: Vec<f32> = (0..n).map(|i| ((code / n.pow(i)) % n) as f32).collect();
                let mut sorted = values.clone();
                sorted.sort_by(f32::total_cmp);
                assert_eq!(median(&mut values), sorted[n as usize / 2], "{sorted:?}");
            }
        }
    }

    #[test]
    fn bad_sizes_and_scales_are_named() {
        let config = grid(2, 8, false);
        let ok = vec![1.0f32; 16];
        let flow = vec![0.0f32; 32];
        let default = CoherenceConfig::default();
        let message = |e: Error| e.to_string();
        let short = coherent_confidence(&flow[..30], &ok, &ok, &config, &default).unwrap_err();
        assert!(message(short).contains("flow"));
        let bad_conf = coherent_confidence(&flow, &ok[..15], &ok, &config, &default).unwrap_err();
        assert!(message(bad_conf).contains("confidence"));
        let zero = CoherenceConfig {
            radius: 1,
            scale_px: 0.0,
        };
        let bad_scale = coherent_confidence(&flow, &ok, &ok, &config, &zero).unwrap_err();
        assert!(message(bad_scale).contains("scale_px"));
        let wide = CoherenceConfig {
            radius: MAX_RADIUS + 1,
            scale_px: 1.0,
        };
        let too_wide = coherent_confidence(&flow, &ok, &ok, &config, &wide).unwrap_err();
        assert!(message(too_wide).contains("radius"));
    }
}
