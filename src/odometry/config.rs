#![forbid(unsafe_code)]
//! The odometry's settings: small typed sections with the paper's defaults, saved beside every result
//! (`config.json`). Each setting is declared once, here: its type, default, rule and doc. From that one
//! declaration come the checks of a config read from JSON, with every bad key named in one message
//! (`ransac.threshold: must be a number > 0, got "abc"`) and a suggestion for a misspelt one, and the
//! schema ([`OdometryConfig::schema_json`]) that `dmlo`'s Python classes are made from, so that Python
//! holds no second copy.
//!
//! The checks are strict: `1` is not a boolean, `1.5` not an integer, `"0.1"` and `null` are not numbers
//! (null only where a setting is optional), NaN is refused, and infinity too except for a limit (no
//! limit). Python's `json` writes an unlimited setting as the bare token `Infinity`, which is not JSON;
//! [`OdometryConfig::from_json`] reads it and [`OdometryConfig::to_json`] writes it.
//!
//! ```
//! use dmlo_rs::odometry::config::OdometryConfig;
//!
//! # fn main() -> dmlo_rs::error::Result<()> {
//! let config = OdometryConfig::from_json(r#"{"ransac": {"threshold": 0.2},
//!                                            "mapping": {"keyframe_distance": Infinity}}"#)?;
//! assert_eq!(config.ransac.threshold, 0.2);
//! assert!(config.mapping.keyframe_distance.is_infinite());
//! assert_eq!(config.matching.max_matches, 1000); // every key left out keeps its default
//! let bad = OdometryConfig::from_json(r#"{"ransac": {"treshold": 0.2}}"#).unwrap_err();
//! assert_eq!(bad.to_string(), "ransac.treshold: no such setting (did you mean ransac.threshold?)");
//! # Ok(())
//! # }
//! ```

use std::path::Path;

use serde_json::{Map, Value};

use crate::coherence::{CoherenceConfig, MAX_RADIUS as MAX_COHERENCE_RADIUS};
use crate::error::{Error, Result};
use crate::odometry::mapping::MappingConfig;
use crate::odometry::motion::MotionLimits;
use crate::pair::PairConfig;
use crate::ransac::{RansacConfig, Refit};
use crate::ray_noise::RayNoise;

pub mod schema;

mod json;

use schema::{
    names, settings, Named, Rule, Setting, AT_LEAST_ONE, AT_LEAST_THREE, BELOW_ONE, COUNT, FINITE,
    FRACTION, LIMIT, NON_NEGATIVE, OPEN_FRACTION, POSITIVE,
};

settings! {
    /// Which network predictions become 3D matches (§III-D-a).
    pub struct MatchingSection {
        /// Q* (in (0, 1]) below this is dropped before NMS.
        min_confidence: f64 = 0.0, FRACTION;
        /// NMS radius in cells; the paper's r = 1.
        nms_radius: u64 = 1, COUNT;
        /// The top N matches kept after NMS.
        max_matches: u64 = 1000, AT_LEAST_THREE;
        /// Beyond the paper: also match the new scan back against the previous one (on both scans'
        /// cached features) and take the midpoint of the two motions. The network errs differently in
        /// the two directions, so part of its error cancels; it costs one more matching pass and a second
        /// coherence pass every frame.
        symmetric: bool = false, Rule::Flag;
        /// With `symmetric`: a cell whose match, followed back by the other direction's flow, lands more
        /// than this many pixels from where it started is left out (optical flow's forward–backward
        /// check); null: keep all.
        consistency_px: Option<f64> = Some(1.0), Rule::Optional(&LIMIT);
        /// Beyond the paper: before NMS, each cell's confidence is multiplied by exp(−d / coherence_px),
        /// d the distance (pixels) of its flow from the (separable) median flow of the
        /// (2·coherence_radius+1)² cells around it: the scene moves rigidly, a wrong match jumps away
        /// from its neighbours. null: the network's confidence as it is (the paper).
        coherence_px: Option<f64> = Some(0.5), Rule::Optional(&POSITIVE);
        /// The coherence's neighbourhood radius in cells.
        coherence_radius: u64 = 2, Rule::Integer { min: 0, max: MAX_COHERENCE_RADIUS as u64 };
    }
}

