#![forbid(unsafe_code)]
//! [`Odometry`]: DMLO's per-frame state machine in the crate (paper §III), over any [`FrameMatcher`] —
//! the learned matcher of `dmlo_rs::inference` (feature `inference`, no Python), or a runtime of the
//! caller's own.
//!
//! Every scan is projected onto the cylinder image (Eq. 1), encoded, and matched against the previous
//! scan's cached features (§III-C); the pair's back end ([`crate::pair::match_pair`]) turns the flow
//! into a motion (§III-D), which the motion model judges ([`super::motion`], §III-D-c) and the local
//! map refines by NDT ([`super::mapping`]); the motions chain into `T_world_lidar` poses, the first scan
//! being the world. The steps and their settings are `dmlo.Odometry`'s, read from the same config
//! ([`super::config`]). Beyond the paper, as in Python: pairs whose predicted motion outgrows the
//! network's window are matched from the prediction, and pairs across missing scans (or whose own
//! motion gives way) are matched again from it.
//! [`Odometry::register_pair`] registers two scans with no drive around them (`dmlo register`).
//!
//! Refused by [`Odometry::new`]: a `matching_stage` the matcher does not run
//! ([`FrameMatcher::runs_matching_stage`]). The moving-object network is not
//! run by the crate: every point not masked by the caller is kept (as `dmlo.Odometry` does with a model
//! folder without `moving.onnx`). Re-matching tries the wide window when the matcher has one
//! ([`FrameMatcher::has_wide_window`]). Scans without usable reflectance switch to the range-only model
//! ([`Odometry::with_range_only`]).
//!
//! A matcher is any type with the four required methods. Here a stand-in for the network, under which
//! every cell stays where it is, registers a scan of a room three times: the sensor stood still.
//! `dmlo_rs::inference::LearnedMatcher` (features `inference` / `onnxruntime`) is the real one.
//!
//! ```
//! use dmlo_rs::dense_match::DenseFlow;
//! use dmlo_rs::odometry::config::OdometryConfig;
//! use dmlo_rs::odometry::pipeline::{FrameMatcher, Odometry, Scan};
//! use dmlo_rs::projection::CylinderConfig;
//!
//! struct StandingStill(CylinderConfig);
//!
//! impl FrameMatcher for StandingStill {
//!     type Features = ();
//!     fn cylinder(&self) -> &CylinderConfig {
//!         &self.0
//!     }
//!     fn encode(&self, _image: &[f32]) -> dmlo_rs::Result<()> {
//!         Ok(())
//!     }
//!     fn flow(&self, _reference: &(), _target: &()) -> dmlo_rs::Result<DenseFlow> {
//!         let (height, width) = (self.0.height, self.0.width);
//!         Ok(DenseFlow {
//!             flow: vec![0.0; 2 * height * width],
//!             confidence: vec![1.0; height * width],
//!             height,
//!             width,
//!         })
//!     }
//! }
//!
//! # fn main() -> dmlo_rs::Result<()> {
//! // A room of 20 × 16 m seen from 1.7 m above its floor: x, y, z and reflectance (0–1) of each point.
//! let mut points: Vec<[f32; 4]> = Vec::new();
//! for step in 0..400 {
//!     let along = -10.0 + step as f32 * 0.05;
//!     for height in 0..12 {
//!         let z = -1.6 + height as f32 * 0.3;
//!         points.push([along, 8.0, z, 0.4]);
//!         points.push([along, -8.0, z, 0.6]);
//!         points.push([10.0, along * 0.8, z, 0.5]);
//!         points.push([-10.0, along * 0.8, z, 0.3]);
//!     }
//!     for across in 0..8 {
//!         points.push([along * 0.9, -7.0 + across as f32 * 2.0, -1.7, 0.2]);
//!     }
//! }
//! let mut odometry = Odometry::new(StandingStill(CylinderConfig::kitti()), OdometryConfig::default())?;
//! for _ in 0..3 {
//!     let pose = odometry.register(Scan::new(&points))?; // T_world_lidar, the first scan the world
//!     assert!(pose.fixed_view::<3, 1>(0, 3).norm() < 0.01);
//! }
//! assert_eq!(odometry.diagnostics().len(), 3);
//! # Ok(())
//! # }
//! ```

use std::collections::BTreeMap;
use std::time::Instant;

use nalgebra::{Matrix4, Point3};
use serde::Serialize;

use crate::dense_match::DenseFlow;
use crate::deskew::{deskew, sweep_times, SweepPattern};
use crate::error::{Error, Result};
use crate::odometry::clock::FrameClock;
use crate::odometry::config::{MatchingStage, OdometryConfig, ReflectanceScale};
use crate::odometry::mapping::LocalMap;
use crate::odometry::motion::{
    midpoint_motion, pose_difference, rigid_inverse, MotionModel, PairEvidence,
};
use crate::pair::{match_pair, PairConfig, PairImages, PairMotion};
use crate::projection::{project, CylinderConfig};
use crate::rigid::isometry_from_matrix;

/// The network as the odometry runs it: scans' images encoded once (features cached, a scan being the
/// target of one pair and the reference of the next), and the dense flow between two encoded scans.
pub trait FrameMatcher {
    /// One scan's encoding.
    type Features;
    /// The cylinder image the model takes.
    fn cylinder(&self) -> &CylinderConfig;
    /// Whether the model reads the reflectance channel (false: a range-only model).
    fn uses_reflectance(&self) -> bool {
        true
    }
    /// Encodes a `(2, H, W)` channel-major image: range (m), then reflectance in [0, 1]; 0 where empty.
    fn encode(&self, image: &[f32]) -> Result<Self::Features>;
    /// The flow of every `reference` cell into `target` and its confidence (§III-C).
    fn flow(&self, reference: &Self::Features, target: &Self::Features) -> Result<DenseFlow>;
    /// Whether the matcher runs its matching stage as the config's `matching_stage` asks: by default the
    /// crate's (`auto`, `crate`), not an exported matching graph (`graph`).
    fn runs_matching_stage(&self, stage: MatchingStage) -> bool {
        stage != MatchingStage::Graph
    }
    /// Whether a wide-window matcher is at hand (the model's `frame_wide.onnx`: the same weights, a wider
    /// coarse window) for pairs re-matched from the prediction, whose flow may exceed the model's window.
    fn has_wide_window(&self) -> bool {
        false
    }
    /// The wide window's flow of `reference` into `target` (its features, and its `(2, H, W)` image for a
    /// matcher whose wide window encodes the scan itself).
    fn wide_flow(
        &self,
        reference: &Self::Features,
        target: &Self::Features,
        target_image: &[f32],
    ) -> Result<DenseFlow> {
        let _ = (reference, target, target_image);
        Err(Error::Model("the matcher has no wide window".into()))
    }
}

