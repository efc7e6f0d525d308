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

/// Two scans' random features: `channels` (coarse, refine), the refine features `size` (rows, columns),
/// the coarse ones at `stride`; seeds `seed + 1` to `seed + 4`.
struct RandomPair {
    maps: [Vec<f32>; 4],
    channels: (usize, usize),
    size: (usize, usize),
    stride: [usize; 2],
}

impl RandomPair {
    fn new(channels: (usize, usize), size: (usize, usize), stride: [usize; 2], seed: u64) -> Self {
        let (height, width) = size;
        let coarse = (height / stride[0], width / stride[1]);
        let maps = [
            features(channels.0, coarse.0, coarse.1, seed + 1),
            features(channels.1, height, width, seed + 2),
            features(channels.0, coarse.0, coarse.1, seed + 3),
            features(channels.1, height, width, seed + 4),
        ];
        RandomPair {
            maps,
            channels,
            size,
            stride,
        }
    }

    /// (reference, target).
    fn scans(&self) -> (ScanFeatures<'_>, ScanFeatures<'_>) {
        let (height, width) = self.size;
        let coarse = (height / self.stride[0], width / self.stride[1]);
        let scan = |first: usize| ScanFeatures {
            coarse: FeatureMap {
                data: &self.maps[first],
                channels: self.channels.0,
                height: coarse.0,
                width: coarse.1,
            },
            refine: FeatureMap {
                data: &self.maps[first + 1],
                channels: self.channels.1,
                height,
                width,
            },
        };
        (scan(0), scan(2))
    }
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
        let pair = RandomPair::new(
            (coarse_channels, refine_channels),
            (height, width),
            stride,
            10 * seed as u64,
        );
        let (reference, target) = pair.scans();
        let mut config = config();
        (config.coarse_window, config.refine_window) = windows;
        config.stride = stride;
        config.coarse_scale = 8.0;
        config.refine_scale = 8.0;
        let checked = match_features(&reference, &target, &config).unwrap();
        let grouped = match_checked(&reference, &target, &config, None, None, Grouping::Allowed);
        assert_eq!(checked, grouped);
        let alone = match_checked(
            &reference,
            &target,
            &config,
            None,
            None,
            Grouping::CellByCell,
        );
        // Same offsets to the bit (the window sums run in the same order); Q* summed in another order.
        assert_eq!(grouped.flow, alone.flow, "case {seed}");
        for (a, b) in grouped.confidence.iter().zip(&alone.confidence) {
            assert_relative_eq!(*a, *b, max_relative = 1e-5);
            assert!(*a > 0.0 && *a <= 1.0, "Q* {a} is not a mass");
        }
    }
}

