#![forbid(unsafe_code)]
//! The odometry's settings as `dmlo run` saves them (`config.json`), read by serde: the same sections,
//! keys, defaults and ranges as Python's `dmlo.odometry.config.OdometryConfig`, so that a config written
//! by either loads unchanged in the other.
//!
//! Python's `json` writes an unlimited setting (a [`Limit`]) as the bare token `Infinity`, which is not
//! JSON; [`OdometryConfig::from_json`] reads it (and refuses it anywhere a finite number is asked for).
//! The checks are as strict as Python's: an unknown key is named with its section, `1` is not a boolean,
//! `1.5` not an integer, `null` is allowed only where a setting is optional, and every value is checked
//! against its range ([`OdometryConfig::validate`]); each error names the key.
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
//! assert!(bad.to_string().contains("ransac.treshold"));
//! # Ok(())
//! # }
//! ```

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::coherence::CoherenceConfig;
use crate::error::{Error, Result};
use crate::odometry::mapping::MappingConfig;
use crate::odometry::motion::MotionLimits;
use crate::pair::PairConfig;
use crate::ransac::{RansacConfig, Refit};
use crate::ray_noise::RayNoise;

/// Which network predictions become 3D matches (§III-D-a).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MatchingSection {
    /// A confidence below this drops the cell before NMS (0 to 1).
    pub min_confidence: f64,
    /// NMS radius in cells (the paper's r = 1).
    pub nms_radius: u64,
    /// The top N matches kept after NMS (at least 3).
    pub max_matches: u64,
    /// Also match the new scan back against the previous one and take the midpoint of the two motions.
    pub symmetric: bool,
    /// With `symmetric`: the forward–backward check's limit in pixels; `None` keeps every cell.
    #[serde(deserialize_with = "optional_limit")]
    pub consistency_px: Option<f64>,
    /// The confidence weighted by the coherence of each cell's flow with its neighbours'; `None`: not.
    pub coherence_px: Option<f64>,
    /// The coherence's neighbourhood radius in cells.
    pub coherence_radius: u64,
}

impl Default for MatchingSection {
    fn default() -> Self {
        MatchingSection {
            min_confidence: 0.0,
            nms_radius: 1,
            max_matches: 1000,
            symmetric: false,
            consistency_px: Some(1.0),
            coherence_px: Some(0.5),
            coherence_radius: 2,
        }
    }
}

/// How RANSAC's refits solve for the motion, as the config names them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RefitKind {
    /// The closed-form SVD solve (the paper's).
    PointToPoint,
    /// The SVD solve refined under ray noise.
    #[default]
    RayNoise,
}

/// RANSAC around the closed-form SVD solve (§III-D-b).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RansacSection {
    /// The inlier threshold (m; the paper's 0.1).
    pub threshold: f64,
    /// Stop once a better hypothesis would have been found with this probability.
    pub confidence: f64,
    /// Hypotheses at most (1 to a million).
    pub max_iterations: u64,
    /// The sampler's seed.
    pub seed: u64,
    /// How the refits solve.
    pub refit: RefitKind,
    /// With `ray_noise`: range noise over bearing noise.
    pub ray_range_ratio: f64,
    /// With `ray_noise`: the refits' bearing tolerance (°).
    pub ray_bearing_threshold_deg: f64,
    /// A match's vote from the tilt of the surface under it (consecutive scans).
    pub vote_by_tilt: bool,
    /// The votes' floor.
    pub min_vote: f64,
    /// Each vote divided by the square root of its cube's crowding, cubes of this many metres; `None`: not.
    pub vote_voxel: Option<f64>,
}

impl Default for RansacSection {
    fn default() -> Self {
        RansacSection {
            threshold: 0.1,
            confidence: 0.999,
            max_iterations: 1000,
            seed: 0,
            refit: RefitKind::RayNoise,
            ray_range_ratio: 4.0,
            ray_bearing_threshold_deg: 0.2,
            vote_by_tilt: true,
            min_vote: 0.05,
            vote_voxel: Some(2.0),
        }
    }
}

/// The constant-velocity motion model and its judgement of every pair (§III-D-c).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MotionModelSection {
    /// Fewer RANSAC inliers than this and the pair has no motion of its own (the paper's 10).
    pub min_inliers: u64,
    /// With tilt votes: the inliers' votes above the floor must reach this.
    pub min_inlier_votes: f64,
    /// A motion further than this from the prediction (m per frame) is a wrong consensus.
    #[serde(deserialize_with = "limit")]
    pub max_deviation: f64,
    /// The same for the rotation (° per frame).
    #[serde(deserialize_with = "limit")]
    pub max_deviation_deg: f64,
    /// The agreeing matches' share of RANSAC's inliers that makes them a consensus of their own.
    pub guided_fraction: f64,
    /// A pair spanning this many frames or more is matched again from the prediction; `None`: never.
    pub rematch_gap: Option<u64>,
    /// Across more frames than this the prediction is a guess.
    pub prediction_horizon: u64,
    /// A pair predicted to move further than this (m) is matched from the prediction at once.
    pub match_from_prediction_m: Option<f64>,
    /// Matching rounds from the prediction at most; `None`: 1 with mapping, 2 without.
    pub prediction_rounds: Option<u64>,
    /// Match from the prediction by placing the coarse windows where it takes each cell first; the
    /// reference is moved and encoded again only when that pair gives way. `None`: with mapping only.
    pub guided_windows: Option<bool>,
    /// Before a velocity is measured (the first pair), the pair is also matched from the reference moved
    /// this far (m) ahead and behind along its x axis; another motion that holds flags the frame
    /// (`FrameDiagnostics::ambiguous_start`). `None`: never.
    pub start_check_m: Option<f64>,
    /// A flagged first pair whose motion drives backwards (along the sensor's x axis) further than this
    /// (m a frame) while a start's motion drives forward as far takes the forward motion (fallback
    /// `forward_start`). `None`: the frame keeps its motion.
    pub start_max_reverse_m: Option<f64>,
}

