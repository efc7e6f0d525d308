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
    Ok(match_checked(reference, target, config, Grouping::Allowed))
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
    grouping: Grouping,
) -> DenseFlow {
    let coarse_origins = coarse_stage(&reference.coarse, &target.coarse, config, grouping);
    refine_stage(
        &reference.refine,
        &target.refine,
        &coarse_origins,
        config,
        grouping,
    )
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
/// coarse match times the stride, rounded half to even like `torch.round`.
fn coarse_stage(
    reference: &FeatureMap<'_>,
    target: &FeatureMap<'_>,
    config: &DenseMatchConfig,
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
            // Origin 0: each window is centred on its own cell, so the windows of a group are neighbours.
            let grouped_columns = if grouped { width / LANES * LANES } else { 0 };
            let mut groups = GroupMatcher::new(
                &padded,
                reference,
                config.coarse_window,
                config.coarse_scale,
            );
            for first_col in (0..grouped_columns).step_by(LANES) {
                let found = groups.match_group(reference, row, first_col, (row, first_col));
                let [rows, cols] = found.offset.map(|lanes| lanes.to_array());
                for (lane, origin) in row_origins[first_col..][..LANES].iter_mut().enumerate() {
                    *origin = origin_of([rows[lane], cols[lane]]);
                }
            }
            let mut cells = WindowMatcher::new(&padded, layout, config.coarse_scale);
            for (col, origin) in row_origins.iter_mut().enumerate().skip(grouped_columns) {
                let found =
                    cells.match_cell(reference, (row, col), (row, col), OffsetRule::BestWindow);
                *origin = origin_of(found.offset);
            }
        });
    origins
}

