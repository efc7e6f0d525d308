#![forbid(unsafe_code)]
//! Non-maximum suppression on the cylinder grid (paper §III-D-a): repeatedly keep the most confident
//! match and suppress every other match within `radius` cells of it, then keep the top `N`.
//!
//! The neighbourhood is the square window `|Δrow| ≤ r, |Δcol| ≤ r` (the paper's `r = 1` → the 8
//! neighbours; the same as a `(2r+1)²` max-pool NMS). On an image covering the full 360° the columns
//! wrap: with a column period `P` (columns per turn), columns are taken modulo `P` and `Δcol` is the
//! shorter way round, so the cells left and right of the azimuth seam are neighbours ([`nms_wrapping`],
//! [`CylinderConfig::column_period`](crate::projection::CylinderConfig::column_period)); [`nms`]
//! never wraps (cropped images, generic grids). Order is total and deterministic: higher score first,
//! then lower input index. The implementation sorts only the candidates it can need
//! (`top_n · (2r+1)²` best, by selection) and marks suppression in a dense grid mask, so a full
//! 64 × 1792 map costs about a linear pass.

use std::cmp::Ordering;

use crate::error::{Error, Result};

/// Largest grid (rows × cols spanned by the input) the suppression mask may allocate.
const MAX_GRID_CELLS: usize = 1 << 28;

/// Greedy NMS. `rows[i]`, `cols[i]` are the grid cell of entry `i` (≥ 0), `scores[i]` its confidence
/// (not NaN). Returns the indices of the kept entries, best first, at most `top_n` (all when `None`).
/// Entries in the same cell suppress each other (the better one survives). Columns do not wrap.
pub fn nms(
    rows: &[i64],
    cols: &[i64],
    scores: &[f32],
    radius: usize,
    top_n: Option<usize>,
) -> Result<Vec<usize>> {
    nms_wrapping(rows, cols, scores, radius, top_n, None)
}

/// [`nms`] on a grid whose columns wrap with `column_period` (`Some(P)`: columns `c` and `c + P` are
/// the same column, and `P − 1` neighbours 0); `None` is [`nms`].
pub fn nms_wrapping(
    rows: &[i64],
    cols: &[i64],
    scores: &[f32],
    radius: usize,
    top_n: Option<usize>,
    column_period: Option<usize>,
) -> Result<Vec<usize>> {
    if column_period == Some(0) {
        return Err(Error::invalid("column_period", "must be > 0"));
    }
    let n = scores.len();
    if rows.len() != n {
        return Err(Error::invalid(
            "rows",
            format!("has {} entries, scores has {n}", rows.len()),
        ));
    }
    if cols.len() != n {
        return Err(Error::invalid(
            "cols",
            format!("has {} entries, scores has {n}", cols.len()),
        ));
    }
    if let Some(i) = scores.iter().position(|s| s.is_nan()) {
        return Err(Error::invalid("scores", format!("element {i} is NaN")));
    }
    for (name, values) in [("rows", rows), ("cols", cols)] {
        if let Some(i) = values.iter().position(|&v| v < 0) {
            return Err(Error::invalid(
                name,
                format!("element {i} is negative ({})", values[i]),
            ));
        }
    }
    let limit = top_n.unwrap_or(n).min(n);
    if limit == 0 {
        return Ok(Vec::new());
    }
    let grid_rows = rows.iter().max().map_or(0, |&r| r as usize + 1);
    let grid_cols = match column_period {
        Some(period) => period,
        None => cols.iter().max().map_or(0, |&c| c as usize + 1),
    };
    if grid_rows.saturating_mul(grid_cols) > MAX_GRID_CELLS {
        return Err(Error::invalid(
            "rows",
            format!(
                "cells span {grid_rows} x {grid_cols}, more than the {MAX_GRID_CELLS} supported"
            ),
        ));
    }

    let better = |a: &u32, b: &u32| -> Ordering {
        scores[*b as usize]
            .total_cmp(&scores[*a as usize])
            .then(a.cmp(b))
    };
    let mut order: Vec<u32> = (0..n as u32).collect();
    let window = (2 * radius + 1).saturating_mul(2 * radius + 1);
    let first_batch = limit.saturating_mul(window).min(n);
    if first_batch < n {
        order.select_nth_unstable_by(first_batch, better);
    }
    order[..first_batch].sort_unstable_by(better);

    let mut suppressed = SuppressionGrid::new(grid_rows, grid_cols, column_period.is_some());
    let mut kept = Vec::with_capacity(limit);
    let mut visit = |candidates: &[u32], kept: &mut Vec<usize>| {
        for &i in candidates {
            if kept.len() == limit {
                return;
            }
            let (row, col) = (rows[i as usize] as usize, cols[i as usize] as usize);
            if suppressed.is_suppressed(row, col) {
                continue;
            }
            kept.push(i as usize);
            suppressed.suppress_around(row, col, radius);
        }
    };
    visit(&order[..first_batch], &mut kept);
    if kept.len() < limit && first_batch < n {
        // Many entries shared cells: the rest (all ranked below the first batch) is needed after all.
        order[first_batch..].sort_unstable_by(better);
        visit(&order[first_batch..], &mut kept);
    }
    Ok(kept)
}