/// One scan given to [`Odometry::register`].
#[derive(Debug, Clone, Copy)]
pub struct Scan<'a> {
    /// `x, y, z, reflectance` in the sensor frame; non-finite points are left out.
    pub points: &'a [[f32; 4]],
    /// Points on moving objects (one per point), left out of matching and of the map.
    pub moving: Option<&'a [bool]>,
    /// The scan's time (any increasing unit): scans the sensor dropped are counted from it.
    pub timestamp: Option<f64>,
    /// With `deskew.enabled`: when each point was measured, in sensor periods, 0 at the moment the pose
    /// refers to (e.g. −0.5…0.5 over a sweep centred on it); `None`: from each point's azimuth.
    pub point_times: Option<&'a [f64]>,
}

impl<'a> Scan<'a> {
    /// A scan with no mask and no timestamp.
    pub fn new(points: &'a [[f32; 4]]) -> Self {
        Scan {
            points,
            moving: None,
            timestamp: None,
            point_times: None,
        }
    }
}

/// What happened to one scan, as `dmlo.Odometry`'s `FrameDiagnostics` (the same keys in
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
    /// The fallback taken (`constant_velocity`, `degenerate_scene`, `guided_consensus`,
    /// `implausible_motion`, `rematched_from_prediction`, `too_few_points`, `unreadable_scan`).
    pub fallback: Option<String>,
    /// Rounds of matching from the prediction whose motion was taken (0: tried, none kept).
    pub rematch_rounds: Option<usize>,
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
    /// Points the moving-object network left out; `None` when it did not run (the crate runs none: a
    /// caller's flags come in [`Scan::moving`]).
    pub num_moving_predicted: Option<usize>,
    /// Fraction of the cylinder image's cells holding a point.
    #[serde(serialize_with = "rounded_option::<4, _>")]
    pub image_fill: Option<f64>,
    /// With `deskew.enabled`: the sweep was motion-compensated.
    pub deskewed: bool,
    /// Milliseconds per stage.
    #[serde(serialize_with = "rounded_map::<3, _>")]
    pub timings_ms: BTreeMap<String, f64>,
}

/// `value` to `DIGITS` decimals, as `dmlo.Odometry`'s diagnostics write it.
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
    fn count_matches(&mut self, pair: &Matched) {
        self.num_matches = pair.motion.source.len();
        self.num_inliers = pair.motion.num_inliers;
        self.inlier_ratio = if self.num_matches > 0 {
            self.num_inliers as f64 / self.num_matches as f64
        } else {
            0.0
        };
    }
}

/// A pair's motion in the frames of the scans given, and the matching rounds it took.
struct Matched {
    motion: PairMotion,
    transform: Matrix4<f64>,
    rounds: usize,
}

impl Matched {
    fn new(motion: PairMotion) -> Self {
        let transform = motion.transform.to_homogeneous();
        Matched {
            motion,
            transform,
            rounds: 1,
        }
    }
}

/// The last usable scan, matched against the next one.
struct Reference<F> {
    cloud: Vec<[f32; 4]>,
    /// Its points' sweep times, when given.
    times: Option<Vec<f64>>,
    /// Its sweep was deskewed.
    deskewed: bool,
    range: Vec<f32>,
    points: Vec<f32>,
    features: F,
    pose: Matrix4<f64>,
    frame: u64,
}

/// A scan projected: the network's `(2, H, W)` image, its range image and its point image `(H, W, 3)`
/// (each cell's kept point, NaN where empty).
struct Projected {
    image: Vec<f32>,
    range: Vec<f32>,
    points: Vec<f32>,
}

/// DMLO odometry (module docs).
pub struct Odometry<M: FrameMatcher> {
    matcher: M,
    config: OdometryConfig,
    pair_config: PairConfig,
    cylinder: CylinderConfig,
    motion: MotionModel,
    map: Option<LocalMap>,
    clock: FrameClock,
    reference: Option<Reference<M::Features>>,
    pose_frame: Option<u64>,
    poses: Vec<Matrix4<f64>>,
    diagnostics: Vec<FrameDiagnostics>,
    reflectance: Option<ReflectanceScale>,
    /// The range-only model, run from the first scan without usable reflectance on.
    range_only: Option<M>,
    /// Scans without usable reflectance and no range-only model run the model on zeros (not refused).
    zero_reflectance_allowed: bool,
}

impl<M: FrameMatcher> Odometry<M> {
    /// An odometry running `matcher` with `config` (checked whole; settings the crate does not run yet
    /// are refused, naming them).
    pub fn new(matcher: M, config: OdometryConfig) -> Result<Self> {
        config.validate()?;
        if !matcher.runs_matching_stage(config.matching_stage) {
            return Err(Error::Config(format!(
                "matching_stage: {}: not how this matcher matches (dmlo.Odometry in Python runs the graph stage)",
                serde_json::to_string(&config.matching_stage).unwrap_or_default()
            )));
        }
        let cylinder = *matcher.cylinder();
        let map = if config.mapping.enabled {
            Some(LocalMap::new(config.mapping_config())?)
        } else {
            None
        };
        let limits = config.motion_limits();
        limits.validate()?;
        Ok(Odometry {
            pair_config: config.pair_config(),
            motion: MotionModel::new(limits),
            matcher,
            config,
            cylinder,
            map,
            clock: FrameClock::new(),
            reference: None,
            pose_frame: None,
            poses: Vec::new(),
            diagnostics: Vec::new(),
            reflectance: None,
            range_only: None,
            zero_reflectance_allowed: false,
        })
    }