/// How RANSAC's refits solve for the motion.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum RefitKind {
    /// The closed-form SVD solve (Eq. 12–14, the paper's; isotropic noise).
    PointToPoint,
    /// That solve refined by Gauss–Newton with each match weighted by its ray.
    #[default]
    RayNoise,
}

impl Named for RefitKind {
    const NAMES: &'static [(Self, &'static str)] = &[
        (RefitKind::PointToPoint, "point_to_point"),
        (RefitKind::RayNoise, "ray_noise"),
    ];
}

const REFITS: [&str; 2] = names(RefitKind::NAMES);

settings! {
    /// RANSAC around the closed-form SVD solve (§III-D-b).
    pub struct RansacSection {
        /// The inlier threshold in metres; the paper's 0.1.
        threshold: f64 = 0.1, POSITIVE;
        /// Stop once a better hypothesis would have been found with this probability.
        confidence: f64 = 0.999, OPEN_FRACTION;
        /// Hypotheses at most. At most a million: a scene without a consensus runs every one, and
        /// nothing stops them midway (Ctrl-C in Python waits for them).
        max_iterations: u64 = 1000, Rule::Integer { min: 1, max: 1_000_000 };
        /// The sampler's seed.
        seed: u64 = 0, COUNT;
        /// How the refits on the inliers solve for the motion: "point_to_point", the closed-form SVD
        /// solve (Eq. 12–14, the paper's, isotropic noise), or beyond the paper "ray_noise": that solve
        /// refined by Gauss–Newton with each match weighted by its ray. The network errs in bearing, so a
        /// match's error grows with range across its ray, while its range, read from the target scan,
        /// stays precise along it (docs/measurements.md compares the two). It assumes every point lies
        /// on a ray from one sensor origin: a skewed sweep breaks that, so skewed sweeps need `deskew`.
        refit: RefitKind = RefitKind::RayNoise, Rule::Choice(&REFITS);
        /// With "ray_noise": range noise over bearing noise, σ_r / σ_b in metres (per radian).
        ray_range_ratio: f64 = 4.0, POSITIVE;
        /// With "ray_noise": the refits' inliers lie within `threshold` along the target's ray and,
        /// across it, within the threshold or this angle's width at the match's range (0.2°: a column of
        /// the KITTI image), whichever is larger.
        ray_bearing_threshold_deg: f64 = 0.2, Rule::Number {
            lower: Some(schema::Bound::AtLeast(0.0)),
            upper: Some(schema::Bound::Below(90.0)),
            unlimited: false,
        };
        /// Beyond the paper: a match's vote in a hypothesis's consensus is the horizontal part of the
        /// normal of the surface under its reference cell (≈ 0 on the road, 1 on a wall), at least
        /// `min_vote`, instead of 1 each. The road's rings look alike from scan to scan, so at speed
        /// its matches lock onto the same rings and agree on no motion at all; counted one each they
        /// outvote the few matches on posts and signs that see the car move. The refits still solve on
        /// every inlier, road matches included. Consecutive scans only: large-motion registration
        /// compares its starts by inlier counts. false: one vote each (the paper).
        vote_by_tilt: bool = true, Rule::Flag;
        /// The votes' floor: at most a wall's vote.
        min_vote: f64 = 0.05, Rule::Number {
            lower: Some(schema::Bound::Above(0.0)),
            upper: Some(schema::Bound::AtMost(1.0)),
            unlimited: false,
        };
        /// Beyond the paper, for consecutive scans: each match's vote divided by the square root of how
        /// many matches share its cube of this many metres in the reference scan. A car a few metres
        /// away fills much of the image and holds hundreds of matches; in a traffic jam the cars keeping
        /// pace with the ego would outvote the static scene. null: no such division.
        vote_voxel: Option<f64> = Some(2.0), Rule::Optional(&POSITIVE);
    }
}

