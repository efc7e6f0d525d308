#![forbid(unsafe_code)]
//! [`Odometry`]: DMLO's per-frame state machine in the crate (paper §III), over any [`FrameMatcher`] —
//! the learned matcher of `dmlo_rs::inference` (feature `inference`, no Python), or a runtime of the
//! caller's own.
//!
//! Every scan is projected onto the cylinder image (Eq. 1), encoded, and matched against the previous
//! scan's cached features (§III-C); the pair's back end ([`crate::pair::match_pair`]) turns the flow
//! into a motion (§III-D), which the motion model judges ([`super::motion`], §III-D-c) and the local
//! map refines by NDT ([`super::mapping`]); the motions chain into `T_world_lidar` poses, the first scan
//! being the world. The settings are the config's ([`super::config`]); `dmlo.Odometry` in Python is this
//! loop. Beyond the paper: pairs whose predicted motion outgrows the
//! network's window are matched from the prediction, and pairs across missing scans (or whose own
//! motion gives way) are matched again from it.
//! [`Odometry::register_pair`] registers two scans with no drive around them (`dmlo register`).
//!
//! Refused by [`Odometry::new`]: a `matching_stage` the matcher does not run
//! ([`FrameMatcher::runs_matching_stage`]). Points on moving objects are left out: those the caller
//! masks ([`Scan::moving`]), else, with a moving-object network ([`Odometry::with_moving_objects`]) and
//! `moving_objects.detect`, those the network flags (without either, every point is kept, as
//! as with a model folder without `moving.onnx`). Re-matching tries the wide window when the matcher has one
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
//!     assert!(pose.translation.vector.norm() < 0.01);
//! }
//! assert_eq!(odometry.diagnostics().len(), 3);
//! # Ok(())
//! # }
//! ```

use std::sync::Arc;
use std::time::Instant;

use nalgebra::{Isometry3, Matrix4};

use crate::dense_match::DenseFlow;
use crate::error::{Error, Result};
use crate::odometry::clock::FrameClock;
use crate::odometry::config::schema::Named;
use crate::odometry::config::{MatchingStage, OdometryConfig, ReflectanceScale};
use crate::odometry::mapping::LocalMap;
use crate::odometry::motion::{nearest_rigid, rigid_inverse, Fallback, MotionModel};
use crate::odometry::moving::{moving_points_and_fill, MovingObjectNetwork};
use crate::pair::{PairConfig, PairMotion};
use crate::projection::{project, CylinderConfig, Projection};
use crate::rigid::isometry_from_parts;

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
    /// Encodes the image of a scan given to [`Odometry::register`] (every other image the odometry
    /// encodes — a reference moved by a guess — goes to [`FrameMatcher::encode`]). By default `encode`;
    /// [`EncodeAhead`] answers it with the features it computed while the scan before was registered.
    fn encode_scan(&self, image: &[f32]) -> Result<Self::Features> {
        self.encode(image)
    }
    /// The moving-object network's flags of the points of a scan given to [`Odometry::register`], when
    /// they were computed ahead ([`EncodeAhead`]); by default none.
    fn moving_ahead(&self, points: &[[f32; 4]]) -> Option<Vec<bool>> {
        let _ = points;
        None
    }
    /// The flow of every `reference` cell into `target` and its confidence (§III-C).
    fn flow(&self, reference: &Self::Features, target: &Self::Features) -> Result<DenseFlow>;
    /// The flow of the `reference` cells marked in `cells` (row-major, one per image cell) into
    /// `target`; the other cells' flow is never read and may be anything (the crate's matching stage
    /// leaves them NaN). The odometry asks for the cells that hold a point. By default every cell's
    /// ([`FrameMatcher::flow`]).
    fn flow_of_cells(
        &self,
        reference: &Self::Features,
        target: &Self::Features,
        cells: &[bool],
    ) -> Result<DenseFlow> {
        let _ = cells;
        self.flow(reference, target)
    }
    /// The flow of the marked `reference` cells into `target` with the coarse windows placed where the
    /// cells are `expected` to land (each cell's expected flow, Δrow and Δcol in pixels, NaN where none;
    /// [`crate::dense_match::match_features_guided`]): the odometry's guess at a pair whose motion
    /// outgrows the network's window, instead of moving the reference by the prediction and encoding it
    /// again. `None`: the matcher cannot place its windows (the default); the reference is then moved.
    fn guided_flow_of_cells(
        &self,
        reference: &Self::Features,
        target: &Self::Features,
        cells: &[bool],
        expected: &[[f32; 2]],
    ) -> Result<Option<DenseFlow>> {
        let _ = (reference, target, cells, expected);
        Ok(None)
    }
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
    /// `x, y, z, reflectance` in the sensor frame, metres; non-finite points and points at the origin
    /// (no return) are left out ([`Odometry::register`]).
    pub points: &'a [[f32; 4]],
    /// Whether the points carry a reflectance (false: the sensor or file gave none, and the fourth value
    /// of every point is a placeholder): such scans run the range-only model.
    pub has_reflectance: bool,
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
            has_reflectance: true,
            moving: None,
            timestamp: None,
            point_times: None,
        }
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
    /// Scans since it became the reference that could not be matched against it (too few inliers) and
    /// were passed over: the next was matched against it instead.
    passed_over: usize,
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
    /// Scans registered since the start (or the last [`Odometry::reset`]): the index of the next.
    frames: usize,
    /// The newest frames whose poses and diagnostics are kept; `None`: all of them.
    history: Option<usize>,
    reflectance: Option<ReflectanceScale>,
    /// Why that scale (the values seen, or the config), for the notices that name it.
    reflectance_reason: String,
    /// The model not running: the range-only one until the first scan without usable reflectance, the
    /// model itself from then on (kept for [`Odometry::reset`]).
    range_only: Option<M>,
    /// The range-only model runs in place of the model.
    runs_range_only: bool,
    /// Notices not yet given to a frame's (or a pair's) diagnostics.
    notices: Vec<Notice>,
    /// The notices said once per odometry that were said.
    said: Said,
    /// Scans without usable reflectance and no range-only model run the model on zeros (not refused).
    zero_reflectance_allowed: bool,
    /// Flags the points on moving objects of scans given without a mask (shared with [`EncodeAhead`]'s
    /// thread, which flags the next scan's).
    moving_objects: Option<Arc<dyn MovingObjectNetwork + Send + Sync>>,
}

