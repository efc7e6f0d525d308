#![forbid(unsafe_code)]
//! A point's cell without arctangents: the bin tables of a config's cell boundaries, and the exact
//! float64 tests for the points a table cannot settle.

use std::sync::{Arc, Mutex};

use super::CylinderConfig;

/// Cells and ranges of a block of points (`NO_CELL` outside the image or at the origin, `NON_FINITE`
/// for NaN/Inf values).
pub(super) struct Located {
    pub(super) cells: [u32; BLOCK],
    pub(super) ranges: [f32; BLOCK],
}

/// Sentinel for "this point lands in no cell".
pub(super) const NO_CELL: u32 = u32::MAX;
/// Sentinel for "this point is NaN/Inf".
pub(super) const NON_FINITE: u32 = u32::MAX - 1;

// ---- exact cell lookup without arctangents -------------------------------------------------------
//
// The definition of a point's cell is the libm formula `⌊origin − atan2(·,·)·cells_per_radian + ½⌋`
// per axis (module docs). Instead of evaluating it, a point is compared with the cell *boundaries*:
// boundary k (k = 0 ..= cells) is the angle at which the formula reaches k, and the cell is (number of
// boundaries the point is at or past) − 1. A table over a cheap monotone *key* of the point (float32
// `z/‖p‖` for the elevation; for the azimuth the "diamond angle" `y/(|x|+|y|)` continued to (−2, 2])
// says how many boundaries every point of its bin passes, and names the one boundary (if any) the bin
// cannot settle; that one is tested exactly in float64 without trigonometry: `z − ‖p‖·sin β ≤ 0` for
// the elevation, the sign of the cross product with the boundary's direction `(cos α, sin α)` for the
// azimuth.
//
// Identity with the formula: a bin settles a boundary only when it lies `KEY_MARGIN` (key units, which
// are never more than radians) beyond the bin, more than the float32 key's error, so the point is
// ≥ 1e-5 rad clear of it; the exact test decides only when the point is `BOUNDARY_MARGIN` = 1e-11 rad
// clear. The formula's own rounding (atan2, products, sums) and the tables' move a boundary by less
// than 1e-14 rad, so every decided comparison is the formula's. Undecided points (≈ 1 in 10⁸ real
// ones; adversarial ones on a boundary), the poles, points within 1e-30 m of the origin or beyond
// 1e18 m, and boundaries within `EDGE_GUARD` of the poles or of ±180° get the formula itself.

/// Points closer than this (radians) to a tested boundary get the libm formula.
const BOUNDARY_MARGIN: f64 = 1e-11;

/// A bin settles a boundary only when it is this far (key units) from the bin: covers the float32
/// key's error (≤ 1e-6 for keys within ±2, including the bin computation).
const KEY_MARGIN: f64 = 1e-5;

/// A key this far (key units) from its bin's unsettled boundary settles the comparison in float32:
/// above the float32 keys' error (≤ 5e-7, with the boundary key's rounding), so the point is
/// ≥ 3e-6 rad from the boundary.
const FAST_KEY_MARGIN: f32 = 4e-6;

/// Boundaries within this many radians of the poles (elevation) or of ±180° (azimuth) are left to
/// the libm formula; boundaries farther beyond them are passed by every point or by none.
const EDGE_GUARD: f64 = 1e-6;

/// Points per block: the keys of a block are computed in vectorisable loops first.
pub(super) const BLOCK: usize = 64;

/// The libm formula for one axis: the cell index, or −1 when negative (outside the image anyway).
#[inline(never)]
fn exact_cell(origin: f64, y: f64, x: f64, cells_per_radian: f64) -> i64 {
    let shifted = origin - y.atan2(x) * cells_per_radian + 0.5;
    if shifted < 0.0 {
        -1
    } else {
        // Huge values saturate, which is outside the image just the same.
        shifted.floor() as i64
    }
}

/// One bin of a [`BinTable`]: every point in it passes `passed` (padded) boundaries for sure, plus
/// the bin's unsettled boundary when the point's key is ≤ `test_key`, the boundary's key in float32
/// (−∞ when the bin has none; NaN when it cannot be decided this way).
#[derive(Clone, Copy)]
struct Bin {
    passed: u32,
    test_key: f32,
}

/// Uniform bins over the key range `[lowest, lowest + span]` of one axis.
struct BinTable {
    bins: Vec<Bin>,
    /// Per bin, the padded index of the boundary its exact test compares with.
    tests: Vec<u32>,
    lowest: f32,
    bins_per_unit: f32,
}