settings! {
    /// The constant-velocity motion model and its judgement of every pair (§III-D-c): the prediction
    /// taken when too few matches agree or their motion is implausible.
    pub struct MotionModelSection {
        /// Fewer RANSAC inliers than this and the pair has no motion of its own (the paper's 10).
        min_inliers: u64 = 10, AT_LEAST_THREE;
        /// Beyond the paper, with `ransac.vote_by_tilt`: RANSAC's inliers must vote at least this much
        /// above the floor (a match on a wall adds about 1, on the road about 0): a consensus resting on
        /// the road alone cannot tell where the car went horizontally (an empty lot), and the prediction
        /// is taken instead.
        min_inlier_votes: f64 = 5.0, NON_NEGATIVE;
        /// Beyond the paper: a RANSAC motion further than this (m per frame; at 10 Hz a 3 g change of
        /// speed) from the constant-velocity prediction is a wrong consensus. The matches that agree
        /// with the prediction (within twice the RANSAC threshold) are solved instead when they are a
        /// consensus of their own — at least `min_inliers` and `guided_fraction` of RANSAC's —
        /// otherwise the prediction is taken.
        max_deviation: f64 = 0.3, LIMIT;
        /// The same for the rotation (° per frame).
        max_deviation_deg: f64 = 3.0, LIMIT;
        /// The agreeing matches' share of RANSAC's inliers that makes them a consensus of their own: a
        /// prediction measured from a wrong pair still finds a few agreeing matches (ground rings look
        /// stationary), and a true static scene outvoted by a passing car or a repeated facade is nearly
        /// as large.
        guided_fraction: f64 = 0.5, FRACTION;
        /// Beyond the paper: a pair spanning this many frames or more (scans missing between them) and a
        /// pair whose own motion would give way to the prediction (too few inliers, or implausible) are
        /// matched again from the prediction: the previous scan moved by it, projected again and matched
        /// in rounds (`large_motion.max_rounds`, `min_step`, `min_step_deg`), once started by the
        /// model's own window and once by the wide one (when the model has it), the more inliers
        /// winning. The re-matched motion is taken when it has more inliers than the pair's own, or when
        /// the pair's own would give way. Across missing scans the prediction alone errs by whatever the
        /// vehicle did meanwhile; re-matching measures it. null: never (the paper).
        rematch_gap: Option<u64> = Some(2), Rule::Optional(&AT_LEAST_ONE);
        /// Across more frames than this (2 s at 10 Hz: a paused log, a stop at a light while no scans
        /// came) the prediction is a guess: no motion is judged implausible against it, NDT does not
        /// start from it, and the wide window of the re-matching also starts from the large-motion
        /// starts (`large_motion.search_ahead_m`).
        prediction_horizon: u64 = 20, AT_LEAST_ONE;
        /// Beyond the paper: when the prediction moves the car further than this (m) since the
        /// reference scan, the near scene's flow leaves the network's window (highway speeds), so the
        /// pair is matched from the prediction at once — the reference moved by it, projected again and
        /// matched in rounds as above — instead of from the identity first. Below it, matching from the
        /// identity is the more accurate (a moved reference loses the cells it occludes). null: never.
        match_from_prediction_m: Option<f64> = Some(1.5), Rule::Optional(&POSITIVE);
        /// Matching rounds from the prediction at most (each projects, encodes and matches the moved
        /// reference again): the first carries the pair within the window, later ones refine while the
        /// correction exceeds `large_motion.min_step`. null: 1 with mapping, whose NDT takes out what a
        /// second round would, and 2 without.
        prediction_rounds: Option<u64> = None, Rule::Optional(&AT_LEAST_ONE);
        /// Beyond the paper: match from the prediction first by placing each coarse window where the
        /// prediction takes its block's points (the reference's own features, nothing encoded again);
        /// the rounds of the moved reference run only when that pair has too few inliers or a motion far
        /// from the prediction. null: with mapping only (its NDT takes out the centimetres by which
        /// frame-to-frame DMLO is better off with the moved reference's rounds); false: always the
        /// rounds.
        guided_windows: Option<bool> = None, Rule::Optional(&Rule::Flag);
        /// Beyond the paper: before a velocity is measured (the first pair, matched from the identity),
        /// the pair is also matched from the reference moved this far (m) ahead and behind along its x
        /// axis, one round each; a motion of its own there (`min_inliers`, `min_inlier_votes`) further
        /// than `max_deviation` from the frame's flags the frame (its diagnostics' `ambiguous_start`): a
        /// drive that starts at speed past evenly spaced posts can match an alias as well as the truth,
        /// and the chain would inherit it. The frame keeps its motion unless `start_max_reverse_m`
        /// prefers a start's. null: never.
        start_check_m: Option<f64> = Some(3.0), Rule::Optional(&POSITIVE);
        /// Beyond the paper: a flagged first pair (above) whose motion drives backwards along the
        /// sensor's x axis (the way KITTI's and the simulator's sensors face) further than this (m a
        /// frame) while a start's motion drives forward as far takes the forward motion (fallback
        /// `forward_start`): at highway speed the aliases of evenly spaced posts reverse while the truth
        /// drives forward, and no vehicle reverses at such speeds. null: the frame keeps its motion (a
        /// sensor mounted facing another way).
        start_max_reverse_m: Option<f64> = Some(0.5), Rule::Optional(&POSITIVE);
    }
}