#[test]
fn marked_cells_get_the_dense_match_and_the_others_none() {
    // Masks as a scan's occupancy: empty top rows (the sky), holes scattered through the rest, a block
    // with a single marked cell; and all cells marked.
    let (height, width) = (16, 128);
    let pair = RandomPair::new((32, 8), (height, width), [4, 8], 4);
    let (reference, target) = pair.scans();
    let mut config = config();
    (config.coarse_window, config.refine_window) = (15, 5);
    (config.coarse_scale, config.refine_scale) = (8.0, 8.0);
    let dense = match_features(&reference, &target, &config).unwrap();

    let mut occupancy: Vec<bool> = (0..height * width)
        .map(|cell| cell / width >= 5 && (cell * 7919) % 11 != 0)
        .collect();
    occupancy[2 * width + 77] = true;
    let all = vec![true; height * width];
    for (name, marks) in [("occupancy", &occupancy), ("all", &all)] {
        let sparse = match_features_of_cells(&reference, &target, &config, marks).unwrap();
        for (cell, &marked) in marks.iter().enumerate() {
            let flow = [sparse.flow[cell], sparse.flow[height * width + cell]];
            if marked {
                let expected = [dense.flow[cell], dense.flow[height * width + cell]];
                assert_eq!(flow, expected, "{name}: cell {cell}");
                assert_relative_eq!(
                    sparse.confidence[cell],
                    dense.confidence[cell],
                    max_relative = 1e-5
                );
            } else {
                assert!(
                    flow.iter().all(|v| v.is_nan()),
                    "{name}: cell {cell} {flow:?}"
                );
                assert_eq!(sparse.confidence[cell], 0.0);
            }
        }
    }
    let all_marked = match_features_of_cells(&reference, &target, &config, &all).unwrap();
    assert_eq!(all_marked, dense);

    let message =
        |marks: &[bool]| match match_features_of_cells(&reference, &target, &config, marks) {
            Err(error) => error.to_string(),
            Ok(_) => panic!("accepted {} marks", marks.len()),
        };
    assert!(message(&all[1..]).contains("cells"));
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

#[test]
fn guided_windows_reach_a_shift_beyond_the_window() {
    // The scene moved by (4, 48) pixels = (1, 6) coarse cells; the coarse window (5: ±2 cells) cannot
    // reach it from each cell, the windows placed by the expected flow can, even a few pixels off.
    let (channels, height, width) = (16, 16, 256);
    let (coarse_height, coarse_width) = (height / 4, width / 8);
    let coarse_ref = features(channels, coarse_height, coarse_width, 1);
    let coarse_tgt = shifted(&coarse_ref, channels, coarse_height, coarse_width, (1, 6));
    let refine_ref = features(channels, height, width, 2);
    let refine_tgt = shifted(&refine_ref, channels, height, width, (4, 48));
    let map = |data, height, width| FeatureMap {
        data,
        channels,
        height,
        width,
    };
    let reference = ScanFeatures {
        coarse: map(&coarse_ref, coarse_height, coarse_width),
        refine: map(&refine_ref, height, width),
    };
    let target = ScanFeatures {
        coarse: map(&coarse_tgt, coarse_height, coarse_width),
        refine: map(&refine_tgt, height, width),
    };
    let config = config();
    // Inside: cells whose coarse cell, moved, and refine window stay in the image.
    let inside = |cell: usize| (cell / width) < 8 && (cell % width) < width - 64;
    let reached = |flow: &DenseFlow| {
        (0..height * width)
            .filter(|&cell| inside(cell))
            .all(|cell| {
                (flow.flow[cell] - 4.0).abs() < 0.51
                    && (flow.flow[height * width + cell] - 48.0).abs() < 0.51
            })
    };
    assert!(!reached(
        &match_features(&reference, &target, &config).unwrap()
    ));
    // A cell that expects nothing (NaN) leaves its block to the others' median.
    let expected: Vec<[f32; 2]> = (0..height * width)
        .map(|cell| match cell % 5 {
            0 => [f32::NAN, f32::NAN],
            1 => [3.2, 45.0],
            _ => [5.0, 50.5],
        })
        .collect();
    let guided = match_features_guided(&reference, &target, &config, None, &expected).unwrap();
    assert!(reached(&guided));
    for cell in (0..height * width).filter(|&cell| inside(cell)) {
        assert!(guided.confidence[cell] > 0.5, "cell {cell}");
    }
}

#[test]
fn guided_windows_with_no_expectation_are_the_plain_match() {
    let (height, width) = (16, 128);
    let pair = RandomPair::new((32, 8), (height, width), [4, 8], 7);
    let (reference, target) = pair.scans();
    let mut config = config();
    (config.coarse_window, config.refine_window) = (15, 5);
    (config.coarse_scale, config.refine_scale) = (8.0, 8.0);
    let nothing = vec![[f32::NAN; 2]; height * width];
    let dense = match_features(&reference, &target, &config).unwrap();
    let guided = match_features_guided(&reference, &target, &config, None, &nothing).unwrap();
    assert_eq!(guided, dense);
    let marks: Vec<bool> = (0..height * width).map(|cell| cell % 3 != 0).collect();
    let sparse = match_features_of_cells(&reference, &target, &config, &marks).unwrap();
    let guided =
        match_features_guided(&reference, &target, &config, Some(&marks), &nothing).unwrap();
    // Bit for bit, NaN flows of the unmarked cells included.
    let bits = |values: &[f32]| values.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&guided.flow), bits(&sparse.flow));
    assert_eq!(bits(&guided.confidence), bits(&sparse.confidence));
}

#[test]
fn guided_cells_matched_in_groups_match_as_they_do_one_by_one() {
    // Guides that change from block to block (groups split where neighbours' windows part) and reach
    // past the borders (centres clamped).
    let (height, width) = (16, 192);
    let pair = RandomPair::new((32, 8), (height, width), [4, 8], 9);
    let (reference, target) = pair.scans();
    let mut config = config();
    (config.coarse_window, config.refine_window) = (15, 7);
    (config.coarse_scale, config.refine_scale) = (8.0, 8.0);
    let expected: Vec<[f32; 2]> = (0..height * width)
        .map(|cell| {
            let (row, col) = ((cell / width) as f32, (cell % width) as f32);
            [(row - 8.0) * 1.5, col - 96.0]
        })
        .collect();
    let guide = coarse_guide(&expected, &reference.coarse, config.stride);
    assert!(guide.iter().any(|g| g[1] > 8) && guide.iter().any(|g| g[1] < -8));
    let grouped = match_checked(
        &reference,
        &target,
        &config,
        None,
        Some(&guide),
        Grouping::Allowed,
    );
    assert_eq!(
        grouped,
        match_features_guided(&reference, &target, &config, None, &expected).unwrap()
    );
    let alone = match_checked(
        &reference,
        &target,
        &config,
        None,
        Some(&guide),
        Grouping::CellByCell,
    );
    assert_eq!(grouped.flow, alone.flow);
    for (a, b) in grouped.confidence.iter().zip(&alone.confidence) {
        assert_relative_eq!(*a, *b, max_relative = 1e-5);
    }
}

#[test]
fn a_guide_of_the_wrong_size_is_named() {
    let pair = RandomPair::new((32, 8), (16, 64), [4, 8], 3);
    let (reference, target) = pair.scans();
    let message = |cells: Option<&[bool]>, expected: &[[f32; 2]]| match match_features_guided(
        &reference,
        &target,
        &config(),
        cells,
        expected,
    ) {
        Err(error) => error.to_string(),
        Ok(_) => panic!("accepted"),
    };
    let expected = vec![[0.0f32; 2]; 16 * 64];
    assert!(message(None, &expected[1..]).starts_with("expected"));
    let marks = vec![true; 16 * 64 - 1];
    assert!(message(Some(&marks), &expected).starts_with("cells"));
}