impl BinTable {
    /// `keys[m]`: key of padded boundary `m`, non-increasing; a point passes it when its own key is
    /// ≤ (up to the margins). `never` and `undecidable` are the indices of the boundaries tested when
    /// a bin holds no unsettled boundary (passed by none) or more than one (always undecided);
    /// `exact[m]` says whether boundary m has an exact test (not edge-guarded).
    fn new(
        keys: &[f64],
        exact: &[bool],
        lowest: f64,
        highest: f64,
        never: usize,
        undecidable: usize,
    ) -> Self {
        let spacing = keys
            .windows(2)
            .filter(|w| w[0].is_finite() && w[1].is_finite())
            .map(|w| w[0] - w[1])
            .filter(|&d| d > 0.0)
            .fold(f64::INFINITY, f64::min);
        let span = highest - lowest;
        // Bins of half the closest spacing leave at most one boundary unsettled per bin (when the
        // spacing exceeds 4·KEY_MARGIN; closer boundaries just make their bins undecidable).
        let bins = (span / (0.5 * spacing))
            .ceil()
            .clamp(16.0, (1 << 16) as f64) as usize;
        let bin_width = span / bins as f64;
        let (bins, tests) = (0..bins)
            .map(|bin| {
                let lower = lowest + bin as f64 * bin_width;
                let upper = lower + bin_width;
                let passed = keys.partition_point(|&key| key >= upper + KEY_MARGIN);
                let unsettled = keys.partition_point(|&key| key >= lower - KEY_MARGIN) - passed;
                let test = match unsettled {
                    0 => never,
                    1 => passed,
                    _ => undecidable,
                };
                let test_key = if test == never {
                    f32::NEG_INFINITY
                } else if test == undecidable || !exact[test] {
                    f32::NAN
                } else {
                    keys[test] as f32
                };
                let bin = Bin {
                    passed: passed as u32,
                    test_key,
                };
                (bin, test as u32)
            })
            .unzip();
        BinTable {
            bins,
            tests,
            lowest: lowest as f32,
            bins_per_unit: (1.0 / bin_width) as f32,
        }
    }

    /// The bin of a key: `⌊(key − lowest)·bins_per_unit⌋` clamped to the table, up to rounding at bin
    /// edges (which `KEY_MARGIN` covers). Any key, even NaN, lands in some bin (callers only trust
    /// bins of finite keys). Branch-free float32 arithmetic that vectorises: the clamped position
    /// minus ½ is rounded to an integer by adding 2²³, whose float32 bits then hold it.
    #[inline(always)]
    fn index(&self, key: f32) -> u32 {
        const TWO_POW_23: f32 = 8_388_608.0;
        let position = (key - self.lowest) * self.bins_per_unit;
        let highest = self.bins.len() as f32 - 0.5;
        let position = if position < highest {
            position
        } else {
            highest
        };
        // NaN fails the comparison and goes to bin 0.
        let position = if position >= 0.5 { position } else { 0.5 };
        (position - 0.5 + TWO_POW_23).to_bits() - TWO_POW_23.to_bits()
    }

    #[inline(always)]
    fn bin(&self, index: u32) -> Bin {
        self.bins[index as usize]
    }

    #[inline(always)]
    fn test(&self, index: u32) -> usize {
        self.tests[index as usize] as usize
    }
}

/// One padded azimuth boundary: the point `(x, y)` passes it when
/// `cos·y − sin·x + beyond[y < 0]·(|x| + |y|) ≤ 0`. `beyond` is 0 where the cross product decides
/// (point and boundary in the same half-plane of y's sign, so less than π apart), ∓∞ where the
/// half-plane alone does; NaN everywhere makes the test undecided.
#[derive(Clone, Copy)]
struct AzimuthBoundary {
    cos: f64,
    sin: f64,
    beyond: [f64; 2],
}

impl AzimuthBoundary {
    const ALWAYS: Self = AzimuthBoundary {
        cos: 0.0,
        sin: 0.0,
        beyond: [f64::NEG_INFINITY; 2],
    };
    const NEVER: Self = AzimuthBoundary {
        cos: 0.0,
        sin: 0.0,
        beyond: [f64::INFINITY; 2],
    };
    const UNDECIDABLE: Self = AzimuthBoundary {
        cos: f64::NAN,
        sin: f64::NAN,
        beyond: [f64::NAN; 2],
    };
}

/// Monotone stand-in for the azimuth `atan2(y, x)` on (−π, π]: `y/(|x|+|y|)` in the right
/// half-plane, continued to (−2, 2] on the left.
#[inline(always)]
fn pseudo_azimuth(x: f32, y: f32) -> f32 {
    let q = y / (x.abs() + y.abs());
    if x >= 0.0 {
        q
    } else {
        2.0f32.copysign(y) - q
    }
}