settings! {
    /// Beyond the paper: motion compensation of every sweep before it is projected.
    ///
    /// A spinning sensor measures its columns one after the other while the vehicle moves (a 10 Hz
    /// sweep at 15 m/s ends 1.5 m from where it began); raw KITTI and most live sensors deliver such
    /// skewed sweeps. With `enabled`, every scan after the first measured motion is moved into the
    /// sensor frame of one moment — the one its pose refers to — by the constant-velocity prediction,
    /// before projection, matching and mapping. The points' times come from the scan's own point
    /// times, or else from the azimuth: a sensor turning `clockwise` seen from above (Velodyne, KITTI),
    /// the pose at the moment it looks at `reference_azimuth_deg` (0: forward, as KITTI and
    /// `dmlo simulate --motion-distortion`). Off by default: a sweep that is already one snapshot (the
    /// simulator's default ones, a driver's or a dataset's motion-compensated scans) would be skewed by
    /// it. Skewed sweeps left as they are suit the default `ransac.refit` ("ray_noise") worst, since it
    /// trusts each point's ray from one sensor origin.
    pub struct DeskewSection {
        /// Deskew the sweeps.
        enabled: bool = false, Rule::Flag;
        /// The sensor turns clockwise seen from above (Velodyne, KITTI).
        clockwise: bool = true, Rule::Flag;
        /// The azimuth (°) at whose moment the pose holds.
        reference_azimuth_deg: f64 = 0.0, FINITE;
    }
}

settings! {
    /// Scan-to-map NDT refinement of every pose over a local map of recent scans (§III-D-c), on by
    /// default: the network's matches bring each scan within NDT's basin with no initial guess, and NDT
    /// against many scans in one frame, fitting every point rather than a few hundred matches, takes out
    /// the error the matches leave and the drift that frame-to-frame estimates pile up. A consecutive
    /// pair registered on its own is refined against the reference scan alone. `enabled = false` is the
    /// paper's frame-to-frame DMLO.
    pub struct MappingSection {
        /// Refine every pose against the local map.
        enabled: bool = true, Rule::Flag;
        /// NDT voxel edge (m).
        voxel_size: f64 = 1.0, POSITIVE;
        /// Keyframes the local map keeps.
        max_scans: u64 = 10, AT_LEAST_ONE;
        /// A scan enters the map only once it moved this far (m) from the newest map scan …
        keyframe_distance: f64 = 2.0, LIMIT;
        /// … or turned this much (°); 0 and 0 put every scan in.
        keyframe_angle_deg: f64 = 5.0, LIMIT;
        /// Within this distance (m) of the newest keyframe the horizontal motion and heading come from
        /// the scan's upright surfaces alone: the ground rings sit at fixed ranges from the sensor, so
        /// the rings of a keyframe taken nearby lie where the scan's own would if the car stood still,
        /// and they hold a creeping car in place (a pair registered on its own that moved less is
        /// treated the same way); a car standing at the keyframe is aligned to it by point-to-plane ICP.
        /// 0 turns both off.
        ring_lock_distance: f64 = 0.5, LIMIT;
        /// When the DMLO pose is this far (m) from the constant-velocity prediction, NDT also starts from
        /// the prediction and the better-scoring alignment wins (a wrong RANSAC consensus is caught by
        /// the map) …
        motion_model_start_distance: f64 = 0.3, LIMIT;
        /// … or this much turned from it (°).
        motion_model_start_angle_deg: f64 = 1.5, LIMIT;
        /// Voxel (m) of the scan aligned to the map within `far_range` of the sensor; 0: every point.
        /// Near the sensor every surface is sampled densely and the nearest objects, often vehicles
        /// keeping pace, fill much of the scan: the coarser voxel keeps them from outweighing the static
        /// scene.
        downsample: f64 = 0.75, NON_NEGATIVE;
        /// The same beyond `far_range`: the finer voxel keeps the sparse far scene's structure (a far
        /// point's lever arm constrains rotation).
        downsample_far: f64 = 0.4, NON_NEGATIVE;
        /// Metres from the sensor where the far scene begins.
        far_range: f64 = 15.0, LIMIT;
        /// The height, roll and pitch come from a second, two-step NDT of the points within `far_range`
        /// and the far ones off upright surfaces (the ground, told by the slope to the next ring): seen
        /// from the keyframes behind, far walls, poles and trees tilt the scan nose-down a little every
        /// frame, and each keyframe would carry the tilt into the map (docs/measurements.md).
        level_without_far_upright: bool = true, Rule::Flag;
        /// Newton steps at most.
        max_iterations: u64 = 30, AT_LEAST_ONE;
        /// Translations with less than this fraction of the best-constrained translation's information
        /// keep the DMLO estimate instead of the map's pull; 0 turns the test off.
        degeneracy_threshold: f64 = 0.05, BELOW_ONE;
        /// The same for the rotations.
        rotation_degeneracy_threshold: f64 = 0.01, BELOW_ONE;
    }
}