    /// The odometry with a range-only model beside the matcher (the bundled model's `range_only/`): from
    /// the first scan without usable reflectance on it runs instead, the reference scan encoded again by
    /// it (without one such a scan is an error: a model that reads reflectance cannot run on zeros).
    pub fn with_range_only(mut self, range_only: M) -> Result<Self> {
        if range_only.uses_reflectance() {
            return Err(Error::invalid(
                "range_only",
                "reads the reflectance channel: not a range-only model",
            ));
        }
        if range_only.cylinder() != self.matcher.cylinder() {
            return Err(Error::invalid(
                "range_only",
                "its cylinder image differs from the model's",
            ));
        }
        if self.matcher.uses_reflectance() {
            self.range_only = Some(range_only);
        }
        Ok(self)
    }

    /// The odometry running its model on zero reflectance for scans without usable reflectance when there
    /// is no range-only model, instead of refusing them: the model never saw such images, so its poses
    /// cannot be trusted, and the caller should say so (`dmlo.Odometry` warns). For a model trained with
    /// reflectance, and for tools that must run on whatever a user gives them.
    pub fn allowing_zero_reflectance(mut self) -> Self {
        self.zero_reflectance_allowed = true;
        self
    }

    /// The matcher it runs.
    pub fn matcher(&self) -> &M {
        &self.matcher
    }

    /// The config it runs with.
    pub fn config(&self) -> &OdometryConfig {
        &self.config
    }

    /// Every pose so far, `T_world_lidar` (the first scan is the world).
    pub fn poses(&self) -> &[Matrix4<f64>] {
        &self.poses
    }

    /// What happened to every scan so far.
    pub fn diagnostics(&self) -> &[FrameDiagnostics] {
        &self.diagnostics
    }

    /// The reflectance scale chosen on the first scan ([`ReflectanceScale::Ignored`]: none used).
    pub fn reflectance_scale(&self) -> Option<ReflectanceScale> {
        self.reflectance
    }

    /// Adds the next scan and returns its pose `T_world_lidar`. A scan with fewer than `min_points`
    /// finite points (after the moving ones) is not matched: its pose comes from the motion model and its
    /// diagnostics say so. Errors name a bad argument (a mask of the wrong length, a non-finite timestamp,
    /// reflectance the model cannot use); the odometry's state is then as before the call, apart from
    /// the clock of a scan whose error came from the matcher.
    pub fn register(&mut self, scan: Scan<'_>) -> Result<Matrix4<f64>> {
        let KeptPoints {
            keep,
            kept,
            finite_reflectance,
        } = kept_points(&scan)?;
        check_one_per_point(scan.point_times, "point_times", "time", scan.points.len())?;
        let times = scan.point_times.map(|times| kept_rows(times, &keep));
        let min_points = self.config.min_points as usize;
        let scale = self.reflectance_for(&finite_reflectance, min_points)?;
        let tick = self.clock.advance(scan.timestamp)?;
        let mut diagnostics = FrameDiagnostics {
            index: self.poses.len(),
            num_points: scan.points.len(),
            ..Default::default()
        };
        if kept.len() < min_points {
            return Ok(self.skip(diagnostics, "too_few_points"));
        }
        let mut cloud = normalised(kept, scale.unwrap_or(ReflectanceScale::Unit));
        let deskewed = self.config.deskew.enabled && self.motion.is_measured();
        if deskewed {
            let start = Instant::now();
            cloud = self.deskewed(&cloud, times.as_deref())?;
            self.deskew_reference()?;
            let ms = start.elapsed().as_secs_f64() * 1e3;
            diagnostics.timings_ms.insert("deskew".into(), ms);
            diagnostics.deskewed = true;
        }
        let mut watch = Stopwatch::new();
        let projected = self.project(&cloud)?;
        let filled = projected.range.iter().filter(|&&r| r > 0.0).count();
        diagnostics.image_fill = Some(filled as f64 / projected.range.len() as f64);
        let features = self.matcher.encode(&projected.image)?;
        watch.lap("network", &mut diagnostics);
        let previous = self.reference.take();
        let pose = match self.pose_of(
            previous.as_ref(),
            &cloud,
            &projected,
            &features,
            tick.frame,
            &mut diagnostics,
            &mut watch,
        ) {
            Ok(pose) => pose,
            Err(e) => {
                self.reference = previous;
                return Err(e);
            }
        };
        if let Some(map) = &mut self.map {
            let keyframe = map.is_keyframe(&pose);
            diagnostics.map_keyframe = Some(keyframe);
            if keyframe {
                map.insert(&as_points(&cloud), &pose, &projected.points)?;
            }
            watch.lap("map_update", &mut diagnostics);
        }
        self.reference = Some(Reference {
            cloud,
            times,
            deskewed,
            range: projected.range,
            points: projected.points,
            features,
            pose,
            frame: tick.frame,
        });
        Ok(self.record(pose, tick.frame, diagnostics))
    }

    /// The pose of the scan at `frame` matched against `previous` (none: the first scan), refined by the map.
    #[allow(clippy::too_many_arguments)]
    fn pose_of(
        &mut self,
        previous: Option<&Reference<M::Features>>,
        cloud: &[[f32; 4]],
        projected: &Projected,
        features: &M::Features,
        frame: u64,
        diagnostics: &mut FrameDiagnostics,
        watch: &mut Stopwatch,
    ) -> Result<Matrix4<f64>> {
        let Some(previous) = previous else {
            return Ok(self.predict(frame));
        };
        let gap = (frame - previous.frame) as usize;
        let motion =
            self.motion_from_flow(previous, projected, features, gap, diagnostics, watch)?;
        let mut pose = previous.pose * rigid_inverse(&motion);
        if self.map.is_some() {
            pose =
                self.refine_with_map(cloud, &projected.points, &pose, gap, frame, diagnostics)?;
            watch.lap("ndt", diagnostics);
        }
        self.motion.update(&previous.pose, &pose, gap);
        Ok(pose)
    }

