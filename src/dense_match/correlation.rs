#![forbid(unsafe_code)]
//! A cell's scaled similarities with the target's window around a centre (Eq. 2), in SIMD lanes.
//!
//! The target is zero-padded by the window radius on every side (and on the right by enough for whole
//! lanes), so every read stays inside it and cells outside the image read zero features, as in the
//! network. Two layouts, chosen by the channel count:
//!
//! - **planes** (few channels: the refine stage's 8): channel-major as the network writes it. Eight
//!   neighbouring target cells of a window row are contiguous in each channel's plane: one multiply-add
//!   per channel gives eight similarities, with the reference cell's value splatted. Neighbouring cells'
//!   windows overlap, so the few planes stay in L1.
//! - **cells** (many channels, a multiple of 8: the coarse stage's 32): channels-last, a window row one
//!   contiguous run. With 32 planes a window touches 32 × D rows of the planes, which the prefetcher
//!   cannot follow (docs/measurements.md times both layouts); a dot product per cell of 4 lanes and one
//!   horizontal sum streams instead.
//!
//! Both read one cell's window at a time. Where eight neighbouring reference cells' windows are
//! neighbours too (almost everywhere, `GroupMatcher`), [`PaddedTarget::group_logits`] reads planes of any
//! channel count for all eight at once: a window cell of the eight is one run of a plane row, so the
//! planes' cost above is shared eight ways.

use wide::f32x8;

use super::window::WindowLayout;
use super::FeatureMap;

/// SIMD lanes of a window row chunk.
pub(super) const LANES: usize = 8;

/// The window layout of a window size: rows padded to whole lanes (the padding holds −∞).
pub(super) fn lane_layout(size: usize) -> WindowLayout {
    WindowLayout {
        size,
        row_stride: size.div_ceil(LANES) * LANES,
    }
}

fn lanes(values: &[f32], start: usize) -> f32x8 {
    f32x8::from(<[f32; LANES]>::try_from(&values[start..start + LANES]).unwrap_or_default())
}

/// A target feature map, zero-padded and laid out for window reads (module docs).
pub(super) struct PaddedTarget {
    values: Vec<f32>,
    channels: usize,
    /// Columns of the padded image.
    columns: usize,
    /// Values per channel plane (planes layout).
    plane: usize,
    cell_major: bool,
}

impl PaddedTarget {
    /// With `groups`, planes whatever the channel count (the layout [`Self::group_logits`] reads);
    /// otherwise the layout the channel count reads fastest one window at a time (module docs).
    pub(super) fn new(map: &FeatureMap<'_>, layout: WindowLayout, groups: bool) -> Self {
        let cell_major = !groups && map.channels >= 2 * LANES && map.channels % LANES == 0;
        let radius = layout.size / 2;
        let rows = map.height + 2 * radius;
        let columns = map.width + layout.row_stride;
        let plane = rows * columns;
        let mut values = vec![0.0f32; map.channels * plane];
        let planes = map.data.chunks_exact(map.height * map.width);
        for (channel, source_plane) in planes.enumerate() {
            for (row, source) in source_plane.chunks_exact(map.width).enumerate() {
                let start = (row + radius) * columns + radius;
                if cell_major {
                    for (col, &value) in source.iter().enumerate() {
                        values[(start + col) * map.channels + channel] = value;
                    }
                } else {
                    let start = channel * plane + start;
                    values[start..start + map.width].copy_from_slice(source);
                }
            }
        }
        PaddedTarget {
            values,
            channels: map.channels,
            columns,
            plane,
            cell_major,
        }
    }

    /// Scaled similarities of `reference` with the window centred on `centre` (inside the image),
    /// written in `layout` with −∞ in the row padding.
    pub(super) fn window_logits(
        &self,
        reference: &CellFeatures,
        centre: (usize, usize),
        layout: WindowLayout,
        scale: f32,
        logits: &mut [f32],
    ) {
        for (step, row_logits) in logits.chunks_exact_mut(layout.row_stride).enumerate() {
            // The padding shifts by the radius: the window's top-left cell is (centre.0, centre.1).
            let first_cell = (centre.0 + step) * self.columns + centre.1;
            if self.cell_major {
                self.row_by_cells(&reference.lanes, first_cell, layout.size, scale, row_logits);
            } else {
                self.row_by_planes(&reference.lanes, first_cell, scale, row_logits);
            }
            row_logits[layout.size..].fill(f32::NEG_INFINITY);
        }
    }

