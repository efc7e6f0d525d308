//! What happened to each scan, and the stopwatch that times its stages.

use std::collections::BTreeMap;
use std::time::Instant;

use serde::Serialize;

use super::{Matched, Notice};
use crate::odometry::motion::Fallback;

/// What happened to one scan (`FrameDiagnostics` in Python, the same keys in
/// `diagnostics.jsonl`).
#[derive(Debug, Clone, PartialEq, Default, Serialize)]
pub struct FrameDiagnostics {
    /// The scan's index in the sequence.
    pub index: usize,
    /// Points given.
    pub num_points: usize,
    /// Frames since the scan this one was matched against; `None` for scans not matched.
    pub gap: Option<usize>,
    /// Matches of the pair whose motion the frame took.
    pub num_matches: usize,
    /// Their RANSAC inliers.
    pub num_inliers: usize,
    /// Inliers over matches.
    #[serde(serialize_with = "rounded::<4, _>")]
    pub inlier_ratio: f64,
    /// With tilt votes: the inliers' votes above the floor.
    #[serde(serialize_with = "rounded_option::<2, _>")]
    pub inlier_votes: Option<f64>,
    /// The fallback taken, if any.
    pub fallback: Option<Fallback>,
    /// Rounds of matching from the prediction whose motion was taken (0: tried, none kept).
    pub rematch_rounds: Option<usize>,
    /// Matched from the prediction with the coarse windows placed by it: whether that pair held (false:
    /// it gave way to the reference moved by the prediction); `None` when not tried.
    pub guided_windows: Option<bool>,
    /// The first pair (no velocity yet) checked from starts ahead and behind
    /// (`motion_model.start_check_m`): whether one of them held a motion of its own further from the
    /// frame's than `motion_model.max_deviation` (true: the motion may be an alias, e.g. evenly spaced
    /// posts passed at speed; with `motion_model.start_max_reverse_m`, a frame driving backwards took a
    /// start's forward motion: `fallback` `forward_start`); `None` when not checked.
    pub ambiguous_start: Option<bool>,
    /// With `matching.symmetric`: RANSAC inliers of the scan matched back against the previous one.
    pub backward_inliers: Option<usize>,
    /// NDT against the map converged.
    pub ndt_converged: Option<bool>,
    /// Pose directions the map did not constrain.
    pub ndt_degenerate_directions: Option<usize>,
    /// The horizontal motion came from the upright surfaces alone (near the newest keyframe).
    pub ndt_upright_only: Option<bool>,
    /// The scan entered the map.
    pub map_keyframe: Option<bool>,
    /// The NDT start that won: "dmlo", "motion_model" or "standing".
    pub ndt_start: Option<String>,
    /// Points the moving-object network left out; `None` when it did not run (no network, or the caller's
    /// flags came in [`super::Scan::moving`]).
    pub num_moving_predicted: Option<usize>,
    /// Fraction of the cylinder image's cells holding a point.
    #[serde(serialize_with = "rounded_option::<4, _>")]
    pub image_fill: Option<f64>,
    /// With `deskew.enabled`: the sweep was motion-compensated.
    pub deskewed: bool,
    /// Milliseconds per stage.
    #[serde(serialize_with = "rounded_map::<3, _>")]
    pub timings_ms: BTreeMap<String, f64>,
    /// What the odometry said about the scans at this frame (each once per odometry; the reflectance
    /// notices again when the choice changes).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub notices: Vec<Notice>,
}

/// `value` to `DIGITS` decimals, as the diagnostics are written.
fn round_to<const DIGITS: i32>(value: f64) -> f64 {
    let scale = 10f64.powi(DIGITS);
    (value * scale).round() / scale
}

fn rounded<const DIGITS: i32, S: serde::Serializer>(
    value: &f64,
    s: S,
) -> std::result::Result<S::Ok, S::Error> {
    s.serialize_f64(round_to::<DIGITS>(*value))
}

fn rounded_option<const DIGITS: i32, S: serde::Serializer>(
    value: &Option<f64>,
    s: S,
) -> std::result::Result<S::Ok, S::Error> {
    match value {
        Some(v) => s.serialize_some(&round_to::<DIGITS>(*v)),
        None => s.serialize_none(),
    }
}

fn rounded_map<const DIGITS: i32, S: serde::Serializer>(
    values: &BTreeMap<String, f64>,
    s: S,
) -> std::result::Result<S::Ok, S::Error> {
    s.collect_map(values.iter().map(|(k, v)| (k, round_to::<DIGITS>(*v))))
}

impl FrameDiagnostics {
    pub(super) fn count_matches(&mut self, pair: &Matched) {
        self.num_matches = pair.motion.source.len();
        self.num_inliers = pair.motion.num_inliers;
        self.inlier_ratio = if self.num_matches > 0 {
            self.num_inliers as f64 / self.num_matches as f64
        } else {
            0.0
        };
    }
}

/// Milliseconds per stage, each lap from the end of the last.
pub(super) struct Stopwatch {
    last: Instant,
}

impl Stopwatch {
    pub(super) fn new() -> Self {
        Stopwatch {
            last: Instant::now(),
        }
    }

    pub(super) fn lap(&mut self, stage: &str, diagnostics: &mut FrameDiagnostics) {
        let now = Instant::now();
        let ms = (now - self.last).as_secs_f64() * 1e3;
        *diagnostics
            .timings_ms
            .entry(stage.to_string())
            .or_insert(0.0) += ms;
        self.last = now;
    }
}
