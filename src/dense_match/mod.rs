#![forbid(unsafe_code)]
//! The network's matching stage on cached features (paper §III-C): coarse correlation in a D×D window
//! (Eq. 2), softmax window decoding (Eq. 3, 11), then the refine correlation around the upsampled coarse
//! match at full resolution, decoded the same way. This is `Matcher.match` of the Python package's
//! `dmlo.model.matcher` — same windows, clamping, zero features outside the image and first-maximum
//! tie-breaking — for the CPU, where the exported graph spends three quarters of a frame here: a few
//! dot products and exponentials per window cell are memory-light work that onnxruntime's general
//! MatMul / Gather / Transpose kernels do several times slower than a loop over each cell's window.
//!
//! Features come as the network writes them, channel-major `(C, h, w)`; how the target is laid out for
//! the window reads depends on the channel count (`correlation`).

mod correlation;
mod window;

use rayon::prelude::*;

use correlation::{group_features, lane_layout, CellFeatures, PaddedTarget, LANES};
use wide::f32x8;
use window::{decode_group, GroupMatch};

pub use window::{decode, OffsetRule, WindowLayout, WindowMatch};

use crate::error::{Error, Result};

/// The network's coarse stride (rows, columns): one coarse cell covers 4 × 8 pixels
/// (`MatcherConfig.coarse_stride`).
pub const NETWORK_STRIDE: [usize; 2] = [4, 8];

/// One scan's features at one stage, channel-major `(channels, height, width)` as the network outputs
/// them.
#[derive(Debug, Clone, Copy)]
pub struct FeatureMap<'a> {
    /// `channels · height · width` values, channel by channel, each row-major.
    pub data: &'a [f32],
    /// Feature channels.
    pub channels: usize,
    /// Rows.
    pub height: usize,
    /// Columns.
    pub width: usize,
}

/// A scan's cached features: coarse (stride `stride`) and refine (full resolution).
#[derive(Debug, Clone, Copy)]
pub struct ScanFeatures<'a> {
    /// Coarse features, `(C, H / stride[0], W / stride[1])`.
    pub coarse: FeatureMap<'a>,
    /// Refine features, `(Cr, H, W)`.
    pub refine: FeatureMap<'a>,
}

/// The matching stage's settings: the model's `MatcherConfig` and its two learned softmax temperatures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DenseMatchConfig {
    /// Coarse window size D (odd), in coarse cells.
    pub coarse_window: usize,
    /// Refine window size (odd), in pixels.
    pub refine_window: usize,
    /// Rows and columns of the image one coarse cell covers.
    pub stride: [usize; 2],
    /// Similarity scale of the coarse softmax (the exported `exp(coarse_log_scale)`).
    pub coarse_scale: f32,
    /// Similarity scale of the refine softmax.
    pub refine_scale: f32,
    /// How the refine window becomes a sub-pixel flow.
    pub refine_offset: OffsetRule,
}

/// The flow of every reference cell into the target scan and its confidence.
#[derive(Debug, Clone, PartialEq)]
pub struct DenseFlow {
    /// `(2, H, W)`: Δrow of every cell, then Δcol, in pixels; cell `(i, j)` matches `(i + Δrow, j + Δcol)`.
    pub flow: Vec<f32>,
    /// `(H, W)` Q* of the refine window.
    pub confidence: Vec<f32>,
    /// Image rows.
    pub height: usize,
    /// Image columns.
    pub width: usize,
}

/// Matches `reference` into `target` (both encoded by the same network): [`DenseFlow`] at full resolution.
pub fn match_features(
    reference: &ScanFeatures<'_>,
    target: &ScanFeatures<'_>,
    config: &DenseMatchConfig,
) -> Result<DenseFlow> {
    check_config(config)?;
    check_features(reference, target, config)?;
    Ok(match_checked(
        reference,
        target,
        config,
        None,
        None,
        Grouping::Allowed,
    ))
}