fn refine_stage(
    reference: &FeatureMap<'_>,
    target: &FeatureMap<'_>,
    coarse_origins: &[[i64; 2]],
    config: &DenseMatchConfig,
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
                    let centre_col = first_centre_col as usize;
                    let found = groups.match_group(reference, row, col, (centre_row, centre_col));
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
                    col += LANES;
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

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    /// Deterministic pseudo-random features, unit length per cell like the network's.
    fn features(channels: usize, height: usize, width: usize, seed: u64) -> Vec<f32> {
        let mut state = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let mut values: Vec<f32> = (0..channels * height * width)
            .map(|_| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((state >> 40) as f32 / (1u64 << 24) as f32) - 0.5
            })
            .collect();
        let cells = height * width;
        for cell in 0..cells {
            let norm = (0..channels)
                .map(|c| values[c * cells + cell].powi(2))
                .sum::<f32>()
                .sqrt();
            for c in 0..channels {
                values[c * cells + cell] /= norm;
            }
        }
        values
    }

    /// The target as the reference shifted by `(rows, cols)` cells: target(i, j) = reference(i − rows,
    /// j − cols), random outside.
    fn shifted(
        reference: &[f32],
        channels: usize,
        height: usize,
        width: usize,
        shift: (isize, isize),
    ) -> Vec<f32> {
        let mut target = features(channels, height, width, 99);
        for c in 0..channels {
            for i in 0..height as isize {
                for j in 0..width as isize {
                    let (si, sj) = (i - shift.0, j - shift.1);
                    if si >= 0 && si < height as isize && sj >= 0 && sj < width as isize {
                        target[c * height * width + (i as usize) * width + j as usize] =
                            reference[c * height * width + (si as usize) * width + sj as usize];
                    }
                }
            }
        }
        target
    }

    fn config() -> DenseMatchConfig {
        DenseMatchConfig {
            coarse_window: 5,
            refine_window: 5,
            stride: [4, 8],
            coarse_scale: 30.0,
            refine_scale: 30.0,
            refine_offset: OffsetRule::BestWindow,
        }
    }

    #[test]
    fn a_shifted_scene_is_matched_by_its_shift_away_from_the_borders() {
        let (height, width) = (16, 64);
        // Coarse shift of (1, 1) coarse cells = (4, 8) pixels, then exact in the refine stage.
        let coarse_ref = features(16, 4, 8, 1);
        let coarse_tgt = shifted(&coarse_ref, 16, 4, 8, (1, 1));
        let refine_ref = features(16, height, width, 2);
        let refine_tgt = shifted(&refine_ref, 16, height, width, (4, 8));
        fn map(data: &[f32], channels: usize, height: usize, width: usize) -> FeatureMap<'_> {
            FeatureMap {
                data,
                channels,
                height,
                width,
            }
        }
        let reference = ScanFeatures {
            coarse: map(&coarse_ref, 16, 4, 8),
            refine: map(&refine_ref, 16, height, width),
        };
        let target = ScanFeatures {
            coarse: map(&coarse_tgt, 16, 4, 8),
            refine: map(&refine_tgt, 16, height, width),
        };
        let result = match_features(&reference, &target, &config()).unwrap();
        // Cells whose coarse cell and refine window stay inside the image: the whole shift, confidently.
        for i in 0..8 {
            for j in 0..48 {
                let cell = i * width + j;
                assert_relative_eq!(result.flow[cell], 4.0, epsilon = 0.51);
                assert_relative_eq!(result.flow[height * width + cell], 8.0, epsilon = 0.51);
                assert!(result.confidence[cell] > 0.5, "cell ({i}, {j})");
            }
        }
    }

    #[test]
    fn cells_matched_in_groups_match_as_they_do_one_by_one() {
        // Random scenes, so coarse origins vary from block to block (groups straddling two blocks of equal
        // origin, cells alone where they differ or a centre is clamped), widths with a remainder after the
        // last group, strides that do and do not put a group in one block, and channel counts the
        // correlation has a fast path for and not.
        let cases = [
            // (channels coarse, refine), (height, width), stride, windows (coarse, refine)
            ((32, 8), (16, 64), [4, 8], (15, 7)),
            ((16, 12), (12, 60), [4, 4], (5, 5)),
            ((8, 4), (8, 36), [2, 2], (9, 3)),
            ((32, 8), (16, 192), [4, 8], (41, 11)),
        ];
        for (seed, ((coarse_channels, refine_channels), (height, width), stride, windows)) in
            cases.into_iter().enumerate()
        {
            let (coarse_h, coarse_w) = (height / stride[0], width / stride[1]);
            let seed = 10 * seed as u64;
            let maps = [
                features(coarse_channels, coarse_h, coarse_w, seed + 1),
                features(refine_channels, height, width, seed + 2),
                features(coarse_channels, coarse_h, coarse_w, seed + 3),
                features(refine_channels, height, width, seed + 4),
            ];
            let map = |data, channels, height, width| FeatureMap {
                data,
                channels,
                height,
                width,
            };
            let reference = ScanFeatures {
                coarse: map(&maps[0], coarse_channels, coarse_h, coarse_w),
                refine: map(&maps[1], refine_channels, height, width),
            };
            let target = ScanFeatures {
                coarse: map(&maps[2], coarse_channels, coarse_h, coarse_w),
                refine: map(&maps[3], refine_channels, height, width),
            };
            let mut config = config();
            (config.coarse_window, config.refine_window) = windows;
            config.stride = stride;
            config.coarse_scale = 8.0;
            config.refine_scale = 8.0;
            let checked = match_features(&reference, &target, &config).unwrap();
            let grouped = match_checked(&reference, &target, &config, Grouping::Allowed);
            assert_eq!(checked, grouped);
            let alone = match_checked(&reference, &target, &config, Grouping::CellByCell);
            // Same offsets to the bit (the window sums run in the same order); Q* summed in another order.
            assert_eq!(grouped.flow, alone.flow, "case {seed}");
            for (a, b) in grouped.confidence.iter().zip(&alone.confidence) {
                assert_relative_eq!(*a, *b, max_relative = 1e-5);
                assert!(*a > 0.0 && *a <= 1.0, "Q* {a} is not a mass");
            }
        }
    }

    #[test]
    fn bad_shapes_settings_and_values_are_named() {
        let coarse = features(4, 4, 8, 1);
        let refine = features(4, 16, 64, 2);
        let scan = |coarse: &'static [f32], refine: &'static [f32]| ScanFeatures {
            coarse: FeatureMap {
                data: coarse,
                channels: 4,
                height: 4,
                width: 8,
            },
            refine: FeatureMap {
                data: refine,
                channels: 4,
                height: 16,
                width: 64,
            },
        };
        let coarse: &'static [f32] = Box::leak(coarse.into_boxed_slice());
        let refine: &'static [f32] = Box::leak(refine.into_boxed_slice());
        let good = scan(coarse, refine);
        let message = |r: Result<DenseFlow>| r.unwrap_err().to_string();

        let mut even = config();
        even.refine_window = 4;
        assert!(message(match_features(&good, &good, &even)).starts_with("refine_window"));
        let mut cold = config();
        cold.coarse_scale = 0.0;
        assert!(message(match_features(&good, &good, &cold)).starts_with("coarse_scale"));

        let mut nan = refine.to_vec();
        nan[17] = f32::NAN;
        let nan: &'static [f32] = Box::leak(nan.into_boxed_slice());
        let with_nan = scan(coarse, nan);
        assert!(message(match_features(&good, &with_nan, &config())).starts_with("tgt_refine"));

        let mut short = good;
        short.refine.data = &refine[1..];
        assert!(message(match_features(&short, &good, &config())).starts_with("ref_refine"));

        let mut wrong_stride = config();
        wrong_stride.stride = [2, 8];
        assert!(message(match_features(&good, &good, &wrong_stride)).starts_with("ref_refine"));
        let mut huge_stride = config();
        huge_stride.stride = [usize::MAX, 8];
        assert!(message(match_features(&good, &good, &huge_stride)).starts_with("ref_refine"));

        let mut widest = config();
        widest.coarse_window = 17; // 2 · 8 columns + 1: all the coarse image can use
        assert!(match_features(&good, &good, &widest).is_ok());
        widest.coarse_window = 19;
        assert!(message(match_features(&good, &good, &widest)).starts_with("coarse_window"));
        let mut too_wide = config();
        too_wide.refine_window = 1_000_001;
        assert!(message(match_features(&good, &good, &too_wide)).starts_with("refine_window"));
    }
}