impl<M: FrameMatcher> Odometry<M> {
    /// An odometry running `matcher` with `config` (checked whole; settings the crate does not run yet
    /// are refused, naming them).
    pub fn new(matcher: M, config: OdometryConfig) -> Result<Self> {
        config.validate()?;
        if !matcher.runs_matching_stage(config.matching_stage) {
            return Err(Error::Config(format!(
                "matching_stage: \"{}\": not how this matcher matches",
                config.matching_stage.name()
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
            frames: 0,
            history: None,
            reflectance: None,
            reflectance_reason: String::new(),
            range_only: None,
            runs_range_only: false,
            notices: Vec::new(),
            said: Said::default(),
            zero_reflectance_allowed: false,
            moving_objects: None,
        })
    }

    /// The odometry with a moving-object network (the model's `moving.onnx`): with `moving_objects.detect`
    /// in the config, the points of a scan given without a [`Scan::moving`] mask that it puts on moving
    /// objects (a cell's probability above `moving_objects.threshold`) are left out of matching and of the
    /// map, and the diagnostics count them (`num_moving_predicted`). Its image must be the model's.
    pub fn with_moving_objects(
        mut self,
        network: impl MovingObjectNetwork + Send + Sync + 'static,
    ) -> Result<Self> {
        if network.cylinder() != self.matcher.cylinder() {
            return Err(Error::invalid(
                "moving_objects",
                "its cylinder image differs from the model's",
            ));
        }
        self.moving_objects = Some(Arc::new(network));
        Ok(self)
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
    /// cannot be trusted, and a [`Notice::ZeroReflectance`] says so. For a model trained with
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

    /// Every pose so far, `T_world_lidar` (the first scan is the world); with [`Odometry::keeping_history`]
    /// the newest ones only.
    pub fn poses(&self) -> impl ExactSizeIterator<Item = Isometry3<f64>> + '_ {
        self.poses.iter().map(isometry)
    }

    /// [`Odometry::poses`] as the 4×4 matrices the odometry chains (what the Python binding hands over).
    #[cfg(feature = "python")]
    pub(crate) fn pose_matrices(&self) -> &[Matrix4<f64>] {
        &self.poses
    }

    /// What happened to every scan so far (the newest ones only, as [`Odometry::poses`]).
    pub fn diagnostics(&self) -> &[FrameDiagnostics] {
        &self.diagnostics
    }

    /// The newest scan's pose `T_world_lidar`; `None` before the first.
    pub fn pose(&self) -> Option<Isometry3<f64>> {
        self.poses.last().map(isometry)
    }

    /// The newest scan's motion from the one before, `T_previous_newest` (the pose of the newest scan in
    /// the previous scan's frame); `None` before the second scan.
    pub fn delta(&self) -> Option<Isometry3<f64>> {
        match self.poses.as_slice() {
            [.., previous, newest] => Some(isometry(previous).inverse() * isometry(newest)),
            _ => None,
        }
    }

    /// Scans registered so far (since the last [`Odometry::reset`]), whatever the history keeps.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// The odometry keeping the poses and diagnostics of the newest `frames` scans only (at least 2, for
    /// [`Odometry::delta`]), so that a robot running for days holds bounded memory.
    pub fn keeping_history(mut self, frames: usize) -> Self {
        self.history = Some(frames.max(2));
        self
    }

    /// Forgets the drive: the next scan is the world again, matched against nothing; the motion model, the
    /// local map, the clock, the reflectance scale and the notices said start afresh, and the model runs
    /// again where the range-only one took over. The matcher, the config and the networks stay.
    pub fn reset(&mut self) {
        if self.runs_range_only {
            if let Some(model) = &mut self.range_only {
                std::mem::swap(&mut self.matcher, model);
                self.runs_range_only = false;
            }
        }
        if let Some(map) = &mut self.map {
            map.clear();
        }
        self.motion = MotionModel::new(self.config.motion_limits());
        self.clock = FrameClock::new();
        self.reference = None;
        self.pose_frame = None;
        self.poses.clear();
        self.diagnostics.clear();
        self.frames = 0;
        self.reflectance = None;
        self.reflectance_reason.clear();
        self.notices.clear();
        self.said = Said::default();
    }

    /// The reflectance scale chosen on the first scan ([`ReflectanceScale::Ignored`]: none used).
    pub fn reflectance_scale(&self) -> Option<ReflectanceScale> {
        self.reflectance
    }

    /// Whether the range-only model runs in place of the model (from the first scan without usable
    /// reflectance on; [`Odometry::with_range_only`]).
    pub fn runs_range_only(&self) -> bool {
        self.runs_range_only
    }

    /// Adds the next scan and returns its pose `T_world_lidar`. Points that are non-finite, closer than
    /// [`MIN_RETURN_RANGE_M`] to the sensor (at the origin: no return) or farther than
    /// [`MAX_SENSOR_RANGE_M`] are left out, as are the moving ones. A scan with fewer points left than
    /// `min_points` (and than 3) is not matched: its pose comes from the motion
    /// model and its diagnostics say so (`too_few_points`). A scan that could not be matched against the
    /// previous one (`constant_velocity`: too few inliers) does not become the reference of the next,
    /// unless the scan before it could not be matched either. Errors name a bad argument (a mask of the
    /// wrong length, a non-finite timestamp, reflectance the model cannot use, a scan fewer than half of
    /// whose returns lie at a sensor's ranges: millimetres, or a world frame); the odometry's state is
    /// then as before the call, apart from the clock of a scan whose error came from the matcher.
    pub fn register(&mut self, scan: Scan<'_>) -> Result<Isometry3<f64>> {
        self.register_matrix(scan).map(|pose| isometry(&pose))
    }

    /// [`Odometry::register`]'s pose as the 4×4 matrix the odometry chains.
    pub(crate) fn register_matrix(&mut self, scan: Scan<'_>) -> Result<Matrix4<f64>> {
        let detecting = Instant::now();
        let detected = self.detect_moving(&scan, true)?;
        let detecting = detecting.elapsed().as_secs_f64() * 1e3;
        let (detected, scan_fill) = match detected {
            Some((moving, fill)) => (Some(moving), fill),
            None => (None, None),
        };
        let scan = match &detected {
            Some(moving) => Scan {
                moving: Some(moving),
                ..scan
            },
            None => scan,
        };
        let points = kept_points(&scan)?;
        points.check_plausible("points", scan.points.len())?;
        let KeptPoints {
            keep,
            kept,
            finite_reflectance,
            ..
        } = points;
        check_one_per_point(scan.point_times, "point_times", "time", scan.points.len())?;
        let times = scan.point_times.map(|times| kept_rows(times, &keep));
        let min_points = self.points_needed();
        let index = self.frames;
        let values = scan.has_reflectance.then_some(&finite_reflectance[..]);
        let scale = self.reflectance_for(values, finite_reflectance.len(), min_points, index)?;
        let tick = self.clock.advance(scan.timestamp)?;
        if let (true, Some(timestamp), Some(previous)) =
            (tick.out_of_order, scan.timestamp, tick.previous)
        {
            self.say_once(
                |said| &mut said.timestamp,
                Notice::TimestampNotAfter {
                    timestamp,
                    previous,
                },
            );
        }
        let mut diagnostics = FrameDiagnostics {
            index,
            num_points: scan.points.len(),
            ..Default::default()
        };
        if let Some(moving) = &detected {
            diagnostics.num_moving_predicted = Some(moving.iter().filter(|&&m| m).count());
            diagnostics
                .timings_ms
                .insert("moving_objects".into(), detecting);
        }
        if kept.len() < min_points {
            return Ok(self.skip(diagnostics, Fallback::TooFewPoints));
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
        let image_fill = filled as f64 / projected.range.len() as f64;
        diagnostics.image_fill = Some(image_fill);
        self.check_sensor(scan_fill.unwrap_or(image_fill));
        let features = self.matcher.encode_scan(&projected.image)?;
        watch.lap("network", &mut diagnostics);
        let previous = self.reference.take();
        let motion_before = self.motion.clone();
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
        // A scan that could not be matched against the reference (too few inliers) neither replaces it
        // nor enters the map, nor counts for the motion model (its prediction measured nothing): it is
        // bridged as a scan with too few points is, and the next scan is matched against the reference
        // across the gap. A second such scan in a row does replace it: the reference may be what
        // cannot be matched.
        let unmatched = diagnostics.fallback == Some(Fallback::ConstantVelocity);
        if let Some(previous) = previous.filter(|p| unmatched && p.passed_over == 0) {
            self.motion = motion_before;
            self.reference = Some(Reference {
                passed_over: 1,
                ..previous
            });
            return Ok(self.record(pose, tick.frame, diagnostics));
        }
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
            passed_over: 0,
        });
        Ok(self.record(pose, tick.frame, diagnostics))
    }

    /// The network's `(2, H, W)` input of a scan's finite points and its range image (Eq. 1), its
    /// reflectance on the scale chosen (before the first deciding scan: the one this scan would choose; a
    /// scan plainly on another scale than the one guessed: its own); nothing is decided or said.
    pub fn network_image(&self, scan: Scan<'_>) -> Result<(Vec<f32>, Vec<f32>)> {
        let points = kept_points(&scan)?;
        points.check_plausible("points", scan.points.len())?;
        let KeptPoints {
            kept,
            finite_reflectance,
            ..
        } = points;
        let values = scan.has_reflectance.then_some(&finite_reflectance[..]);
        let (detected, why) = reflectance::detect_reflectance(values);
        let scale = match self.reflectance {
            Some(chosen) => self.scan_scale(chosen, detected, values),
            None => self.first_choice(detected, why).0,
        };
        let projected = self.project(&normalised(kept, scale))?;
        Ok((projected.image, projected.range))
    }

    /// The points of `scan` the moving-object network flags, when it is to run on it: the odometry has one,
    /// the config asks for it and the caller gave no mask; with the fraction of the image's cells the whole
    /// scan fills (the sensor check's figure, which the scan left without them would understate), when the
    /// network's images were made here.
    /// `from_ahead`: flags the matcher computed ahead for a scan given to [`Odometry::register`] are taken.
    fn detect_moving(
        &self,
        scan: &Scan<'_>,
        from_ahead: bool,
    ) -> Result<Option<(Vec<bool>, Option<f64>)>> {
        match &self.moving_objects {
            Some(network) if scan.moving.is_none() && self.config.moving_objects.detect => {
                if from_ahead {
                    if let Some(flags) = self.matcher.moving_ahead(scan.points) {
                        return Ok(Some((flags, None)));
                    }
                }
                let threshold = self.config.moving_objects.threshold;
                let (flags, fill) =
                    moving_points_and_fill(network.as_ref(), scan.points, threshold)?;
                Ok(Some((flags, Some(fill))))
            }
            _ => Ok(None),
        }
    }

    /// The points a scan needs to be matched: `min_points`, and never fewer than the 3 a rigid motion
    /// needs (with fewer, the scan would still choose the reflectance scale).
    fn points_needed(&self) -> usize {
        (self.config.min_points as usize).max(3)
    }

    /// The sensor notice, once, for a scan that fills less than [`LOW_IMAGE_FILL`] of the image.
    fn check_sensor(&mut self, image_fill: f64) {
        if image_fill < LOW_IMAGE_FILL {
            let (height, width) = (self.cylinder.height, self.cylinder.width);
            let notice = Notice::SensorMismatch {
                image_fill,
                height,
                width,
            };
            self.say_once(|said| &mut said.sensor, notice);
        }
    }

    /// `notice`, unless the flag `which` picks says it was said; the flag set.
    fn say_once(&mut self, which: impl FnOnce(&mut Said) -> &mut bool, notice: Notice) {
        let said = which(&mut self.said);
        if !*said {
            *said = true;
            self.notices.push(notice);
        }
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
        let pose = nearest_rigid(&pose);
        self.motion.update(&previous.pose, &pose, gap);
        Ok(pose)
    }

    /// Records a scan that could not be read: its pose comes from the motion model (`reason` in its
    /// diagnostics, e.g. [`Fallback::UnreadableScan`]).
    pub fn predict_skipped(&mut self, reason: Fallback) -> Result<Isometry3<f64>> {
        self.predict_skipped_matrix(reason).map(|pose| isometry(&pose))
    }

    /// [`Odometry::predict_skipped`]'s pose as the 4×4 matrix the odometry chains.
    pub(crate) fn predict_skipped_matrix(&mut self, reason: Fallback) -> Result<Matrix4<f64>> {
        self.clock.advance(None)?;
        let diagnostics = FrameDiagnostics {
            index: self.frames,
            ..Default::default()
        };
        Ok(self.skip(diagnostics, reason))
    }

    fn skip(&mut self, mut diagnostics: FrameDiagnostics, reason: Fallback) -> Matrix4<f64> {
        let frame = self.clock.frame().unwrap_or(0);
        diagnostics.fallback = Some(reason);
        let pose = self.predict(frame);
        self.record(pose, frame, diagnostics)
    }

    fn record(
        &mut self,
        pose: Matrix4<f64>,
        frame: u64,
        mut diagnostics: FrameDiagnostics,
    ) -> Matrix4<f64> {
        diagnostics.notices = std::mem::take(&mut self.notices);
        self.pose_frame = Some(frame);
        self.poses.push(pose);
        self.diagnostics.push(diagnostics);
        self.frames += 1;
        if let Some(kept) = self.history {
            // Trimmed in batches, so that each scan moves the history once on average.
            if self.poses.len() >= 2 * kept {
                let dropped = self.poses.len() - kept;
                self.poses.drain(..dropped);
                self.diagnostics.drain(..dropped);
            }
        }
        pose
    }

    /// The constant-velocity pose of the scan at `frame`; the first scan defines the world.
    fn predict(&self, frame: u64) -> Matrix4<f64> {
        match (self.poses.last(), self.pose_frame) {
            (Some(last), Some(pose_frame)) => {
                let frames = frame.saturating_sub(pose_frame) as usize;
                nearest_rigid(&(last * rigid_inverse(&self.motion.predicted(frames))))
            }
            _ => Matrix4::identity(),
        }
    }

    /// The network input, range image and point image of a scan (Eq. 1).
    fn project(&self, cloud: &[[f32; 4]]) -> Result<Projected> {
        let projection = project(cloud, &self.cylinder)?;
        let points = projection.point_image(cloud);
        Ok(Projected {
            image: network_input(&projection),
            range: projection.range,
            points,
        })
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

/// The notices said once per odometry, and whether each was.
#[derive(Debug, Clone, Copy, Default)]
struct Said {
    clipping: bool,
    rescaled: bool,
    timestamp: bool,
    sensor: bool,
}

/// The network's `(2, H, W)` input of a projected scan: its range image, then its reflectance image.
fn network_input(projection: &Projection) -> Vec<f32> {
    [&projection.range[..], &projection.reflectance].concat()
}

mod deskewing;
mod diagnostics;
mod encode_ahead;
mod matching;
mod notices;
mod reflectance;
mod rematching;
mod scan_points;
mod two_scans;

pub use diagnostics::FrameDiagnostics;
pub use encode_ahead::EncodeAhead;
pub use notices::{Notice, LOW_IMAGE_FILL};
pub use scan_points::{MAX_SENSOR_RANGE_M, MIN_RETURN_RANGE_M};
pub use two_scans::RegisteredPair;

use diagnostics::Stopwatch;
#[cfg(test)]
use matching::{round_trip_outliers, symmetric};
#[cfg(test)]
use reflectance::detect_reflectance;
use reflectance::normalised;
#[cfg(test)]
use rematching::moved_cloud;
use scan_points::{as_points, check_one_per_point, kept_points, kept_rows, KeptPoints};

/// A pose the odometry chained (a rigid 4×4 matrix, orthonormal by construction) as an isometry.
fn isometry(pose: &Matrix4<f64>) -> Isometry3<f64> {
    isometry_from_parts(
        &pose.fixed_view::<3, 3>(0, 0).into_owned(),
        &pose.fixed_view::<3, 1>(0, 3).into_owned(),
    )
}

#[cfg(test)]
mod tests;