    /// Scaled similarities of a group of [`LANES`] reference cells of one row (`reference`: each
    /// channel's values of the group in lanes, [`group_features`]), lane `k` with the `size × size`
    /// window centred on `(centre.0, centre.1 + k)`, all inside the image: `logits[r · size + c]` holds
    /// window cell `(r, c)` of every lane. Planes layout only. Neighbouring cells' windows are neighbouring
    /// runs of a plane row, so one load serves a window cell of all eight; the channel sum runs in the same
    /// order as [`Self::window_logits`]'s, so each lane's logits are those of its window exactly.
    pub(super) fn group_logits(
        &self,
        reference: &[f32x8],
        centre: (usize, usize),
        size: usize,
        scale: f32,
        logits: &mut [f32x8],
    ) {
        debug_assert!(!self.cell_major && reference.len() == self.channels);
        let scale = f32x8::splat(scale);
        for (step, row_logits) in logits.chunks_exact_mut(size).enumerate() {
            let first_cell = (centre.0 + step) * self.columns + centre.1;
            // The channel sum in a register: accumulating whole rows in memory instead, a load and a
            // store per multiply-add, took longer than decoding cells one by one.
            match reference.len() {
                8 => self.group_row::<8>(reference, first_cell, scale, row_logits),
                _ => {
                    for (col, logit) in row_logits.iter_mut().enumerate() {
                        let mut sum = f32x8::ZERO;
                        for (channel, &value) in reference.iter().enumerate() {
                            sum += lanes(&self.values, channel * self.plane + first_cell + col)
                                * value;
                        }
                        *logit = sum * scale;
                    }
                }
            }
        }
    }

    /// One window row of [`Self::group_logits`] for a channel count known at compile time (the bundled
    /// model's refine 8): the channel loop unrolled, the bounds checked once. Not for its coarse 32,
    /// whose reference lanes no longer fit the registers, which makes it slower than the loop above.
    fn group_row<const CHANNELS: usize>(
        &self,
        reference: &[f32x8],
        first_cell: usize,
        scale: f32x8,
        row_logits: &mut [f32x8],
    ) {
        let reference: &[f32x8; CHANNELS] = reference.try_into().expect("one lane set per channel");
        let span = (CHANNELS - 1) * self.plane + row_logits.len() + LANES - 1;
        let values = &self.values[first_cell..first_cell + span];
        for (col, logit) in row_logits.iter_mut().enumerate() {
            let mut sum = f32x8::ZERO;
            for (channel, &value) in reference.iter().enumerate() {
                sum += lanes(values, channel * self.plane + col) * value;
            }
            *logit = sum * scale;
        }
    }

    fn row_by_planes(&self, splatted: &[f32x8], first_cell: usize, scale: f32, out: &mut [f32]) {
        let scale = f32x8::splat(scale);
        for (chunk, out) in out.chunks_exact_mut(LANES).enumerate() {
            let start = first_cell + chunk * LANES;
            let mut sum = f32x8::ZERO;
            for (channel, &value) in splatted.iter().enumerate() {
                sum += lanes(&self.values, channel * self.plane + start) * value;
            }
            out.copy_from_slice(&(sum * scale).to_array());
        }
    }

    fn row_by_cells(
        &self,
        chunks: &[f32x8],
        first_cell: usize,
        size: usize,
        scale: f32,
        out: &mut [f32],
    ) {
        let start = first_cell * self.channels;
        let row = &self.values[start..start + size * self.channels];
        for (cell, logit) in row.chunks_exact(self.channels).zip(out.iter_mut()) {
            let mut sum = f32x8::ZERO;
            for (chunk, &reference) in chunks.iter().enumerate() {
                sum += lanes(cell, chunk * LANES) * reference;
            }
            *logit = sum.reduce_add() * scale;
        }
    }
}

/// One reference cell's features, as its target's layout reads them: each channel splatted across the
/// lanes (planes), or the channels in chunks of eight (cells).
pub(super) struct CellFeatures {
    lanes: Vec<f32x8>,
    cell_major: bool,
}

impl CellFeatures {
    pub(super) fn for_target(target: &PaddedTarget) -> Self {
        let count = if target.cell_major {
            target.channels / LANES
        } else {
            target.channels
        };
        CellFeatures {
            lanes: vec![f32x8::ZERO; count],
            cell_major: target.cell_major,
        }
    }

    /// Reads cell `(row, col)` of `map` (channel-major, as many channels as the target).
    pub(super) fn load(&mut self, map: &FeatureMap<'_>, row: usize, col: usize) {
        let (plane, cell) = (map.height * map.width, row * map.width + col);
        if self.cell_major {
            for (chunk, lanes) in self.lanes.iter_mut().enumerate() {
                let mut values = [0.0f32; LANES];
                for (lane, value) in values.iter_mut().enumerate() {
                    *value = map.data[(chunk * LANES + lane) * plane + cell];
                }
                *lanes = f32x8::from(values);
            }
        } else {
            for (channel, lanes) in self.lanes.iter_mut().enumerate() {
                *lanes = f32x8::splat(map.data[channel * plane + cell]);
            }
        }
    }
}

/// The features of reference cells `(row, first_col … first_col + LANES − 1)`, channel by channel in
/// lanes, for [`PaddedTarget::group_logits`].
pub(super) fn group_features(
    map: &FeatureMap<'_>,
    row: usize,
    first_col: usize,
    out: &mut [f32x8],
) {
    let (plane, first_cell) = (map.height * map.width, row * map.width + first_col);
    for (channel, lanes_out) in out.iter_mut().enumerate() {
        *lanes_out = lanes(map.data, channel * plane + first_cell);
    }
}