settings! {
    /// Registration of two scans far apart with no initial guess (§IV-D), from several starts.
    ///
    /// The wide-window graph matches the pair, as in the paper. Beyond the paper, it does so from
    /// several starts — the reference scan moved as if the target lay `search_ahead_m` metres along the
    /// reference's x axis (a vehicle's heading; negative: behind) and turned by `search_yaw_deg` degrees
    /// (counter-clockwise seen from above), every combination — and the start whose matches have the
    /// most RANSAC inliers goes on. The wide window reaches a few metres of translation, so starts
    /// spaced within its reach cover a stretch of road ahead and behind; yaw starts 30° apart register
    /// loop closures at any heading, at 12 times the starts. Then the reference is moved by the estimate
    /// so far, projected again and matched again with the model's own (narrower, cheaper) window, until
    /// a round corrects less than both steps below; a round with fewer than `motion_model.min_inliers`
    /// inliers keeps the estimate before it. `search_ahead_m = [0]` and `max_rounds = 1` are the
    /// paper's single pass.
    pub struct LargeMotionSection {
        /// Starts along the reference's x axis (m).
        search_ahead_m: Vec<f64> = vec![0.0, -6.0, 6.0, -12.0, 12.0], Rule::FiniteList;
        /// Starts turned about the vertical (°).
        search_yaw_deg: Vec<f64> = vec![0.0], Rule::FiniteList;
        /// Matching rounds from the best start at most, the wide pass included.
        max_rounds: u64 = 4, AT_LEAST_ONE;
        /// A round correcting less than this (m) …
        min_step: f64 = 0.05, LIMIT;
        /// … and this (°) ends the rounds.
        min_step_deg: f64 = 0.1, LIMIT;
    }
}

settings! {
    /// Points on moving objects when no labels say which they are: the moving-object network beside the
    /// model (`moving.onnx`) predicts them, cell by cell of the scan's cylinder image, and they are left
    /// out of matching and of the map like labelled moving points. `detect = false` keeps every point not
    /// labelled moving; a model without the network keeps every point.
    pub struct MovingObjectsSection {
        /// Run the network (when the model has it).
        detect: bool = true, Rule::Flag;
        /// A cell's moving probability above this drops its points.
        threshold: f64 = 0.5, OPEN_FRACTION;
    }
}