/// Everything `project_flat` needs to find a point's cell quickly and exactly.
pub(super) struct CellLocator {
    row0: f64,
    col0: f64,
    rows_per_radian: f64,
    cols_per_radian: f64,
    height: usize,
    width: usize,
    /// `sin β` of the padded elevation boundaries: +∞ (passed by all), boundaries 0 ..= height,
    /// −∞ (passed by none), NaN (undecidable).
    elevation_sines: Vec<f64>,
    elevation_bins: BinTable,
    /// Padded azimuth boundaries, in the same layout.
    azimuth: Vec<AzimuthBoundary>,
    azimuth_bins: BinTable,
}

impl CellLocator {
    fn new(config: &CylinderConfig) -> Self {
        use std::f64::consts::{FRAC_PI_2, PI};
        let row0 = config.row_of_zero_elevation();
        let col0 = config.col_of_zero_azimuth();
        let rows_per_radian = 1.0 / config.vertical_resolution_deg.to_radians();
        let cols_per_radian = 1.0 / config.horizontal_resolution_deg.to_radians();
        let (height, width) = (config.height, config.width);

        // Boundary k of an axis: the angle at which `origin − angle·cells_per_radian + ½ = k`.
        let mut elevation_sines = vec![f64::INFINITY];
        let mut elevation_keys = vec![f64::INFINITY];
        for k in 0..=height {
            let beta = (row0 + 0.5 - k as f64) / rows_per_radian;
            let (sine, key) = if beta >= FRAC_PI_2 + EDGE_GUARD {
                (f64::INFINITY, f64::INFINITY)
            } else if beta <= -FRAC_PI_2 - EDGE_GUARD {
                (f64::NEG_INFINITY, f64::NEG_INFINITY)
            } else if beta.abs() > FRAC_PI_2 - EDGE_GUARD {
                (f64::NAN, 1.0f64.copysign(beta))
            } else {
                (beta.sin(), beta.sin())
            };
            elevation_sines.push(sine);
            elevation_keys.push(key);
        }
        elevation_sines.extend([f64::NEG_INFINITY, f64::NAN]);
        elevation_keys.extend([f64::NEG_INFINITY, f64::NEG_INFINITY]);
        let exact: Vec<bool> = elevation_sines.iter().map(|s| !s.is_nan()).collect();
        let elevation_bins =
            BinTable::new(&elevation_keys, &exact, -1.0, 1.0, height + 2, height + 3);

        let mut azimuth = vec![AzimuthBoundary::ALWAYS];
        let mut azimuth_keys = vec![f64::INFINITY];
        for k in 0..=width {
            let alpha = (col0 + 0.5 - k as f64) / cols_per_radian;
            let (boundary, key) = if alpha >= PI + EDGE_GUARD {
                (AzimuthBoundary::ALWAYS, f64::INFINITY)
            } else if alpha <= -PI - EDGE_GUARD {
                (AzimuthBoundary::NEVER, f64::NEG_INFINITY)
            } else if alpha.abs() > PI - EDGE_GUARD {
                (AzimuthBoundary::UNDECIDABLE, 2.0f64.copysign(alpha))
            } else {
                let (sin, cos) = alpha.sin_cos();
                // y ≥ 0 means an azimuth in [0, π], y < 0 one in (−π, 0): in the boundary's own
                // half-plane the cross product decides, in the other one the boundary's sign does.
                let beyond = if alpha > 0.0 {
                    [0.0, f64::NEG_INFINITY]
                } else {
                    [f64::INFINITY, 0.0]
                };
                // The key in float64 (the points' is float32; KEY_MARGIN covers the difference).
                let q = sin / (cos.abs() + sin.abs());
                let key = if cos >= 0.0 {
                    q
                } else {
                    2.0f64.copysign(sin) - q
                };
                (AzimuthBoundary { cos, sin, beyond }, key)
            };
            azimuth.push(boundary);
            azimuth_keys.push(key);
        }
        azimuth.extend([AzimuthBoundary::NEVER, AzimuthBoundary::UNDECIDABLE]);
        azimuth_keys.extend([f64::NEG_INFINITY, f64::NEG_INFINITY]);
        let exact: Vec<bool> = azimuth.iter().map(|b| !b.cos.is_nan()).collect();
        let azimuth_bins = BinTable::new(&azimuth_keys, &exact, -2.0, 2.0, width + 2, width + 3);

        CellLocator {
            row0,
            col0,
            rows_per_radian,
            cols_per_radian,
            height,
            width,
            elevation_sines,
            elevation_bins,
            azimuth,
            azimuth_bins,
        }
    }