/// Dense "already suppressed" mask of a `rows × cols` grid; with `wraps`, `cols` is the column period
/// and columns are taken modulo it (windows wrap round the seam). Shared with the fused NMS of
/// [`crate::matches::select_matches`].
pub(crate) struct SuppressionGrid {
    mask: Vec<bool>,
    rows: usize,
    cols: usize,
    wraps: bool,
}

impl SuppressionGrid {
    pub(crate) fn new(rows: usize, cols: usize, wraps: bool) -> Self {
        SuppressionGrid {
            mask: vec![false; rows * cols],
            rows,
            cols,
            wraps,
        }
    }

    #[inline]
    fn column(&self, col: usize) -> usize {
        if self.wraps {
            col % self.cols
        } else {
            col
        }
    }

    #[inline]
    pub(crate) fn is_suppressed(&self, row: usize, col: usize) -> bool {
        self.mask[row * self.cols + self.column(col)]
    }

    /// Marks the `(2·radius + 1)²` window around `(row, col)` (clipped at the grid's edges, wrapped
    /// round the seam when the columns wrap).
    pub(crate) fn suppress_around(&mut self, row: usize, col: usize, radius: usize) {
        let (r0, r1) = (
            row.saturating_sub(radius),
            (row + radius).min(self.rows - 1),
        );
        let col = self.column(col);
        for r in r0..=r1 {
            let line = &mut self.mask[r * self.cols..(r + 1) * self.cols];
            if self.wraps && 2 * radius + 1 >= self.cols {
                line.fill(true);
            } else if self.wraps {
                // The window [col − radius, col + radius] modulo the period: one or two runs.
                let start = (col + self.cols - radius % self.cols) % self.cols;
                let end = start + 2 * radius; // inclusive, < 2·cols
                if end < self.cols {
                    line[start..=end].fill(true);
                } else {
                    line[start..].fill(true);
                    line[..=end - self.cols].fill(true);
                }
            } else {
                let (c0, c1) = (
                    col.saturating_sub(radius),
                    (col + radius).min(self.cols - 1),
                );
                line[c0..=c1].fill(true);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Straightforward O(n²) greedy NMS as the reference; with a period, the column distance is the
    /// shorter way round.
    fn reference_wrapping(
        rows: &[i64],
        cols: &[i64],
        scores: &[f32],
        radius: i64,
        top_n: usize,
        period: Option<i64>,
    ) -> Vec<usize> {
        let column_distance = |a: i64, b: i64| match period {
            None => (a - b).abs(),
            Some(p) => {
                let d = (a - b).rem_euclid(p);
                d.min(p - d)
            }
        };
        let mut order: Vec<usize> = (0..scores.len()).collect();
        order.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]).then(a.cmp(&b)));
        let mut kept: Vec<usize> = Vec::new();
        for i in order {
            if kept.len() == top_n {
                break;
            }
            if kept.iter().all(|&k| {
                (rows[k] - rows[i]).abs() > radius || column_distance(cols[k], cols[i]) > radius
            }) {
                kept.push(i);
            }
        }
        kept
    }

    fn reference(
        rows: &[i64],
        cols: &[i64],
        scores: &[f32],
        radius: i64,
        top_n: usize,
    ) -> Vec<usize> {
        reference_wrapping(rows, cols, scores, radius, top_n, None)
    }

