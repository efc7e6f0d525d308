#![forbid(unsafe_code)]
//! From a cell's D×D similarities to a sub-pixel offset and a confidence: the softmax of Eq. 3 and the
//! best 2×2 window of Eq. 11 (`dmlo.model.window` in the Python package, whose semantics this follows
//! exactly: the first maximum wins ties, and the softmax is only ever used through ratios).
//!
//! A window's rows may be padded to a whole number of SIMD lanes: row `r` of a window stored with
//! `row_stride` holds its cells at `r · row_stride + 0 … window − 1`, and the padding must be −∞ (it then
//! weighs 0 in the softmax and never wins a maximum).

use wide::{f32x8, CmpGt};

/// Where a cell's match lies in its window and how sure the network is of it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WindowMatch {
    /// Sub-pixel (Δrow, Δcol) from the window centre, in window cells.
    pub offset: [f32; 2],
    /// Q*: the softmax mass of the best 2×2 window.
    pub confidence: f32,
}

/// How the window's distribution becomes a sub-pixel offset (`MatcherConfig.refine_offset`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OffsetRule {
    /// The paper's Eq. 11: the centroid of the best 2×2 window.
    BestWindow,
    /// Beyond the paper: the centroid of the 3×3 cells around the most likely cell (moved inside the
    /// window when that cell is on its edge).
    PeakCentroid,
}

impl OffsetRule {
    /// The rule a model's `refine_offset` names: "window" (Eq. 11) or "peak_centroid"; None for any other.
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "window" => Some(OffsetRule::BestWindow),
            "peak_centroid" => Some(OffsetRule::PeakCentroid),
            _ => None,
        }
    }
}

/// Shape of a window's logits in memory: `size × size` cells, rows `row_stride` ≥ `size` apart.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WindowLayout {
    /// Cells per side (≥ 3).
    pub size: usize,
    /// Distance between the starts of consecutive rows.
    pub row_stride: usize,
}

impl WindowLayout {
    /// Rows stored without padding.
    pub fn dense(size: usize) -> Self {
        WindowLayout {
            size,
            row_stride: size,
        }
    }

    /// Values a window occupies.
    pub fn len(&self) -> usize {
        self.size * self.row_stride
    }

    /// True for a window of no cells.
    pub fn is_empty(&self) -> bool {
        self.size == 0
    }
}

/// Decodes one cell's window of logits laid out as `layout`; `weights` is scratch of the same length.
pub fn decode(
    logits: &[f32],
    weights: &mut [f32],
    layout: WindowLayout,
    rule: OffsetRule,
) -> WindowMatch {
    debug_assert!(layout.size >= 3 && layout.row_stride >= layout.size);
    debug_assert!(logits.len() == layout.len() && weights.len() == logits.len());
    let total = softmax_weights(logits, weights);
    let (best_row, best_col, best_sum) = best_window(weights, layout);
    let radius = (layout.size / 2) as f32;
    let offset = match rule {
        OffsetRule::BestWindow => {
            let at = |row: usize, col: usize| weights[row * layout.row_stride + col];
            let (r, c) = (best_row, best_col);
            [
                r as f32 + (at(r + 1, c) + at(r + 1, c + 1)) / best_sum - radius,
                c as f32 + (at(r, c + 1) + at(r + 1, c + 1)) / best_sum - radius,
            ]
        }
        OffsetRule::PeakCentroid => peak_centroid(logits, weights, layout),
    };
    WindowMatch {
        offset,
        confidence: best_sum / total,
    }
}

/// Eight cells' [`WindowMatch`]es at once, lane by lane.
#[derive(Debug, Clone, Copy)]
pub(super) struct GroupMatch {
    /// Δrow, then Δcol, of each lane's match from its window centre, in window cells.
    pub offset: [f32x8; 2],
    /// Q* of each lane.
    pub confidence: f32x8,
}