/// Where the network's correlation and window decoding run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MatchingStage {
    /// The crate when the network runs on a CPU and the model allows it, else the graph.
    #[default]
    Auto,
    /// The crate's matching stage on cached features: on a CPU it computes each window directly instead
    /// of through the graph's gathered tensors.
    Crate,
    /// Inside the exported ONNX graph (e.g. on a GPU).
    Graph,
}

impl Named for MatchingStage {
    const NAMES: &'static [(Self, &'static str)] = &[
        (MatchingStage::Auto, "auto"),
        (MatchingStage::Crate, "crate"),
        (MatchingStage::Graph, "graph"),
    ];
}

const MATCHING_STAGES: [&str; 3] = names(MatchingStage::NAMES);

/// The scans' reflectance scale.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ReflectanceScale {
    /// Decided from the first scan's values.
    #[default]
    Auto,
    /// Already in [0, 1].
    Unit,
    /// 0 to 255.
    ZeroTo255,
    /// 0 to 65535.
    ZeroTo65535,
    /// Not used: the range-only model runs.
    Ignored,
}

impl Named for ReflectanceScale {
    const NAMES: &'static [(Self, &'static str)] = &[
        (ReflectanceScale::Auto, "auto"),
        (ReflectanceScale::Unit, "unit"),
        (ReflectanceScale::ZeroTo255, "0-255"),
        (ReflectanceScale::ZeroTo65535, "0-65535"),
        (ReflectanceScale::Ignored, "none"),
    ];
}

const REFLECTANCE_SCALES: [&str; 5] = names(ReflectanceScale::NAMES);

settings! {
    /// Every setting of the odometry (module docs); `Default` is `dmlo run`'s.
    pub struct OdometryConfig {
        [
            matching: MatchingSection,
            ransac: RansacSection,
            motion_model: MotionModelSection,
            deskew: DeskewSection,
            mapping: MappingSection,
            large_motion: LargeMotionSection,
            moving_objects: MovingObjectsSection,
        ]
        /// The network's (and the crate's matching stage's) threads; 0 lets them choose. More than the
        /// machine's cores are bounded to them, with a warning.
        threads: u64 = 0, COUNT;
        /// Where the network's correlation and window decoding run: "crate" (the crate, on cached
        /// features: on a CPU it computes each window directly instead of through the graph's gathered
        /// tensors), "graph" (inside the ONNX graph, e.g. on a GPU), "auto": the crate when the network
        /// runs on the CPU and the model allows it.
        matching_stage: MatchingStage = MatchingStage::Auto, Rule::Choice(&MATCHING_STAGES);
        /// Scans with fewer finite points are bridged by the motion model.
        min_points: u64 = 1000, COUNT;
        /// The scans' reflectance scale: "auto" decides from the first scan's values (max ≤ 1: [0, 1];
        /// ≤ 255: 0–255; ≤ 65535: 0–65535; absent, one value everywhere or none of these: no usable
        /// reflectance); "unit", "0-255", "0-65535" say it; "none" ignores it. Without usable
        /// reflectance the range-only model beside the model runs (`range_only/`).
        reflectance: ReflectanceScale = ReflectanceScale::Auto, Rule::Choice(&REFLECTANCE_SCALES);
    }
}

/// The sections of the config: their keys, their settings and their docs, in declaration order.
const SECTIONS: [(&str, &[Setting], &str); 7] = [
    ("matching", MatchingSection::SETTINGS, MatchingSection::DOC),
    ("ransac", RansacSection::SETTINGS, RansacSection::DOC),
    (
        "motion_model",
        MotionModelSection::SETTINGS,
        MotionModelSection::DOC,
    ),
    ("deskew", DeskewSection::SETTINGS, DeskewSection::DOC),
    ("mapping", MappingSection::SETTINGS, MappingSection::DOC),
    (
        "large_motion",
        LargeMotionSection::SETTINGS,
        LargeMotionSection::DOC,
    ),
    (
        "moving_objects",
        MovingObjectsSection::SETTINGS,
        MovingObjectsSection::DOC,
    ),
];

impl OdometryConfig {
    /// The config a JSON text describes (Python's `Infinity` read as no limit), every key left out at its
    /// default. [`Error::Config`] names every bad key, in one message.
    pub fn from_json(text: &str) -> Result<Self> {
        let value: Value = serde_json::from_str(&json::quote_non_finite_tokens(text))
            .map_err(|e| Error::Config(format!("config: not JSON: {e}")))?;
        Self::from_value(&value)
    }