impl Default for MotionModelSection {
    fn default() -> Self {
        MotionModelSection {
            min_inliers: 10,
            min_inlier_votes: 5.0,
            max_deviation: 0.3,
            max_deviation_deg: 3.0,
            guided_fraction: 0.5,
            rematch_gap: Some(2),
            prediction_horizon: 20,
            match_from_prediction_m: Some(1.5),
            prediction_rounds: None,
            guided_windows: None,
            start_check_m: Some(3.0),
            start_max_reverse_m: Some(0.5),
        }
    }
}

/// Motion compensation of every sweep before projection.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DeskewSection {
    /// Deskew the sweeps.
    pub enabled: bool,
    /// The sensor turns clockwise seen from above (Velodyne, KITTI).
    pub clockwise: bool,
    /// The azimuth (°) at whose moment the pose holds.
    pub reference_azimuth_deg: f64,
}

impl Default for DeskewSection {
    fn default() -> Self {
        DeskewSection {
            enabled: false,
            clockwise: true,
            reference_azimuth_deg: 0.0,
        }
    }
}

/// Scan-to-map NDT refinement over a local map of keyframes (§III-D-c); `enabled = false` is the
/// paper's frame-to-frame DMLO.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MappingSection {
    /// Refine every pose against the local map.
    pub enabled: bool,
    /// NDT voxel edge (m).
    pub voxel_size: f64,
    /// Keyframes the map keeps.
    pub max_scans: u64,
    /// Keyframe spacing (m) …
    #[serde(deserialize_with = "limit")]
    pub keyframe_distance: f64,
    /// … or turn (°).
    #[serde(deserialize_with = "limit")]
    pub keyframe_angle_deg: f64,
    /// The near-keyframe handling's reach (m); 0 turns it off.
    #[serde(deserialize_with = "limit")]
    pub ring_lock_distance: f64,
    /// NDT also starts from the prediction when the DMLO pose lies this far from it (m) …
    #[serde(deserialize_with = "limit")]
    pub motion_model_start_distance: f64,
    /// … or this much turned (°).
    #[serde(deserialize_with = "limit")]
    pub motion_model_start_angle_deg: f64,
    /// Voxel (m) of the scan aligned to the map within `far_range` of the sensor; 0: every point …
    pub downsample: f64,
    /// … and beyond it.
    pub downsample_far: f64,
    /// Metres from the sensor.
    #[serde(deserialize_with = "limit")]
    pub far_range: f64,
    /// The height, roll and pitch from NDT without the upright surfaces beyond `far_range`.
    pub level_without_far_upright: bool,
    /// Newton steps at most.
    pub max_iterations: u64,
    /// The translations' degeneracy threshold.
    pub degeneracy_threshold: f64,
    /// The rotations' degeneracy threshold.
    pub rotation_degeneracy_threshold: f64,
}

impl Default for MappingSection {
    fn default() -> Self {
        let c = MappingConfig::default();
        MappingSection {
            enabled: true,
            voxel_size: c.voxel_size,
            max_scans: c.max_scans as u64,
            keyframe_distance: c.keyframe_distance,
            keyframe_angle_deg: c.keyframe_angle_deg,
            ring_lock_distance: c.ring_lock_distance,
            motion_model_start_distance: c.motion_model_start_distance,
            motion_model_start_angle_deg: c.motion_model_start_angle_deg,
            downsample: c.downsample,
            downsample_far: c.downsample_far,
            far_range: c.far_range,
            level_without_far_upright: c.level_without_far_upright,
            max_iterations: c.max_iterations as u64,
            degeneracy_threshold: c.degeneracy_threshold,
            rotation_degeneracy_threshold: c.rotation_degeneracy_threshold,
        }
    }
}

/// Registration of scans far apart, with no initial guess (§IV-D), from several starts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LargeMotionSection {
    /// Starts along the reference's x axis (m).
    pub search_ahead_m: Vec<f64>,
    /// Starts turned about the vertical (°).
    pub search_yaw_deg: Vec<f64>,
    /// Matching rounds from the best start at most.
    pub max_rounds: u64,
    /// A round correcting less than this (m) …
    #[serde(deserialize_with = "limit")]
    pub min_step: f64,
    /// … and this (°) ends the rounds.
    #[serde(deserialize_with = "limit")]
    pub min_step_deg: f64,
}