    #[test]
    fn wrapping_matches_the_quadratic_reference_across_the_seam() {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        for trial in 0..60 {
            // Small periods make the seam and windows wider than the grid likely; entries may sit
            // in column P (the duplicated ±180° column of a 1801-wide image).
            let period = [2usize, 3, 5, 7, 12, 60][trial % 6];
            let n = rng.random_range(1..300);
            let rows: Vec<i64> = (0..n).map(|_| rng.random_range(0..8)).collect();
            let cols: Vec<i64> = (0..n)
                .map(|_| rng.random_range(0..=period as i64))
                .collect();
            let scores: Vec<f32> = (0..n)
                .map(|_| (rng.random_range(0..40) as f32) / 10.0)
                .collect();
            let radius = trial % 4;
            let top_n = if trial % 2 == 0 {
                n
            } else {
                rng.random_range(1..40)
            };
            assert_eq!(
                nms_wrapping(&rows, &cols, &scores, radius, Some(top_n), Some(period)).unwrap(),
                reference_wrapping(
                    &rows,
                    &cols,
                    &scores,
                    radius as i64,
                    top_n,
                    Some(period as i64)
                ),
                "trial {trial}, period {period}, radius {radius}"
            );
        }
    }

    #[test]
    fn the_seam_suppresses_only_when_wrapping() {
        // A full KITTI ring: 1801 columns, period 1800. The best entry sits at column 0; its
        // neighbours across the seam are columns 1799 and 1800 (= 0 again).
        let rows = [5, 5, 5, 4, 5];
        let cols = [0, 1799, 1800, 1798, 2];
        let scores = [0.9, 0.8, 0.7, 0.6, 0.5];
        assert_eq!(
            nms_wrapping(&rows, &cols, &scores, 1, None, Some(1800)).unwrap(),
            vec![0, 3, 4]
        );
        assert_eq!(nms(&rows, &cols, &scores, 1, None).unwrap(), vec![0, 1, 4]);
        assert!(nms_wrapping(&rows, &cols, &scores, 1, None, Some(0)).is_err());
    }

    #[test]
    fn matches_the_quadratic_reference_on_random_maps() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for trial in 0..30 {
            let n = rng.random_range(1..600);
            let rows: Vec<i64> = (0..n).map(|_| rng.random_range(0..20)).collect();
            let cols: Vec<i64> = (0..n).map(|_| rng.random_range(0..60)).collect();
            // Coarse scores create ties, which must break by index.
            let scores: Vec<f32> = (0..n)
                .map(|_| (rng.random_range(0..50) as f32) / 10.0)
                .collect();
            let radius = trial % 3;
            let top_n = if trial % 2 == 0 {
                n
            } else {
                rng.random_range(1..50)
            };
            assert_eq!(
                nms(&rows, &cols, &scores, radius, Some(top_n)).unwrap(),
                reference(&rows, &cols, &scores, radius as i64, top_n),
                "trial {trial}"
            );
        }
    }

    #[test]
    fn keeps_the_local_maxima_of_a_full_map() {
        // A 64 × 1792 map with isolated peaks on a lower background: every peak survives and no kept
        // entry has a better neighbour in its window.
        let (h, w) = (64i64, 1792i64);
        let mut rows = Vec::new();
        let mut cols = Vec::new();
        let mut scores = Vec::new();
        for r in 0..h {
            for c in 0..w {
                rows.push(r);
                cols.push(c);
                let peak = r % 4 == 1 && c % 4 == 1;
                scores.push(if peak {
                    1.0 + (r * w + c) as f32 * 1e-6
                } else {
                    0.5
                });
            }
        }
        let kept = nms(&rows, &cols, &scores, 1, None).unwrap();
        let peaks = kept.iter().filter(|&&i| scores[i] > 0.9).count();
        assert_eq!(peaks, (h as usize / 4) * (w as usize / 4));
        for &k in &kept {
            for &other in &kept {
                if k != other {
                    assert!((rows[k] - rows[other]).abs() > 1 || (cols[k] - cols[other]).abs() > 1);
                }
            }
        }
        let top = nms(&rows, &cols, &scores, 1, Some(10)).unwrap();
        assert_eq!(top.len(), 10);
        assert_eq!(
            top[0],
            ((h - 3) * w + (w - 3)) as usize,
            "the best peak is the last one"
        );
    }

    #[test]
    fn duplicates_empty_and_bad_input() {
        let kept = nms(
            &[0, 0, 0, 5],
            &[0, 0, 0, 5],
            &[0.5, 0.9, 0.9, 0.1],
            1,
            Some(3),
        )
        .unwrap();
        assert_eq!(kept, vec![1, 3]);
        assert!(nms(&[], &[], &[], 1, Some(5)).unwrap().is_empty());
        assert!(nms(&[0], &[0, 1], &[1.0], 1, None).is_err());
        assert!(nms(&[-1], &[0], &[1.0], 1, None).is_err());
        assert!(nms(&[0], &[0], &[f32::NAN], 1, None).is_err());
        assert!(nms(&[1 << 40], &[1 << 40], &[1.0], 1, None).is_err());
    }
}