    /// `(cell or NO_CELL, range)` of a finite point, by the libm formula alone.
    #[inline(never)]
    fn exact(&self, x: f64, y: f64, z: f64) -> (u32, f32) {
        let range = (x * x + y * y + z * z).sqrt();
        // At the origin, or farther than a float32 range can say (finite coordinates near f32::MAX):
        // out of view rather than an infinite range in the image.
        if range == 0.0 || !(range as f32).is_finite() {
            return (NO_CELL, 0.0);
        }
        let row = exact_cell(self.row0, z, (x * x + y * y).sqrt(), self.rows_per_radian);
        let col = exact_cell(self.col0, y, x, self.cols_per_radian);
        (self.cell(row, col), range as f32)
    }

    #[inline(always)]
    fn cell(&self, row: i64, col: i64) -> u32 {
        if row < 0 || col < 0 || row >= self.height as i64 || col >= self.width as i64 {
            NO_CELL
        } else {
            (row as usize * self.width + col as usize) as u32
        }
    }

    /// The padded count of elevation boundaries passed, by the bin's float64 test; `None` when the
    /// point is within `BOUNDARY_MARGIN` of it.
    #[inline(never)]
    fn exact_row_count(&self, bin: u32, z: f64, range: f64) -> Option<i64> {
        let passed = self.elevation_bins.bin(bin).passed as i64;
        let side = z - range * self.elevation_sines[self.elevation_bins.test(bin)];
        (side.abs() > BOUNDARY_MARGIN * range).then_some(passed + (side <= 0.0) as i64)
    }

    /// Like [`Self::exact_row_count`] for the azimuth.
    #[inline(never)]
    fn exact_col_count(&self, bin: u32, x: f64, y: f64) -> Option<i64> {
        let passed = self.azimuth_bins.bin(bin).passed as i64;
        let b = &self.azimuth[self.azimuth_bins.test(bin)];
        let norm1 = x.abs() + y.abs();
        let side = b.cos * y - b.sin * x + b.beyond[y.is_sign_negative() as usize] * norm1;
        (side.abs() > BOUNDARY_MARGIN * norm1).then_some(passed + (side <= 0.0) as i64)
    }

    /// `(cell, range)` of every point of a block of at most [`BLOCK`] points (`NO_CELL` outside the
    /// image or at the origin, `NON_FINITE` for NaN/Inf values), written to `out`. The arithmetic
    /// runs in loops over the block that vectorise, with the table reads between them.
    pub(super) fn locate_block(&self, points: &[f32], channels: usize, out: &mut Located) {
        // Separate code for each point layout: the loops below then know their stride.
        if channels == 4 {
            self.locate_block_of::<4>(points, out)
        } else {
            self.locate_block_of::<3>(points, out)
        }
    }