impl Default for LargeMotionSection {
    fn default() -> Self {
        LargeMotionSection {
            search_ahead_m: vec![0.0, -6.0, 6.0, -12.0, 12.0],
            search_yaw_deg: vec![0.0],
            max_rounds: 4,
            min_step: 0.05,
            min_step_deg: 0.1,
        }
    }
}

/// Points on moving objects predicted by the moving-object network beside the model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MovingObjectsSection {
    /// Run the network (when the model has it).
    pub detect: bool,
    /// A cell's moving probability above this drops its points.
    pub threshold: f64,
}

impl Default for MovingObjectsSection {
    fn default() -> Self {
        MovingObjectsSection {
            detect: true,
            threshold: 0.5,
        }
    }
}

/// Where the network's correlation and window decoding run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MatchingStage {
    /// The crate when the network runs on a CPU.
    #[default]
    Auto,
    /// The crate's matching stage on cached features.
    Crate,
    /// Inside the ONNX graph.
    Graph,
}

/// The scans' reflectance scale.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum ReflectanceScale {
    /// Decided from the first scan's values.
    #[default]
    #[serde(rename = "auto")]
    Auto,
    /// Already in [0, 1].
    #[serde(rename = "unit")]
    Unit,
    /// 0 to 255.
    #[serde(rename = "0-255")]
    Byte,
    /// 0 to 65535.
    #[serde(rename = "0-65535")]
    Word,
    /// Not used: the range-only model runs.
    #[serde(rename = "none")]
    Ignored,
}

/// Every setting of the odometry (module docs); `Default` is `dmlo run`'s.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OdometryConfig {
    /// Which predictions become matches.
    pub matching: MatchingSection,
    /// RANSAC.
    pub ransac: RansacSection,
    /// The motion model.
    pub motion_model: MotionModelSection,
    /// Deskewing.
    pub deskew: DeskewSection,
    /// The local map.
    pub mapping: MappingSection,
    /// Registration from several starts.
    pub large_motion: LargeMotionSection,
    /// The moving-object network.
    pub moving_objects: MovingObjectsSection,
    /// The network's and the matching stage's threads; 0 lets them choose.
    pub threads: u64,
    /// Where the matching stage runs.
    pub matching_stage: MatchingStage,
    /// Scans with fewer finite points are bridged by the motion model.
    pub min_points: u64,
    /// The scans' reflectance scale.
    pub reflectance: ReflectanceScale,
}

impl Default for OdometryConfig {
    fn default() -> Self {
        OdometryConfig {
            matching: MatchingSection::default(),
            ransac: RansacSection::default(),
            motion_model: MotionModelSection::default(),
            deskew: DeskewSection::default(),
            mapping: MappingSection::default(),
            large_motion: LargeMotionSection::default(),
            moving_objects: MovingObjectsSection::default(),
            threads: 0,
            matching_stage: MatchingStage::Auto,
            min_points: 1000,
            reflectance: ReflectanceScale::Auto,
        }
    }
}

impl OdometryConfig {
    /// The config a JSON text describes (Python's `Infinity` read as an unlimited [`Limit`]), every key left
    /// out at its default, checked against the schema ([`Self::validate`]). Errors ([`Error::Config`]) name
    /// the key.
    pub fn from_json(text: &str) -> Result<Self> {
        let value: serde_json::Value = serde_json::from_str(&quote_non_finite_tokens(text))
            .map_err(|e| Error::Config(format!("config: not JSON: {e}")))?;
        // serde would also take a list of values for a section: Python's schema (and this one) wants mappings.
        let sections = value.as_object().ok_or_else(|| {
            Error::Config(format!(
                "config: must be a mapping of settings, got {value}"
            ))
        })?;
        for (key, section) in sections {
            if matches!(section, serde_json::Value::Array(_)) {
                return Err(Error::Config(format!(
                    "{key}: must be a mapping of settings, got {section}"
                )));
            }
        }
        let config: OdometryConfig = serde_path_to_error::deserialize(value)
            .map_err(|e| config_error(e.path().to_string(), e.inner()))?;
        config.validate()?;
        Ok(config)
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

    /// The config as JSON, unlimited settings written as Python's `json` writes them (`Infinity`), so that
    /// `dmlo run --config` reads it back.
    pub fn to_json(&self) -> String {
        let mut value = serde_json::to_value(self).expect("the config serialises");
        restore_infinities(&mut value, self);
        let text = serde_json::to_string_pretty(&value).expect("a JSON value serialises");
        text.replace(&format!("\"{INFINITY_JSON}\""), "Infinity")
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

/// A setting that may be infinite (no limit), never NaN or negative: in JSON a number or Python's
/// `Infinity`.
pub type Limit = f64;

mod checks;
mod json;

use json::{
    config_error, limit, optional_limit, quote_non_finite_tokens, restore_infinities, INFINITY_JSON,
};

#[cfg(test)]
mod tests;