    /// [`Self::from_json`] of a file (`dmlo run`'s `config.json`); errors name the file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path)
            .map_err(|e| Error::Config(format!("{}: {e}", path.display())))?;
        Self::from_json(&text).map_err(|e| match e {
            Error::Config(message) => Error::Config(format!("{}: {message}", path.display())),
            other => other,
        })
    }

    /// The config as JSON, every key with its value, unlimited settings written as Python's `json` writes
    /// them (`Infinity`), so that either language reads it back.
    pub fn to_json(&self) -> String {
        let text = serde_json::to_string_pretty(&Value::Object(self.to_values()))
            .unwrap_or_else(|_| "{}".into());
        json::with_tokens(text)
    }

    /// Checks every setting as it is now (fields may have been set in code); the error names every bad
    /// key, as [`Self::from_json`]'s does.
    pub fn validate(&self) -> Result<()> {
        let errors = config_errors(&Value::Object(self.to_values()));
        if errors.is_empty() {
            Ok(())
        } else {
            Err(Error::Config(errors.join("; ")))
        }
    }

    /// The schema as JSON: each section's key, doc and settings, then the top-level settings; each setting's
    /// key, type (`bool`, `int`, `float`, `str`, `list[float]`), whether null is allowed, the names a `str`
    /// takes, its rule in words, its default and its doc. What `dmlo`'s Python classes are made from.
    pub fn schema_json() -> String {
        let defaults = Value::Object(Self::default().to_values());
        let describe = |settings: &[Setting], defaults: &Value| -> Value {
            Value::Array(
                settings
                    .iter()
                    .map(|s| {
                        let mut entry = Map::new();
                        entry.insert("key".into(), s.key.into());
                        entry.insert("type".into(), s.rule.value_type().into());
                        entry.insert(
                            "optional".into(),
                            matches!(s.rule, Rule::Optional(_)).into(),
                        );
                        if let Rule::Choice(names) = s.rule {
                            entry.insert("choices".into(), names.to_vec().into());
                        }
                        entry.insert("rule".into(), s.rule.describe(&Value::Null).into());
                        entry.insert("default".into(), defaults[s.key].clone());
                        entry.insert("doc".into(), doc_text(s.doc).into());
                        Value::Object(entry)
                    })
                    .collect(),
            )
        };
        let sections: Vec<Value> = SECTIONS
            .iter()
            .map(|(key, settings, doc)| {
                serde_json::json!({
                    "key": key,
                    "doc": doc_text(doc),
                    "settings": describe(settings, &defaults[*key]),
                })
            })
            .collect();
        let schema = serde_json::json!({
            "sections": sections,
            "settings": describe(Self::SETTINGS, &defaults),
        });
        json::with_tokens(serde_json::to_string_pretty(&schema).unwrap_or_else(|_| "{}".into()))
    }

    /// The config of a JSON value (non-finite numbers marked), checked.
    fn from_value(value: &Value) -> Result<Self> {
        let errors = config_errors(value);
        if !errors.is_empty() {
            return Err(Error::Config(errors.join("; ")));
        }
        let Value::Object(values) = value else {
            return Err(Error::Config(
                "config: must be a mapping of settings".into(),
            ));
        };
        Self::from_values(values, "")
            .map_err(|key| Error::Config(format!("{key}: a checked value its field cannot hold")))
    }

    /// The pair's back end ([`crate::pair::match_pair`]) as this config sets it.
    pub fn pair_config(&self) -> PairConfig {
        let (m, r) = (&self.matching, &self.ransac);
        PairConfig {
            min_confidence: m.min_confidence as f32,
            nms_radius: m.nms_radius as usize,
            max_matches: m.max_matches as usize,
            coherence: m.coherence_px.map(|scale_px| CoherenceConfig {
                radius: m.coherence_radius as usize,
                scale_px: scale_px as f32,
            }),
            ransac: RansacConfig {
                threshold: r.threshold,
                confidence: r.confidence,
                max_iterations: r.max_iterations as usize,
                seed: r.seed,
                refit: self.refit(),
                ..Default::default()
            },
            tilt_vote_floor: r.vote_by_tilt.then_some(r.min_vote),
            vote_voxel: r.vote_voxel,
        }
    }

    /// The refit RANSAC and the motion model's guided consensus solve with.
    pub fn refit(&self) -> Refit {
        match self.ransac.refit {
            RefitKind::PointToPoint => Refit::PointToPoint,
            RefitKind::RayNoise => Refit::RayNoise {
                noise: RayNoise {
                    range_ratio: self.ransac.ray_range_ratio,
                    ..Default::default()
                },
                bearing_threshold_deg: self.ransac.ray_bearing_threshold_deg,
            },
        }
    }

    /// The motion model's limits ([`crate::odometry::motion::MotionModel`]).
    pub fn motion_limits(&self) -> MotionLimits {
        let m = &self.motion_model;
        MotionLimits {
            min_inliers: m.min_inliers as usize,
            min_inlier_votes: m.min_inlier_votes,
            max_deviation: m.max_deviation,
            max_deviation_deg: m.max_deviation_deg,
            guided_fraction: m.guided_fraction,
            prediction_horizon: m.prediction_horizon as usize,
            threshold: self.ransac.threshold,
            refit: self.refit(),
        }
    }

    /// The local map's settings ([`crate::odometry::mapping::LocalMap`]).
    pub fn mapping_config(&self) -> MappingConfig {
        let p = &self.mapping;
        MappingConfig {
            voxel_size: p.voxel_size,
            max_scans: p.max_scans as usize,
            keyframe_distance: p.keyframe_distance,
            keyframe_angle_deg: p.keyframe_angle_deg,
            ring_lock_distance: p.ring_lock_distance,
            motion_model_start_distance: p.motion_model_start_distance,
            motion_model_start_angle_deg: p.motion_model_start_angle_deg,
            downsample: p.downsample,
            downsample_far: p.downsample_far,
            far_range: p.far_range,
            level_without_far_upright: p.level_without_far_upright,
            max_iterations: p.max_iterations as usize,
            degeneracy_threshold: p.degeneracy_threshold,
            rotation_degeneracy_threshold: p.rotation_degeneracy_threshold,
        }
    }

    /// Whether pairs matched from the prediction place their coarse windows by it first: the setting, or
    /// with mapping only (its NDT takes out the decimetres that the moved reference's rounds would spare
    /// frame-to-frame DMLO).
    pub fn guided_windows(&self) -> bool {
        self.motion_model
            .guided_windows
            .unwrap_or(self.mapping.enabled)
    }

    /// Matching rounds from the prediction: the setting, or 1 with mapping and 2 without.
    pub fn prediction_rounds(&self) -> usize {
        match self.motion_model.prediction_rounds {
            Some(rounds) => rounds as usize,
            None if self.mapping.enabled => 1,
            None => 2,
        }
    }
}

