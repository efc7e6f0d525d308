#![forbid(unsafe_code)]
//! Φ for a whole scan ([`project_flat`]: every cell keeps its closest point) and Φ⁻¹ for many locations.

use nalgebra::Point3;
use rayon::prelude::*;

use super::locate::{cached_locator, Located, BLOCK, NON_FINITE, NO_CELL};
use super::CylinderConfig;
use crate::error::{Error, Result};

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

    /// The point image `H × W × 3`: each cell's kept point of the projected `points`, NaN where the cell
    /// is empty (the surfaces under the matches, the map's keyframes).
    pub fn point_image(&self, points: &[[f32; 4]]) -> Vec<f32> {
        self.index
            .iter()
            .flat_map(|&i| match usize::try_from(i) {
                Ok(i) => [points[i][0], points[i][1], points[i][2]],
                Err(_) => [f32::NAN; 3],
            })
            .collect()
    }
}

/// `points` must be a flat array of whole points of 3 (x, y, z) or 4 (… reflectance) values.
pub(super) fn check_flat_points(points: &[f32], channels: usize) -> Result<()> {
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
    check_cell_count(config)?;
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

/// Below 2³¹ cells, the lookup's 32-bit arithmetic is exact (that is already a 32 GiB image).
fn check_cell_count(config: &CylinderConfig) -> Result<()> {
    let (height, width) = (config.height, config.width);
    if height * width >= i32::MAX as usize {
        return Err(Error::invalid(
            "config",
            format!("image too large: {height} x {width} cells, at most 2^31 - 1"),
        ));
    }
    Ok(())
}

/// The flat cell index (`row · width + col`) each point of a flat `N × channels` scan falls in, by the
/// same rule as [`project_flat`] (so a point's cell is the one whose kept point it competed for); −1 for
/// points outside the cropped image, at the origin or with a NaN/Inf value. Lets a per-cell result (a
/// mask predicted on the image) reach every point, not only the one each cell kept.
pub fn point_cells(points: &[f32], channels: usize, config: &CylinderConfig) -> Result<Vec<i64>> {
    config.validate()?;
    check_flat_points(points, channels)?;
    check_cell_count(config)?;
    let locator = cached_locator(config);
    let mut cells = vec![-1_i64; points.len() / channels];
    cells
        .par_chunks_mut(BLOCK)
        .zip(points.par_chunks(BLOCK * channels))
        .for_each(|(out, block)| {
            let mut located = Located {
                cells: [NO_CELL; BLOCK],
                ranges: [0.0; BLOCK],
            };
            locator.locate_block(block, channels, &mut located);
            for (cell, &found) in out.iter_mut().zip(located.cells.iter()) {
                if found != NO_CELL && found != NON_FINITE {
                    *cell = i64::from(found);
                }
            }
        });
    Ok(cells)
}