    /// Records a scan that could not be read: its pose comes from the motion model (`reason` in its
    /// diagnostics, e.g. "unreadable_scan").
    pub fn predict_skipped(&mut self, reason: &str) -> Result<Matrix4<f64>> {
        self.clock.advance(None)?;
        let diagnostics = FrameDiagnostics {
            index: self.poses.len(),
            ..Default::default()
        };
        Ok(self.skip(diagnostics, reason))
    }

    fn skip(&mut self, mut diagnostics: FrameDiagnostics, reason: &str) -> Matrix4<f64> {
        let frame = self.clock.frame().unwrap_or(0);
        diagnostics.fallback = Some(reason.to_string());
        let pose = self.predict(frame);
        self.record(pose, frame, diagnostics)
    }

    fn record(
        &mut self,
        pose: Matrix4<f64>,
        frame: u64,
        diagnostics: FrameDiagnostics,
    ) -> Matrix4<f64> {
        self.pose_frame = Some(frame);
        self.poses.push(pose);
        self.diagnostics.push(diagnostics);
        pose
    }

    /// The constant-velocity pose of the scan at `frame`; the first scan defines the world.
    fn predict(&self, frame: u64) -> Matrix4<f64> {
        match (self.poses.last(), self.pose_frame) {
            (Some(last), Some(pose_frame)) => {
                let frames = frame.saturating_sub(pose_frame) as usize;
                last * rigid_inverse(&self.motion.predicted(frames))
            }
            _ => Matrix4::identity(),
        }
    }

    /// The reflectance scale of the sequence, chosen on the first scan with `min_points` finite points
    /// (`finite`: their reflectance; `None` before it); errors when the scans have no reflectance the
    /// model can use.
    fn reflectance_for(
        &mut self,
        finite: &[f32],
        min_points: usize,
    ) -> Result<Option<ReflectanceScale>> {
        if finite.len() < min_points {
            // Not matched (too few points): it decides nothing, and its reflectance is never read.
            return Ok(self.reflectance);
        }
        let detected = detect_reflectance(finite);
        let choice = match self.reflectance {
            Some(chosen) => {
                if chosen != ReflectanceScale::Ignored && detected.0 == ReflectanceScale::Ignored {
                    self.switch_to_range_only(&detected.1)?;
                    self.reflectance = Some(ReflectanceScale::Ignored);
                    return Ok(self.reflectance);
                }
                return Ok(Some(chosen));
            }
            None if !self.matcher.uses_reflectance() => ReflectanceScale::Ignored,
            None => match (self.config.reflectance, detected.0) {
                (ReflectanceScale::Auto, scale) | (_, scale @ ReflectanceScale::Ignored) => scale,
                (setting, _) => setting,
            },
        };
        if choice == ReflectanceScale::Ignored && self.matcher.uses_reflectance() {
            let why = if self.config.reflectance == ReflectanceScale::Ignored {
                "the config says reflectance none".to_string()
            } else {
                detected.1
            };
            self.switch_to_range_only(&why)?;
        }
        self.reflectance = Some(choice);
        Ok(Some(choice))
    }

    /// Runs the range-only model from now on, the reference scan encoded again by it; an error naming
    /// `why` when there is none.
    fn switch_to_range_only(&mut self, why: &str) -> Result<()> {
        let Some(range_only) = self.range_only.take() else {
            if self.zero_reflectance_allowed {
                return Ok(());
            }
            return Err(self.no_reflectance(why));
        };
        if let Some(reference) = &self.reference {
            match self
                .project(&reference.cloud)
                .and_then(|p| range_only.encode(&p.image))
            {
                Ok(features) => self.reference.as_mut().expect("checked").features = features,
                Err(e) => {
                    self.range_only = Some(range_only);
                    return Err(e);
                }
            }
        }
        self.matcher = range_only;
        Ok(())
    }

    fn no_reflectance(&self, why: &str) -> Error {
        Error::invalid(
            "points",
            format!(
                "{why}, and the model reads reflectance: give the range-only model beside it \
                 (range_only/) to Odometry::with_range_only"
            ),
        )
    }

    /// The sweep moved into the sensor frame of its pose's moment by the per-frame velocity: the
    /// sensor's motion over one period is the inverse of `T_tgt_ref` (a sweep lasts one period however
    /// many scans went missing before it).
    fn deskewed(&self, cloud: &[[f32; 4]], times: Option<&[f64]>) -> Result<Vec<[f32; 4]>> {
        let d = &self.config.deskew;
        let pattern = SweepPattern {
            clockwise: d.clockwise,
            reference_azimuth_deg: d.reference_azimuth_deg,
        };
        let flat: &[f32] = cloud.as_flattened();
        let derived;
        let times = match times {
            Some(times) => times,
            None => {
                derived = sweep_times(flat, 4, &pattern)?;
                &derived[..]
            }
        };
        let motion = isometry_from_matrix(&rigid_inverse(self.motion.velocity()), "velocity")?;
        let moved = deskew(flat, 4, times, &motion)?;
        Ok(moved
            .chunks_exact(4)
            .map(|p| [p[0], p[1], p[2], p[3]])
            .collect())
    }