/// [`match_features`] for the reference cells marked in `cells` (row-major, one per full-resolution
/// cell) only: their flow is that of [`match_features`] bit for bit, their confidence too up to the
/// order a window's mass is summed in (cells next to unmarked ones may be matched alone rather than in a
/// group); every other cell gets a NaN flow and confidence 0, and coarse cells whose block holds no marked cell are not matched.
/// The odometry asks for the cells that hold a point: an empty cell's match is never read, and a
/// quarter of a KITTI image is empty.
pub fn match_features_of_cells(
    reference: &ScanFeatures<'_>,
    target: &ScanFeatures<'_>,
    config: &DenseMatchConfig,
    cells: &[bool],
) -> Result<DenseFlow> {
    check_config(config)?;
    check_features(reference, target, config)?;
    let (height, width) = (reference.refine.height, reference.refine.width);
    if cells.len() != height * width {
        return Err(Error::invalid(
            "cells",
            format!(
                "{} marks for a {height}×{width} image ({} cells)",
                cells.len(),
                height * width
            ),
        ));
    }
    Ok(match_checked(
        reference,
        target,
        config,
        Some(cells),
        None,
        Grouping::Allowed,
    ))
}

/// [`match_features_of_cells`] (every cell when `cells` is `None`) with the coarse windows placed where
/// the reference cells are expected to land: `expected` holds each full-resolution cell's expected flow
/// (Δrow, Δcol in pixels, row-major; NaN where nothing is expected, e.g. an empty cell), and the coarse
/// window of each block is centred on its cell moved by the median expected flow of the block's cells
/// (in coarse cells, rounded; clamped into the image). A predicted motion gives such a guide (where each
/// cell's point lands under it): the flow may then exceed the coarse window's reach without the reference
/// being moved and encoded again. With no expectation anywhere this is [`match_features_of_cells`] bit for
/// bit.
pub fn match_features_guided(
    reference: &ScanFeatures<'_>,
    target: &ScanFeatures<'_>,
    config: &DenseMatchConfig,
    cells: Option<&[bool]>,
    expected: &[[f32; 2]],
) -> Result<DenseFlow> {
    check_config(config)?;
    check_features(reference, target, config)?;
    let (height, width) = (reference.refine.height, reference.refine.width);
    for (name, len) in [
        ("cells", cells.map(<[bool]>::len)),
        ("expected", Some(expected.len())),
    ] {
        if let Some(len) = len.filter(|&len| len != height * width) {
            return Err(Error::invalid(
                name,
                format!(
                    "{len} values for a {height}×{width} image ({} cells)",
                    height * width
                ),
            ));
        }
    }
    let guide = coarse_guide(expected, &reference.coarse, config.stride);
    Ok(match_checked(
        reference,
        target,
        config,
        cells,
        Some(&guide),
        Grouping::Allowed,
    ))
}

/// Per coarse cell, the median expected flow of its block's cells in coarse cells, rounded half to even
/// (0 where no cell of the block expects anything).
fn coarse_guide(
    expected: &[[f32; 2]],
    coarse: &FeatureMap<'_>,
    stride: [usize; 2],
) -> Vec<[i32; 2]> {
    let width = coarse.width * stride[1];
    let median = |values: &mut Vec<f32>| -> f32 {
        let middle = values.len() / 2;
        let (_, value, _) = values.select_nth_unstable_by(middle, f32::total_cmp);
        *value
    };
    let mut rows = Vec::with_capacity(stride[0] * stride[1]);
    let mut cols = Vec::with_capacity(stride[0] * stride[1]);
    (0..coarse.height * coarse.width)
        .map(|block| {
            let (block_row, block_col) = (block / coarse.width, block % coarse.width);
            rows.clear();
            cols.clear();
            for row in block_row * stride[0]..(block_row + 1) * stride[0] {
                let first = row * width + block_col * stride[1];
                for &[d_row, d_col] in &expected[first..first + stride[1]] {
                    if d_row.is_finite() && d_col.is_finite() {
                        rows.push(d_row);
                        cols.push(d_col);
                    }
                }
            }
            if rows.is_empty() {
                return [0, 0];
            }
            let to_coarse = |pixels: f32, stride: usize| {
                (pixels / stride as f32)
                    .round_ties_even()
                    .clamp(i32::MIN as f32, i32::MAX as f32) as i32
            };
            [
                to_coarse(median(&mut rows), stride[0]),
                to_coarse(median(&mut cols), stride[1]),
            ]
        })
        .collect()
}