    #[inline(always)]
    fn locate_block_of<const CHANNELS: usize>(&self, points: &[f32], out: &mut Located) {
        let channels = CHANNELS;
        let n = points.len() / CHANNELS;
        let mut xyz = [[0.0f32; BLOCK]; 3];
        let mut reflectance_finite = [1u32; BLOCK];
        if n == BLOCK {
            // A full block: fixed trip count and stride, so the loads can be shuffled into lanes.
            let points = &points[..BLOCK * CHANNELS];
            for i in 0..BLOCK {
                let p = &points[i * CHANNELS..i * CHANNELS + CHANNELS];
                (xyz[0][i], xyz[1][i], xyz[2][i]) = (p[0], p[1], p[2]);
                if CHANNELS == 4 {
                    reflectance_finite[i] = p[3].is_finite() as u32;
                }
            }
        } else {
            for (i, p) in points.chunks_exact(CHANNELS).enumerate() {
                (xyz[0][i], xyz[1][i], xyz[2][i]) = (p[0], p[1], p[2]);
                if CHANNELS == 4 {
                    reflectance_finite[i] = p[3].is_finite() as u32;
                }
            }
        }
        let [xs, ys, zs] = &xyz;
        // Ranges in float64 (the output's exact value), keys and bins in float32 (four lanes).
        let ranges32 = &mut out.ranges;
        for i in 0..BLOCK {
            let (x, y, z) = (xs[i] as f64, ys[i] as f64, zs[i] as f64);
            ranges32[i] = (x * x + y * y + z * z).sqrt() as f32;
        }
        let mut row_keys = [0.0f32; BLOCK];
        let mut col_keys = [0.0f32; BLOCK];
        let mut row_bins = [0u32; BLOCK];
        let mut col_bins = [0u32; BLOCK];
        // 0/1 flags as u32: whole lanes, no packing of booleans.
        let mut ordinary = [0u32; BLOCK];
        for i in 0..BLOCK {
            let (x, y, z, range) = (xs[i], ys[i], zs[i], ranges32[i]);
            row_keys[i] = z / range;
            col_keys[i] = pseudo_azimuth(x, y);
            row_bins[i] = self.elevation_bins.index(row_keys[i]);
            col_bins[i] = self.azimuth_bins.index(col_keys[i]);
            // The keys are trustworthy for normal float32 values without overflow and a direction
            // in the plane; anything else, including NaN/Inf (whose range fails the comparisons),
            // goes to the formula.
            ordinary[i] = ((range < 1e18) & (range > 1e-30) & (x.abs() + y.abs() > 0.0)) as u32
                & reflectance_finite[i];
        }
        let mut row_bin = [Bin {
            passed: 0,
            test_key: 0.0,
        }; BLOCK];
        let mut col_bin = row_bin;
        for i in 0..BLOCK {
            row_bin[i] = self.elevation_bins.bin(row_bins[i]);
            col_bin[i] = self.azimuth_bins.bin(col_bins[i]);
        }
        // Padded counts from the keys alone, settled when the key is `FAST_KEY_MARGIN` clear of the
        // bin's unsettled boundary (almost always).
        let mut settled = [0u32; BLOCK];
        // Cells fit u32 (checked by `project_flat`); counts stay far below 2³¹.
        let (height, width) = (self.height as i32, self.width as i32);
        for i in 0..BLOCK {
            let (row_key, col_key) = (row_keys[i], col_keys[i]);
            let (rb, cb) = (row_bin[i], col_bin[i]);
            let row = rb.passed as i32 + (row_key <= rb.test_key) as i32 - 2;
            let col = cb.passed as i32 + (col_key <= cb.test_key) as i32 - 2;
            let inside = (row >= 0) & (col >= 0) & (row < height) & (col < width);
            let cell = (row as u32)
                .wrapping_mul(width as u32)
                .wrapping_add(col as u32);
            out.cells[i] = if inside { cell } else { NO_CELL };
            settled[i] = ordinary[i]
                & ((row_key - rb.test_key).abs() > FAST_KEY_MARGIN) as u32
                & ((col_key - cb.test_key).abs() > FAST_KEY_MARGIN) as u32;
        }
        // Most blocks are settled throughout: one vectorised check instead of a branch per point.
        if settled.iter().fold(1, |all, &s| all & s) == 0 {
            for i in 0..n {
                if settled[i] == 0 {
                    let p = &points[i * channels..(i + 1) * channels];
                    (out.cells[i], out.ranges[i]) = self.locate_slowly(p, row_bins[i], col_bins[i]);
                }
            }
        }
    }

    /// [`Self::locate_block`] for a point whose keys did not settle its cell: the float64 tests,
    /// and the formula for what they cannot decide (or for unusual points).
    #[inline(never)]
    fn locate_slowly(&self, p: &[f32], row_bin: u32, col_bin: u32) -> (u32, f32) {
        if !p.iter().all(|v| v.is_finite()) {
            return (NON_FINITE, 0.0);
        }
        let (x32, y32, z32) = (p[0], p[1], p[2]);
        let (x, y, z) = (x32 as f64, y32 as f64, z32 as f64);
        let range = (x * x + y * y + z * z).sqrt();
        let usual = range < 1e18 && range as f32 > 1e-30 && x32.abs() + y32.abs() > 0.0;
        if !usual {
            return self.exact(x, y, z);
        }
        let row = match self.exact_row_count(row_bin, z, range) {
            Some(m) => m - 2,
            None => exact_cell(self.row0, z, (x * x + y * y).sqrt(), self.rows_per_radian),
        };
        let col = match self.exact_col_count(col_bin, x, y) {
            Some(m) => m - 2,
            None => exact_cell(self.col0, y, x, self.cols_per_radian),
        };
        (self.cell(row, col), range as f32)
    }
}

/// Tables of the most recent config, reused while calls keep the same config (building them costs
/// about a tenth of projecting a scan).
pub(super) fn cached_locator(config: &CylinderConfig) -> Arc<CellLocator> {
    static CACHE: Mutex<Option<(CylinderConfig, Arc<CellLocator>)>> = Mutex::new(None);
    // A poisoned cache only means another thread panicked while holding it; the data is replaced.
    let mut cache = CACHE
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    match &*cache {
        Some((cached, locator)) if cached == config => Arc::clone(locator),
        _ => {
            let locator = Arc::new(CellLocator::new(config));
            *cache = Some((*config, Arc::clone(&locator)));
            locator
        }
    }
}