    /// The first deskewed scan's reference, measured before any velocity was, deskewed too (its own
    /// motion is the velocity just measured) and encoded again: a skewed scan matched against a deskewed
    /// one loses the skew's cancellation between two sweeps of the same motion, and with mapping the map
    /// then holds only deskewed scans.
    fn deskew_reference(&mut self) -> Result<()> {
        let Some(reference) = self.reference.as_ref().filter(|r| !r.deskewed) else {
            return Ok(());
        };
        let cloud = self.deskewed(&reference.cloud, reference.times.as_deref())?;
        let projected = self.project(&cloud)?;
        let features = self.matcher.encode(&projected.image)?;
        let reference = self.reference.as_mut().expect("checked above");
        if let Some(map) = &mut self.map {
            map.restart(&as_points(&cloud), &reference.pose, &projected.points)?;
        }
        reference.cloud = cloud;
        reference.range = projected.range;
        reference.points = projected.points;
        reference.features = features;
        reference.deskewed = true;
        Ok(())
    }

    /// The network input, range image and point image of a scan (Eq. 1).
    fn project(&self, cloud: &[[f32; 4]]) -> Result<Projected> {
        let projection = project(cloud, &self.cylinder)?;
        let points = projection.point_image(cloud);
        let mut image = projection.range.clone();
        image.extend_from_slice(&projection.reflectance);
        Ok(Projected {
            image,
            range: projection.range,
            points,
        })
    }

    /// The pair's back end on a flow (`leave_out`: reference cells not matched), tilt votes as the
    /// config says (`tilt_votes`) or one vote each.
    fn match_flow(
        &self,
        ref_range: &[f32],
        tgt_range: &[f32],
        flow: &DenseFlow,
        ref_points: &[f32],
        leave_out: Option<&[bool]>,
        tilt_votes: bool,
    ) -> Result<Matched> {
        let images = PairImages {
            ref_points: Some(ref_points),
            leave_out,
            ..PairImages::new(ref_range, tgt_range, &flow.flow, &flow.confidence)
        };
        Ok(Matched::new(match_pair(
            &images,
            &self.cylinder,
            &self.pair_config,
            tilt_votes,
        )?))
    }

    #[allow(clippy::too_many_arguments)]
    fn motion_from_flow(
        &mut self,
        previous: &Reference<M::Features>,
        target: &Projected,
        features: &M::Features,
        gap: usize,
        diagnostics: &mut FrameDiagnostics,
        watch: &mut Stopwatch,
    ) -> Result<Matrix4<f64>> {
        diagnostics.gap = Some(gap);
        let predicted = self.motion.predicted(gap);
        let pair = if self.beyond_window(gap, &predicted) {
            let pair =
                self.matched_from_prediction(previous, target, features, &predicted, diagnostics)?;
            watch.lap("rematch", diagnostics);
            pair
        } else {
            let flow = self.matcher.flow(&previous.features, features)?;
            watch.lap("matching", diagnostics);
            let pair = if self.config.matching.symmetric {
                let (forward, backward) =
                    self.matched_both_ways(previous, target, features, &flow, diagnostics, watch)?;
                diagnostics.count_matches(&forward);
                diagnostics.backward_inliers = Some(backward.motion.num_inliers);
                let min_inliers = self.config.motion_model.min_inliers as usize;
                symmetric(forward, backward, min_inliers)
            } else {
                let pair = self.match_flow(
                    &previous.range,
                    &target.range,
                    &flow,
                    &previous.points,
                    None,
                    true,
                )?;
                watch.lap("pair", diagnostics);
                diagnostics.count_matches(&pair);
                pair
            };
            let pair = self.rematched_if_better(
                pair,
                previous,
                target,
                features,
                &predicted,
                gap,
                diagnostics,
            )?;
            if diagnostics.rematch_rounds.is_some() {
                watch.lap("rematch", diagnostics);
            }
            pair
        };
        diagnostics.inlier_votes = pair.motion.inlier_votes;
        let evidence = PairEvidence::new(
            pair.transform,
            pair.motion.num_inliers,
            pair.motion.inlier_votes,
            &pair.motion.source,
            &pair.motion.target,
        );
        let judged = self.motion.judge(&evidence, &predicted, gap);
        if let Some(fallback) = judged.fallback {
            diagnostics.fallback = Some(fallback.name().to_string());
        }
        Ok(judged.motion)
    }

    /// The forward pair (`flow`, reference → target) and the target matched back against the reference
    /// from the cached features (`T_ref_tgt`), each without the cells whose flow the other direction's
    /// flow does not lead back to within `matching.consistency_px`.
    fn matched_both_ways(
        &self,
        previous: &Reference<M::Features>,
        target: &Projected,
        features: &M::Features,
        flow: &DenseFlow,
        diagnostics: &mut FrameDiagnostics,
        watch: &mut Stopwatch,
    ) -> Result<(Matched, Matched)> {
        let back = self.matcher.flow(features, &previous.features)?;
        watch.lap("network_backward", diagnostics);
        let wraps = self.cylinder.wraps_azimuth();
        let (forward_out, backward_out) = match self.config.matching.consistency_px {
            Some(limit) => (
                Some(round_trip_outliers(flow, &back, wraps, limit)),
                Some(round_trip_outliers(&back, flow, wraps, limit)),
            ),
            None => (None, None),
        };
        let forward = self.match_flow(
            &previous.range,
            &target.range,
            flow,
            &previous.points,
            forward_out.as_deref(),
            true,
        )?;
        watch.lap("pair", diagnostics);
        let backward = self.match_flow(
            &target.range,
            &previous.range,
            &back,
            &target.points,
            backward_out.as_deref(),
            true,
        )?;
        watch.lap("backward", diagnostics);
        Ok((forward, backward))
    }

    /// Whether the predicted motion outgrows the network's window (`motion_model.match_from_prediction_m`)
    /// between consecutive scans; never before a velocity is measured.
    fn beyond_window(&self, gap: usize, predicted: &Matrix4<f64>) -> bool {
        let m = &self.config.motion_model;
        let Some(limit) = m.match_from_prediction_m else {
            return false;
        };
        if !self.motion.is_measured() || gap as u64 > m.prediction_horizon {
            return false;
        }
        if m.rematch_gap
            .is_some_and(|rematch_gap| gap as u64 >= rematch_gap)
        {
            return false;
        }
        pose_difference(&Matrix4::identity(), predicted).0 > limit
    }