/// [`decode`] with [`OffsetRule::BestWindow`] of eight `size × size` windows at once, lane `k` of
/// `logits[r · size + c]` being window `k`'s cell `(r, c)`; `weights` is scratch of the same length.
/// The same operations in the same order per lane, so the offsets are [`decode`]'s exactly (the
/// softmax total, summed in another order, may differ in the last bits). Branch-free: the best
/// window's choice is a lane mask.
pub(super) fn decode_group(logits: &[f32x8], weights: &mut [f32x8], size: usize) -> GroupMatch {
    debug_assert!(size >= 3 && logits.len() == size * size && weights.len() == logits.len());
    let max = logits
        .iter()
        .fold(f32x8::splat(f32::NEG_INFINITY), |max, &logit| {
            max.max(logit)
        });
    let mut total = f32x8::ZERO;
    for (weight, &logit) in weights.iter_mut().zip(logits) {
        *weight = (logit - max).exp();
        total += *weight;
    }
    let mut best_sum = f32x8::splat(f32::NEG_INFINITY);
    let (mut best_row, mut best_col) = (f32x8::ZERO, f32x8::ZERO);
    // The best window's mass in its lower row and in its right column: Eq. 11's numerators.
    let (mut lower_mass, mut right_mass) = (f32x8::ZERO, f32x8::ZERO);
    for row in 0..size - 1 {
        let (top, bottom) = (
            &weights[row * size..][..size],
            &weights[(row + 1) * size..][..size],
        );
        let mut left_pair = top[0] + bottom[0];
        for col in 0..size - 1 {
            let right_pair = top[col + 1] + bottom[col + 1];
            let sum = left_pair + right_pair;
            // Strictly greater: the first maximum in row-major order wins, as in `best_window`.
            let better = sum.cmp_gt(best_sum);
            best_sum = better.blend(sum, best_sum);
            best_row = better.blend(f32x8::splat(row as f32), best_row);
            best_col = better.blend(f32x8::splat(col as f32), best_col);
            lower_mass = better.blend(bottom[col] + bottom[col + 1], lower_mass);
            right_mass = better.blend(right_pair, right_mass);
            left_pair = right_pair;
        }
    }
    let radius = f32x8::splat((size / 2) as f32);
    GroupMatch {
        offset: [
            best_row + lower_mass / best_sum - radius,
            best_col + right_mass / best_sum - radius,
        ],
        // A mass, ≤ 1: summed in another order than the window's four, the total can fall an ulp short.
        confidence: (best_sum / total).min(f32x8::ONE),
    }
}

/// `weights = exp(logits − max)` (so the largest is 1) and their sum. Eight lanes at a time: the
/// exponentials are most of a window's cost, and libm's scalar `expf` is ~4× slower than `f32x8::exp`.
fn softmax_weights(logits: &[f32], weights: &mut [f32]) -> f32 {
    let chunk = |logit: &[f32]| f32x8::from(<[f32; 8]>::try_from(logit).unwrap_or_default());
    let logit_chunks = logits.chunks_exact(8);
    let rest = logit_chunks.remainder();
    // The maximum in lanes too: a scalar fold is a chain of dependent comparisons as long as the window.
    let lane_max = logit_chunks
        .clone()
        .fold(f32x8::splat(f32::NEG_INFINITY), |max, logit| {
            max.max(chunk(logit))
        });
    let max = rest.iter().copied().fold(
        lane_max
            .to_array()
            .into_iter()
            .fold(f32::NEG_INFINITY, f32::max),
        f32::max,
    );
    let shift = f32x8::splat(max);
    let mut lanes = f32x8::ZERO;
    for (logit, weight) in logit_chunks.zip(weights.chunks_exact_mut(8)) {
        let values = (chunk(logit) - shift).exp();
        weight.copy_from_slice(&values.to_array());
        lanes += values;
    }
    let mut total = lanes.reduce_add();
    let start = logits.len() - rest.len();
    for (weight, &logit) in weights[start..].iter_mut().zip(rest) {
        *weight = (logit - max).exp();
        total += *weight;
    }
    total
}

/// Top-left cell and mass of the 2×2 window of largest mass (the first in row-major order on ties).
fn best_window(weights: &[f32], layout: WindowLayout) -> (usize, usize, f32) {
    let (window, stride) = (layout.size, layout.row_stride);
    let (mut best_row, mut best_col, mut best_sum) = (0, 0, f32::NEG_INFINITY);
    for row in 0..window - 1 {
        let (top, bottom) = (
            &weights[row * stride..row * stride + window],
            &weights[(row + 1) * stride..(row + 1) * stride + window],
        );
        let mut left_pair = top[0] + bottom[0];
        for col in 0..window - 1 {
            let right_pair = top[col + 1] + bottom[col + 1];
            let sum = left_pair + right_pair;
            if sum > best_sum {
                (best_row, best_col, best_sum) = (row, col, sum);
            }
            left_pair = right_pair;
        }
    }
    (best_row, best_col, best_sum)
}