/// Whether neighbouring cells may be matched in groups ([`GroupMatcher`]); tests compare both ways.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Grouping {
    Allowed,
    #[cfg(test)]
    CellByCell,
}

fn match_checked(
    reference: &ScanFeatures<'_>,
    target: &ScanFeatures<'_>,
    config: &DenseMatchConfig,
    cells: Option<&[bool]>,
    guide: Option<&[[i32; 2]]>,
    grouping: Grouping,
) -> DenseFlow {
    let blocks = cells.map(|cells| marked_blocks(cells, &reference.coarse, config.stride));
    let coarse_origins = coarse_stage(
        &reference.coarse,
        &target.coarse,
        config,
        blocks.as_deref(),
        guide,
        grouping,
    );
    refine_stage(
        &reference.refine,
        &target.refine,
        &coarse_origins,
        config,
        cells,
        grouping,
    )
}

/// Which coarse cells' blocks (`stride` rows × columns of the image) hold a marked cell.
fn marked_blocks(cells: &[bool], coarse: &FeatureMap<'_>, stride: [usize; 2]) -> Vec<bool> {
    let width = coarse.width * stride[1];
    let mut blocks = vec![false; coarse.height * coarse.width];
    for (cell, _) in cells.iter().enumerate().filter(|(_, &marked)| marked) {
        let (row, col) = (cell / width, cell % width);
        blocks[(row / stride[0]) * coarse.width + col / stride[1]] = true;
    }
    blocks
}

fn check_config(config: &DenseMatchConfig) -> Result<()> {
    for (name, window) in [
        ("coarse_window", config.coarse_window),
        ("refine_window", config.refine_window),
    ] {
        if window < 3 || window % 2 == 0 {
            return Err(Error::invalid(
                name,
                format!("must be odd and >= 3, got {window}"),
            ));
        }
    }
    if config.stride.contains(&0) {
        return Err(Error::invalid("stride", "must be >= 1 in both directions"));
    }
    for (name, scale) in [
        ("coarse_scale", config.coarse_scale),
        ("refine_scale", config.refine_scale),
    ] {
        if !(scale.is_finite() && scale > 0.0) {
            return Err(Error::invalid(
                name,
                format!("must be finite and > 0, got {scale}"),
            ));
        }
    }
    Ok(())
}

fn check_features(
    reference: &ScanFeatures<'_>,
    target: &ScanFeatures<'_>,
    config: &DenseMatchConfig,
) -> Result<()> {
    let maps = [
        ("ref_coarse", &reference.coarse),
        ("ref_refine", &reference.refine),
        ("tgt_coarse", &target.coarse),
        ("tgt_refine", &target.refine),
    ];
    for (name, map) in maps {
        let expected = map
            .channels
            .checked_mul(map.height)
            .and_then(|n| n.checked_mul(map.width));
        if map.channels == 0
            || map.height == 0
            || map.width == 0
            || expected != Some(map.data.len())
        {
            return Err(Error::invalid(
                name,
                format!(
                    "{} values for ({}, {}, {}) features",
                    map.data.len(),
                    map.channels,
                    map.height,
                    map.width
                ),
            ));
        }
        if let Some(i) = map.data.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(
                name,
                format!("feature value {i} is not finite ({})", map.data[i]),
            ));
        }
    }
    let shape = |m: &FeatureMap<'_>| (m.channels, m.height, m.width);
    for (target_name, reference_name, reference_map, target_map) in [
        (
            "tgt_coarse",
            "ref_coarse",
            &reference.coarse,
            &target.coarse,
        ),
        (
            "tgt_refine",
            "ref_refine",
            &reference.refine,
            &target.refine,
        ),
    ] {
        if shape(reference_map) != shape(target_map) {
            return Err(Error::invalid(
                target_name,
                format!(
                    "shape {:?} differs from {reference_name} {:?}",
                    shape(target_map),
                    shape(reference_map)
                ),
            ));
        }
    }
    let (coarse, refine) = (&reference.coarse, &reference.refine);
    if coarse.height.checked_mul(config.stride[0]) != Some(refine.height)
        || coarse.width.checked_mul(config.stride[1]) != Some(refine.width)
    {
        return Err(Error::invalid(
            "ref_refine",
            format!(
                "{}×{} is not the coarse {}×{} times the stride {:?}",
                refine.height, refine.width, coarse.height, coarse.width, config.stride
            ),
        ));
    }
    // Beyond twice the image a window adds only zero padding; the bound keeps a mistyped size from
    // asking for a padded copy of the target that cannot be allocated.
    for (name, window, map) in [
        ("coarse_window", config.coarse_window, coarse),
        ("refine_window", config.refine_window, refine),
    ] {
        let widest = 2 * map.height.max(map.width) + 1;
        if window > widest {
            return Err(Error::invalid(
                name,
                format!(
                    "{window} is wider than the {}×{} features can use (at most {widest})",
                    map.height, map.width
                ),
            ));
        }
    }
    Ok(())
}