    fn matched_from_prediction(
        &self,
        previous: &Reference<M::Features>,
        target: &Projected,
        features: &M::Features,
        predicted: &Matrix4<f64>,
        diagnostics: &mut FrameDiagnostics,
    ) -> Result<Matched> {
        let rounds = self.config.prediction_rounds();
        let again = self.rematch(
            &previous.cloud,
            predicted,
            &target.range,
            features,
            1..=rounds,
            None,
            true,
        )?;
        diagnostics.rematch_rounds = Some(again.as_ref().map_or(0, |pair| pair.rounds));
        Ok(match again {
            Some(pair) => {
                diagnostics.count_matches(&pair);
                pair
            }
            None => Matched {
                motion: PairMotion {
                    transform: nalgebra::Isometry3::identity(),
                    source: Vec::new(),
                    target: Vec::new(),
                    cells: Vec::new(),
                    inliers: Vec::new(),
                    num_inliers: 0,
                    inlier_votes: None,
                },
                transform: *predicted,
                rounds: 0,
            },
        })
    }

    /// The pair, or the pair matched again from the prediction (`motion_model.rematch_gap`) when it
    /// spans missing scans or its own motion would give way, and the re-match is usable and better.
    #[allow(clippy::too_many_arguments)]
    fn rematched_if_better(
        &self,
        pair: Matched,
        previous: &Reference<M::Features>,
        target: &Projected,
        features: &M::Features,
        predicted: &Matrix4<f64>,
        gap: usize,
        diagnostics: &mut FrameDiagnostics,
    ) -> Result<Matched> {
        let Some(rematch_gap) = self.config.motion_model.rematch_gap else {
            return Ok(pair);
        };
        if !self.motion.is_measured() {
            return Ok(pair);
        }
        let min_inliers = self.config.motion_model.min_inliers as usize;
        let gives_way = pair.motion.num_inliers < min_inliers
            || (!self.motion.gated_last()
                && self.motion.implausible(&pair.transform, predicted, gap));
        if (gap as u64) < rematch_gap && !gives_way {
            return Ok(pair);
        }
        let large = &self.config.large_motion;
        let mut tried = vec![self.rematch(
            &previous.cloud,
            predicted,
            &target.range,
            features,
            1..=large.max_rounds as usize,
            None,
            false,
        )?];
        // When the prediction's error outgrows the model's window too (a turn during the gap), the wide
        // window started from the prediction does better; beyond the prediction's horizon it is a guess,
        // and the search's starts join it.
        if self.matcher.has_wide_window() {
            let mut starts = vec![*predicted];
            if gap as u64 > self.config.motion_model.prediction_horizon {
                starts.extend(search_starts(&large.search_ahead_m, &large.search_yaw_deg));
            }
            tried.push(Some(self.register_far(
                &previous.cloud,
                target,
                features,
                &starts,
            )?));
        }
        diagnostics.rematch_rounds = Some(0);
        let usable = tried.into_iter().flatten().filter(|again| {
            again.motion.num_inliers >= min_inliers
                && !self.motion.implausible(&again.transform, predicted, gap)
        });
        // The most inliers; on a tie the first tried (the model's own window).
        let best = usable.fold(None::<Matched>, |best, again| match best {
            Some(best) if best.motion.num_inliers >= again.motion.num_inliers => Some(best),
            _ => Some(again),
        });
        let Some(again) = best else {
            return Ok(pair);
        };
        if !gives_way && again.motion.num_inliers <= pair.motion.num_inliers {
            return Ok(pair);
        }
        diagnostics.rematch_rounds = Some(again.rounds);
        diagnostics.fallback = Some("rematched_from_prediction".into());
        diagnostics.count_matches(&again);
        Ok(again)
    }

    /// `T_tgt_ref` of `reference` and the target scan with no usable guess but `starts`: the wide window
    /// from every start, the start with the most inliers (one vote each: starts are compared by their
    /// counts) going on to rounds of the model's own window.
    fn register_far(
        &self,
        reference: &[[f32; 4]],
        target: &Projected,
        tgt_features: &M::Features,
        starts: &[Matrix4<f64>],
    ) -> Result<Matched> {
        let mut best: Option<(Matched, Matrix4<f64>)> = None;
        for start in starts {
            let moved = self.project(&moved_cloud(reference, start))?;
            let encoded = self.matcher.encode(&moved.image)?;
            let flow = self
                .matcher
                .wide_flow(&encoded, tgt_features, &target.image)?;
            let pair = self.match_flow(
                &moved.range,
                &target.range,
                &flow,
                &moved.points,
                None,
                false,
            )?;
            if best
                .as_ref()
                .is_none_or(|(kept, _)| pair.motion.num_inliers > kept.motion.num_inliers)
            {
                best = Some((pair, *start));
            }
        }
        let (pair, start) = best.ok_or_else(|| Error::Config("large_motion: no start".into()))?;
        let refined = self.rematch(
            reference,
            &(pair.transform * start),
            &target.range,
            tgt_features,
            2..=self.config.large_motion.max_rounds as usize,
            Some(pair.transform),
            false,
        )?;
        Ok(match refined {
            Some(refined) => refined,
            None => in_given_frames(pair, &start, 1),
        })
    }