/// The softmax-weighted centroid of the 3×3 cells around the largest logit (the first on ties), that
/// block moved inside the window, in window cells from the centre.
fn peak_centroid(logits: &[f32], weights: &[f32], layout: WindowLayout) -> [f32; 2] {
    let (window, stride) = (layout.size, layout.row_stride);
    let mut best = 0;
    for (index, &logit) in logits.iter().enumerate() {
        if logit > logits[best] {
            best = index;
        }
    }
    let row_centre = (best / stride).clamp(1, window - 2);
    let col_centre = (best % stride).clamp(1, window - 2);
    let (mut mass, mut row_moment, mut col_moment) = (0.0f32, 0.0f32, 0.0f32);
    for row in row_centre - 1..=row_centre + 1 {
        for col in col_centre - 1..=col_centre + 1 {
            let weight = weights[row * stride + col];
            mass += weight;
            row_moment += weight * row as f32;
            col_moment += weight * col as f32;
        }
    }
    let radius = (window / 2) as f32;
    [row_moment / mass - radius, col_moment / mass - radius]
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    fn softmax(logits: &[f32]) -> Vec<f64> {
        let max = logits.iter().copied().fold(f32::NEG_INFINITY, f32::max) as f64;
        let e: Vec<f64> = logits.iter().map(|&l| (l as f64 - max).exp()).collect();
        let total: f64 = e.iter().sum();
        e.into_iter().map(|v| v / total).collect()
    }

    #[test]
    fn a_peak_between_four_cells_is_found_at_their_corner() {
        // Equal mass on the cells (1, 2), (1, 3), (2, 2), (2, 3) of a 5×5 window, none elsewhere.
        let window = 5;
        let mut logits = vec![-50.0f32; 25];
        for (r, c) in [(1, 2), (1, 3), (2, 2), (2, 3)] {
            logits[r * window + c] = 3.0;
        }
        let mut scratch = vec![0.0; 25];
        let found = decode(
            &logits,
            &mut scratch,
            WindowLayout::dense(window),
            OffsetRule::BestWindow,
        );
        assert_relative_eq!(found.offset[0], -0.5, epsilon = 1e-5);
        assert_relative_eq!(found.offset[1], 0.5, epsilon = 1e-5);
        assert_relative_eq!(found.confidence, 1.0, epsilon = 1e-5);
    }

    #[test]
    fn offsets_and_confidence_follow_the_softmax() {
        let window = 7;
        let logits: Vec<f32> = (0..49)
            .map(|i| ((i * 37 % 11) as f32 - 5.0) * 0.7)
            .collect();
        let p = softmax(&logits);
        // The reference: every 2×2 window's mass in f64, the best one's centroid.
        let (mut best, mut best_sum) = ((0, 0), -1.0);
        for r in 0..6 {
            for c in 0..6 {
                let s =
                    p[r * 7 + c] + p[r * 7 + c + 1] + p[(r + 1) * 7 + c] + p[(r + 1) * 7 + c + 1];
                if s > best_sum {
                    (best, best_sum) = ((r, c), s);
                }
            }
        }
        let (r, c) = best;
        let row = r as f64 + (p[(r + 1) * 7 + c] + p[(r + 1) * 7 + c + 1]) / best_sum - 3.0;
        let col = c as f64 + (p[r * 7 + c + 1] + p[(r + 1) * 7 + c + 1]) / best_sum - 3.0;
        let mut scratch = vec![0.0; 49];
        let found = decode(
            &logits,
            &mut scratch,
            WindowLayout::dense(window),
            OffsetRule::BestWindow,
        );
        assert_relative_eq!(found.offset[0] as f64, row, epsilon = 1e-5);
        assert_relative_eq!(found.offset[1] as f64, col, epsilon = 1e-5);
        assert_relative_eq!(found.confidence as f64, best_sum, epsilon = 1e-5);
    }

    #[test]
    fn a_padded_window_decodes_like_its_dense_copy() {
        // 7 cells per row stored 8 apart, as the correlation lays them out; the padding lanes hold −∞.
        let window = 7;
        let dense: Vec<f32> = (0..49)
            .map(|i| ((i * 29 % 13) as f32 - 6.0) * 0.9)
            .collect();
        let layout = WindowLayout {
            size: window,
            row_stride: 8,
        };
        let mut padded = vec![f32::NEG_INFINITY; layout.len()];
        for row in 0..window {
            padded[row * 8..row * 8 + window]
                .copy_from_slice(&dense[row * window..(row + 1) * window]);
        }
        for rule in [OffsetRule::BestWindow, OffsetRule::PeakCentroid] {
            let want = decode(&dense, &mut [0.0; 49], WindowLayout::dense(window), rule);
            let got = decode(&padded, &mut vec![0.0; layout.len()], layout, rule);
            assert_relative_eq!(got.offset[0], want.offset[0], epsilon = 1e-6);
            assert_relative_eq!(got.offset[1], want.offset[1], epsilon = 1e-6);
            assert_relative_eq!(got.confidence, want.confidence, epsilon = 1e-6);
            assert!(want.confidence > 0.05 && want.confidence < 0.95); // a spread, not a one-hot window
        }
    }

    #[test]
    fn ties_go_to_the_first_window_in_row_major_order() {
        let window = 3;
        let logits = vec![0.0f32; 9]; // all four 2×2 windows tie
        let mut scratch = vec![0.0; 9];
        let found = decode(
            &logits,
            &mut scratch,
            WindowLayout::dense(window),
            OffsetRule::BestWindow,
        );
        assert_relative_eq!(found.offset[0], -0.5, epsilon = 1e-6);
        assert_relative_eq!(found.offset[1], -0.5, epsilon = 1e-6);
        assert_relative_eq!(found.confidence, 4.0 / 9.0, epsilon = 1e-6);
    }

    #[test]
    fn the_peak_centroid_stays_inside_the_window_at_its_edge() {
        let window = 5;
        let mut logits = vec![-50.0f32; 25];
        logits[0] = 2.0; // the corner cell: the 3×3 block moves to rows/cols 0..=2
        logits[1] = 2.0;
        let mut scratch = vec![0.0; 25];
        let found = decode(
            &logits,
            &mut scratch,
            WindowLayout::dense(window),
            OffsetRule::PeakCentroid,
        );
        assert_relative_eq!(found.offset[0], -2.0, epsilon = 1e-5);
        assert_relative_eq!(found.offset[1], -1.5, epsilon = 1e-5);
    }
}