/// One thread's scratch for matching reference cells against a padded target, a window at a time.
struct WindowMatcher<'a> {
    target: &'a PaddedTarget,
    layout: WindowLayout,
    scale: f32,
    features: CellFeatures,
    logits: Vec<f32>,
    weights: Vec<f32>,
}

impl<'a> WindowMatcher<'a> {
    fn new(target: &'a PaddedTarget, layout: WindowLayout, scale: f32) -> Self {
        WindowMatcher {
            target,
            layout,
            scale,
            features: CellFeatures::for_target(target),
            logits: vec![0.0; layout.len()],
            weights: vec![0.0; layout.len()],
        }
    }

    /// Cell `cell` of `reference` decoded in the target window centred on `centre` (inside the image).
    fn match_cell(
        &mut self,
        reference: &FeatureMap<'_>,
        cell: (usize, usize),
        centre: (usize, usize),
        rule: OffsetRule,
    ) -> WindowMatch {
        self.features.load(reference, cell.0, cell.1);
        self.target.window_logits(
            &self.features,
            centre,
            self.layout,
            self.scale,
            &mut self.logits,
        );
        decode(&self.logits, &mut self.weights, self.layout, rule)
    }
}

/// One thread's scratch for matching [`LANES`] neighbouring reference cells of a row at once, one per
/// lane, each against its own window (`PaddedTarget::group_logits`). Used wherever the cells' windows
/// are neighbours too, which is almost everywhere: in the coarse stage every window is centred on its own
/// cell, in the refine stage the cells of one coarse block share its origin. The stage then takes about
/// two thirds of its time cell by cell (no horizontal sums, no row padding, the best 2×2 window found
/// without branches), with the same offsets (`decode_group`).
struct GroupMatcher<'a> {
    target: &'a PaddedTarget,
    size: usize,
    scale: f32,
    features: Vec<f32x8>,
    logits: Vec<f32x8>,
    weights: Vec<f32x8>,
}

impl<'a> GroupMatcher<'a> {
    fn new(target: &'a PaddedTarget, reference: &FeatureMap<'_>, size: usize, scale: f32) -> Self {
        GroupMatcher {
            target,
            size,
            scale,
            features: vec![f32x8::ZERO; reference.channels],
            logits: vec![f32x8::ZERO; size * size],
            weights: vec![f32x8::ZERO; size * size],
        }
    }

    /// Cells `(row, first_col + k)` of `reference`, lane `k` in the window centred on
    /// `(centre.0, centre.1 + k)` (all inside the image).
    fn match_group(
        &mut self,
        reference: &FeatureMap<'_>,
        row: usize,
        first_col: usize,
        centre: (usize, usize),
    ) -> GroupMatch {
        group_features(reference, row, first_col, &mut self.features);
        self.target.group_logits(
            &self.features,
            centre,
            self.size,
            self.scale,
            &mut self.logits,
        );
        decode_group(&self.logits, &mut self.weights, self.size)
    }
}

/// Whether a stage matches groups of cells: the planes it then needs are worth building only if the
/// image holds a group.
fn groups_fit(map: &FeatureMap<'_>, grouping: Grouping) -> bool {
    grouping == Grouping::Allowed && map.width >= LANES
}