    /// Rounds of matching the reference moved by the estimate so far (from `estimate`) against the
    /// target's features with the model's window, until a round — or the `last_correction` that led to
    /// `estimate` — corrects less than the configured steps (`large_motion.min_step`, `min_step_deg`).
    /// `None` when not one round kept `min_inliers` inliers.
    #[allow(clippy::too_many_arguments)]
    fn rematch(
        &self,
        reference: &[[f32; 4]],
        estimate: &Matrix4<f64>,
        tgt_range: &[f32],
        tgt_features: &M::Features,
        rounds: std::ops::RangeInclusive<usize>,
        last_correction: Option<Matrix4<f64>>,
        tilt_votes: bool,
    ) -> Result<Option<Matched>> {
        let large = &self.config.large_motion;
        let min_inliers = self.config.motion_model.min_inliers as usize;
        let mut estimate = *estimate;
        let mut result: Option<Matched> = None;
        let mut correction = last_correction;
        for round in rounds {
            if let Some(correction) = &correction {
                let (moved_m, turned_deg) = pose_difference(&Matrix4::identity(), correction);
                if moved_m < large.min_step && turned_deg < large.min_step_deg {
                    break;
                }
            }
            let moved = self.project(&moved_cloud(reference, &estimate))?;
            let flow = self
                .matcher
                .flow(&self.matcher.encode(&moved.image)?, tgt_features)?;
            let pair = self.match_flow(
                &moved.range,
                tgt_range,
                &flow,
                &moved.points,
                None,
                tilt_votes,
            )?;
            if pair.motion.num_inliers < min_inliers {
                break;
            }
            correction = Some(pair.transform);
            let given = in_given_frames(pair, &estimate, round);
            estimate = given.transform;
            result = Some(given);
        }
        Ok(result)
    }

    /// The DMLO `pose` refined against the local map; NDT also starts from the prediction once a
    /// velocity is measured and the prediction is within its horizon.
    fn refine_with_map(
        &self,
        cloud: &[[f32; 4]],
        points: &[f32],
        pose: &Matrix4<f64>,
        gap: usize,
        frame: u64,
        diagnostics: &mut FrameDiagnostics,
    ) -> Result<Matrix4<f64>> {
        let map = self.map.as_ref().expect("mapping is on");
        let within_horizon = gap as u64 <= self.config.motion_model.prediction_horizon;
        let prediction = (self.motion.is_measured() && within_horizon).then(|| self.predict(frame));
        let refined = map.refine(
            &as_points(cloud),
            points,
            pose,
            prediction.as_ref(),
            &self.cylinder,
        )?;
        diagnostics.ndt_converged = Some(refined.converged);
        diagnostics.ndt_start = refined.start.map(|start| start.name().to_string());
        diagnostics.ndt_degenerate_directions = refined.degenerate_directions;
        diagnostics.ndt_upright_only = Some(refined.upright_only);
        Ok(refined.pose)
    }
}

/// A pair matched with the reference moved by `start`, as the motion between the scans given: the
/// motion composed with `start`, the matches' reference points moved back.
fn in_given_frames(mut pair: Matched, start: &Matrix4<f64>, rounds: usize) -> Matched {
    let back = rigid_inverse(start);
    let (rotation, translation) = (back.fixed_view::<3, 3>(0, 0), back.fixed_view::<3, 1>(0, 3));
    for p in &mut pair.motion.source {
        *p = Point3::from(rotation * p.coords + translation);
    }
    pair.transform *= start;
    pair.rounds = rounds;
    pair
}

/// One motion from a pair matched both ways: the midpoint of the forward motion and the inverted
/// backward one, with both directions' matches (the backward ones turned round). A direction with fewer
/// than `min_inliers` inliers is left out; with neither, the forward pair goes on to the motion model.
fn symmetric(forward: Matched, backward: Matched, min_inliers: usize) -> Matched {
    let reverse = Matched {
        transform: rigid_inverse(&backward.transform),
        motion: PairMotion {
            transform: backward.motion.transform.inverse(),
            source: backward.motion.target,
            target: backward.motion.source,
            ..backward.motion
        },
        rounds: backward.rounds,
    };
    match (
        forward.motion.num_inliers >= min_inliers,
        reverse.motion.num_inliers >= min_inliers,
    ) {
        (true, true) => {}
        (false, true) => return reverse,
        _ => return forward,
    }
    let transform = midpoint_motion(&forward.transform, &reverse.transform);
    let joined = |a: &[Point3<f64>], b: &[Point3<f64>]| [a, b].concat();
    Matched {
        motion: PairMotion {
            transform: forward.motion.transform,
            source: joined(&forward.motion.source, &reverse.motion.source),
            target: joined(&forward.motion.target, &reverse.motion.target),
            cells: [forward.motion.cells, reverse.motion.cells].concat(),
            inliers: [forward.motion.inliers, reverse.motion.inliers].concat(),
            num_inliers: forward.motion.num_inliers + reverse.motion.num_inliers,
            inlier_votes: forward
                .motion
                .inlier_votes
                .zip(reverse.motion.inlier_votes)
                .map(|(a, b)| a + b),
        },
        transform,
        rounds: forward.rounds,
    }
}

/// Per cell, whether following `flow` and then `back` (read at the nearest cell of the match) lands
/// further than `limit` pixels from where it started, or the match leaves the image: optical flow's
/// forward–backward consistency check, in float32 as `dmlo.Odometry` computes it.
fn round_trip_outliers(flow: &DenseFlow, back: &DenseFlow, wraps: bool, limit: f64) -> Vec<bool> {
    let (height, width) = (flow.height, flow.width);
    let cells = height * width;
    let limit = limit as f32;
    (0..cells)
        .map(|cell| {
            let (row, col) = (cell / width, cell % width);
            let (d_row, d_col) = (flow.flow[cell], flow.flow[cells + cell]);
            let at_row = (row as f32 + d_row).round_ties_even() as i64;
            let mut at_col = (col as f32 + d_col).round_ties_even() as i64;
            if wraps {
                at_col = at_col.rem_euclid(width as i64);
            }
            if at_row < 0 || at_row >= height as i64 || at_col < 0 || at_col >= width as i64 {
                return true;
            }
            let at = at_row as usize * width + at_col as usize;
            (d_row + back.flow[at]).hypot(d_col + back.flow[cells + at]) > limit
        })
        .collect()
}