/// The messages of every bad key of a config's JSON value, in declaration order.
fn config_errors(value: &Value) -> Vec<String> {
    let Value::Object(values) = value else {
        return vec![format!(
            "config: must be a mapping of settings, got {}",
            schema::shown(value)
        )];
    };
    let mut errors = Vec::new();
    for (key, settings, _) in SECTIONS {
        match values.get(key) {
            None => {}
            Some(Value::Object(section)) => {
                schema::section_errors(&format!("{key}."), section, settings, &[], &mut errors)
            }
            Some(other) => errors.push(format!(
                "{key}: must be a mapping of settings, got {}",
                schema::shown(other)
            )),
        }
    }
    let section_keys: Vec<&str> = SECTIONS.iter().map(|(key, _, _)| *key).collect();
    schema::section_errors(
        "",
        values,
        OdometryConfig::SETTINGS,
        &section_keys,
        &mut errors,
    );
    errors
}

/// A doc comment's lines as one text: the leading space of each line dropped, paragraphs kept.
fn doc_text(doc: &str) -> String {
    doc.lines()
        .map(|line| line.strip_prefix(' ').unwrap_or(line))
        .collect::<Vec<_>>()
        .join("\n")
        .trim()
        .to_string()
}

#[cfg(test)]
mod tests;