/// Unclamped integer window origin of every coarse cell, in full-resolution pixels (Δrow, Δcol): the
/// coarse match times the stride, rounded half to even like `torch.round`. Each cell's window is centred on
/// the cell moved by its `guide` offset (coarse cells; none: on the cell itself), clamped into the image.
fn coarse_stage(
    reference: &FeatureMap<'_>,
    target: &FeatureMap<'_>,
    config: &DenseMatchConfig,
    blocks: Option<&[bool]>,
    guide: Option<&[[i32; 2]]>,
    grouping: Grouping,
) -> Vec<[i64; 2]> {
    let (height, width) = (reference.height, reference.width);
    let layout = lane_layout(config.coarse_window);
    let grouped = groups_fit(reference, grouping);
    let padded = PaddedTarget::new(target, layout, grouped);
    let origin_of = |offset: [f32; 2]| {
        [
            (offset[0] * config.stride[0] as f32).round_ties_even() as i64,
            (offset[1] * config.stride[1] as f32).round_ties_even() as i64,
        ]
    };
    let mut origins = vec![[0i64; 2]; height * width];
    origins
        .par_chunks_mut(width)
        .enumerate()
        .for_each(|(row, row_origins)| {
            // Unmarked blocks keep origin 0: nothing reads it.
            let wanted = |col: usize| blocks.is_none_or(|blocks| blocks[row * width + col]);
            let guide_of = |col: usize| guide.map_or([0, 0], |guide| guide[row * width + col]);
            let mut groups = GroupMatcher::new(
                &padded,
                reference,
                config.coarse_window,
                config.coarse_scale,
            );
            let mut cells = WindowMatcher::new(&padded, layout, config.coarse_scale);
            // The walk of the refine stage: groups of neighbouring cells whose windows are neighbours too
            // (the same guide, no centre clamped; unguided, every full group of the row), else single cells.
            let grouped_columns = if grouped { width / LANES * LANES } else { 0 };
            let mut col = 0;
            while col < width {
                let [guide_row, guide_col] = guide_of(col);
                let centre_row =
                    (row as i64 + guide_row as i64).clamp(0, height as i64 - 1) as usize;
                let first_centre_col = col as i64 + guide_col as i64;
                let last = col + LANES - 1;
                if last < grouped_columns
                    && (col + 1..=last).all(|c| guide_of(c) == [guide_row, guide_col])
                    && first_centre_col >= 0
                    && first_centre_col + (LANES as i64 - 1) < width as i64
                {
                    if (col..=last).any(wanted) {
                        let centre = (centre_row, first_centre_col as usize);
                        let found = groups.match_group(reference, row, col, centre);
                        let [rows, cols] = found.offset.map(|lanes| lanes.to_array());
                        let shift = [centre.0 as f32 - row as f32, centre.1 as f32 - col as f32];
                        for (lane, origin) in row_origins[col..][..LANES].iter_mut().enumerate() {
                            *origin = origin_of([shift[0] + rows[lane], shift[1] + cols[lane]]);
                        }
                    }
                    col += LANES;
                    continue;
                }
                if wanted(col) {
                    let centre_col = first_centre_col.clamp(0, width as i64 - 1) as usize;
                    let found = cells.match_cell(
                        reference,
                        (row, col),
                        (centre_row, centre_col),
                        OffsetRule::BestWindow,
                    );
                    row_origins[col] = origin_of([
                        (centre_row as f32 - row as f32) + found.offset[0],
                        (centre_col as f32 - col as f32) + found.offset[1],
                    ]);
                }
                col += 1;
            }
        });
    origins
}