/// The guesses `T_tgt_ref` of a target `ahead` metres along the reference's x axis, turned by `yaw`
/// (every yaw with every distance, yaw first).
fn search_starts(ahead_m: &[f64], yaw_deg: &[f64]) -> Vec<Matrix4<f64>> {
    let mut starts = Vec::with_capacity(ahead_m.len() * yaw_deg.len());
    for yaw in yaw_deg {
        let (sin, cos) = yaw.to_radians().sin_cos();
        for &ahead in ahead_m {
            #[rustfmt::skip]
            let ref_tgt = Matrix4::new(
                cos, -sin, 0.0, ahead,
                sin, cos, 0.0, 0.0,
                0.0, 0.0, 1.0, 0.0,
                0.0, 0.0, 0.0, 1.0,
            );
            starts.push(rigid_inverse(&ref_tgt));
        }
    }
    starts
}

/// A scan with its points moved by `transform`, in float32 as the points are stored (as Python's).
fn moved_cloud(cloud: &[[f32; 4]], transform: &Matrix4<f64>) -> Vec<[f32; 4]> {
    if *transform == Matrix4::identity() {
        return cloud.to_vec();
    }
    let t: Matrix4<f32> = transform.cast();
    cloud
        .iter()
        .map(|&[x, y, z, reflectance]| {
            let row = |i: usize| x * t[(i, 0)] + y * t[(i, 1)] + z * t[(i, 2)] + t[(i, 3)];
            [row(0), row(1), row(2), reflectance]
        })
        .collect()
}

/// A scan's points as the odometry keeps them.
struct KeptPoints {
    /// Per point: finite and not flagged moving.
    keep: Vec<bool>,
    /// Those points.
    kept: Vec<[f32; 4]>,
    /// The reflectance of every finite point, moving or not: what the reflectance scale is chosen from.
    finite_reflectance: Vec<f32>,
}

/// The points of `scan` the odometry keeps (a `moving` mask of the wrong length is an error naming it).
fn kept_points(scan: &Scan<'_>) -> Result<KeptPoints> {
    check_one_per_point(scan.moving, "moving", "flag", scan.points.len())?;
    let mut finite_reflectance = Vec::with_capacity(scan.points.len());
    let keep: Vec<bool> = scan
        .points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let finite = p.iter().all(|v| v.is_finite());
            if finite {
                finite_reflectance.push(p[3]);
            }
            finite && !scan.moving.is_some_and(|m| m[i])
        })
        .collect();
    Ok(KeptPoints {
        kept: kept_rows(scan.points, &keep),
        keep,
        finite_reflectance,
    })
}

/// Checks that `values` (the scan's `name`: one `what` a point), when given, has one entry per point.
fn check_one_per_point<T>(
    values: Option<&[T]>,
    name: &'static str,
    what: &str,
    points: usize,
) -> Result<()> {
    match values {
        Some(values) if values.len() != points => Err(Error::invalid(
            name,
            format!(
                "expected one {what} per point ({points}), got {}",
                values.len()
            ),
        )),
        _ => Ok(()),
    }
}

/// The rows of `values` whose `keep` flag is set.
fn kept_rows<T: Copy>(values: &[T], keep: &[bool]) -> Vec<T> {
    values
        .iter()
        .zip(keep)
        .filter(|&(_, &kept)| kept)
        .map(|(value, _)| *value)
        .collect()
}

fn as_points(cloud: &[[f32; 4]]) -> Vec<Point3<f64>> {
    cloud
        .iter()
        .map(|p| Point3::new(p[0] as f64, p[1] as f64, p[2] as f64))
        .collect()
}

/// The scale a scan's finite reflectance values look like, and why ([`ReflectanceScale::Ignored`]: none
/// usable), as `dmlo.odometry.reflectance.detect`.
fn detect_reflectance(values: &[f32]) -> (ReflectanceScale, String) {
    let Some((low, high)) = values.iter().fold(None, |acc: Option<(f32, f32)>, &v| {
        Some(acc.map_or((v, v), |(l, h)| (l.min(v), h.max(v))))
    }) else {
        return (
            ReflectanceScale::Ignored,
            "no point has a finite reflectance".into(),
        );
    };
    if low == high {
        return (
            ReflectanceScale::Ignored,
            format!("every point's reflectance is {high}"),
        );
    }
    if low < 0.0 {
        return (
            ReflectanceScale::Ignored,
            format!("reflectance from {low} to {high} is on no known scale"),
        );
    }
    for (scale, divisor, name) in [
        (ReflectanceScale::Unit, 1.0, "[0, 1]"),
        (ReflectanceScale::Byte, 255.0, "0–255"),
        (ReflectanceScale::Word, 65535.0, "0–65535"),
    ] {
        if high <= divisor {
            return (scale, format!("values up to {high} look like {name}"));
        }
    }
    (
        ReflectanceScale::Ignored,
        format!("reflectance up to {high} is on no known scale"),
    )
}

/// The cloud's reflectance divided by the scale's divisor and clipped to [0, 1] (zeros when ignored).
fn normalised(mut cloud: Vec<[f32; 4]>, scale: ReflectanceScale) -> Vec<[f32; 4]> {
    let divisor: f32 = match scale {
        ReflectanceScale::Auto | ReflectanceScale::Unit => 1.0,
        ReflectanceScale::Byte => 255.0,
        ReflectanceScale::Word => 65535.0,
        ReflectanceScale::Ignored => {
            cloud.iter_mut().for_each(|p| p[3] = 0.0);
            return cloud;
        }
    };
    for p in &mut cloud {
        p[3] = (p[3] / divisor).clamp(0.0, 1.0);
    }
    cloud
}

/// Milliseconds per stage, each lap from the end of the last.
struct Stopwatch {
    last: Instant,
}

impl Stopwatch {
    fn new() -> Self {
        Stopwatch {
            last: Instant::now(),
        }
    }

    fn lap(&mut self, stage: &str, diagnostics: &mut FrameDiagnostics) {
        let now = Instant::now();
        let ms = (now - self.last).as_secs_f64() * 1e3;
        *diagnostics
            .timings_ms
            .entry(stage.to_string())
            .or_insert(0.0) += ms;
        self.last = now;
    }
}

mod two_scans;

pub use two_scans::RegisteredPair;

#[cfg(test)]
mod tests;