fn refine_stage(
    reference: &FeatureMap<'_>,
    target: &FeatureMap<'_>,
    coarse_origins: &[[i64; 2]],
    config: &DenseMatchConfig,
    marked: Option<&[bool]>,
    grouping: Grouping,
) -> DenseFlow {
    let (height, width) = (reference.height, reference.width);
    let layout = lane_layout(config.refine_window);
    // Eq. 11 only: the peak centroid is decoded a window at a time.
    let grouped = groups_fit(reference, grouping) && config.refine_offset == OffsetRule::BestWindow;
    let padded = PaddedTarget::new(target, layout, grouped);
    let coarse_width = width / config.stride[1];
    let mut flow = vec![0.0f32; 2 * height * width];
    let mut confidence = vec![0.0f32; height * width];
    let (flow_rows, flow_cols) = flow.split_at_mut(height * width);
    flow_rows
        .par_chunks_mut(width)
        .zip(flow_cols.par_chunks_mut(width))
        .zip(confidence.par_chunks_mut(width))
        .enumerate()
        .for_each(|(row, ((row_flow_rows, row_flow_cols), row_confidence))| {
            let mut cells = WindowMatcher::new(&padded, layout, config.refine_scale);
            let mut groups = GroupMatcher::new(
                &padded,
                reference,
                config.refine_window,
                config.refine_scale,
            );
            let block_origins =
                &coarse_origins[(row / config.stride[0]) * coarse_width..][..coarse_width];
            let origin_of = |col: usize| block_origins[col / config.stride[1]];
            let row_marks = marked.map(|marked| &marked[row * width..][..width]);
            let wanted = |col: usize| row_marks.is_none_or(|marks| marks[col]);
            // The walk over the row is the dense one (groups where they fit, else single cells), cells
            // not wanted left out of it, so that a wanted cell's window is summed as the dense stage sums it.
            // Window centres are clamped into the image, as `clamp_origin` does.
            let mut col = 0;
            while col < width {
                let [origin_row, origin_col] = origin_of(col);
                let centre_row = (row as i64 + origin_row).clamp(0, height as i64 - 1) as usize;
                let first_centre_col = col as i64 + origin_col;
                let last = col + LANES - 1;
                // A group: its cells share the origin and no window centre is clamped (they are then
                // neighbours); otherwise this cell alone.
                if grouped
                    && last < width
                    && (col + 1..=last).all(|c| origin_of(c) == [origin_row, origin_col])
                    && first_centre_col >= 0
                    && first_centre_col + (LANES as i64 - 1) < width as i64
                {
                    let lanes = col..col + LANES;
                    if lanes.clone().any(wanted) {
                        let centre_col = first_centre_col as usize;
                        let found =
                            groups.match_group(reference, row, col, (centre_row, centre_col));
                        let [rows, cols] = found.offset.map(|lanes| lanes.to_array());
                        let confidence = found.confidence.to_array();
                        let shift = [
                            centre_row as f32 - row as f32,
                            centre_col as f32 - col as f32,
                        ];
                        for lane in 0..LANES {
                            row_flow_rows[col + lane] = shift[0] + rows[lane];
                            row_flow_cols[col + lane] = shift[1] + cols[lane];
                            row_confidence[col + lane] = confidence[lane];
                        }
                    }
                    for unwanted in lanes.filter(|&c| !wanted(c)) {
                        leave_unmatched(row_flow_rows, row_flow_cols, row_confidence, unwanted);
                    }
                    col += LANES;
                    continue;
                }
                if !wanted(col) {
                    leave_unmatched(row_flow_rows, row_flow_cols, row_confidence, col);
                    col += 1;
                    continue;
                }
                let centre_col = first_centre_col.clamp(0, width as i64 - 1) as usize;
                let found = cells.match_cell(
                    reference,
                    (row, col),
                    (centre_row, centre_col),
                    config.refine_offset,
                );
                row_flow_rows[col] = (centre_row as f32 - row as f32) + found.offset[0];
                row_flow_cols[col] = (centre_col as f32 - col as f32) + found.offset[1];
                row_confidence[col] = found.confidence;
                col += 1;
            }
        });
    DenseFlow {
        flow,
        confidence,
        height,
        width,
    }
}

/// A cell the refine stage was not asked for: NaN flow, confidence 0.
fn leave_unmatched(
    flow_rows: &mut [f32],
    flow_cols: &mut [f32],
    confidence: &mut [f32],
    col: usize,
) {
    flow_rows[col] = f32::NAN;
    flow_cols[col] = f32::NAN;
    confidence[col] = 0.0;
}

#[cfg(test)]
mod tests;
