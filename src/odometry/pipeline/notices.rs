//! What the odometry says about the scans it is given, once each (a reflectance notice again when its
//! choice changes): carried by the diagnostics of the frame it arose in, for the caller to pass on
//! (Python turns each into a warning of its category).

use serde::ser::{Serialize, SerializeStruct, Serializer};

use crate::odometry::config::schema::Named;
use crate::odometry::config::ReflectanceScale;

/// A scan that fills less of the cylinder image than this was taken by a sensor the model was not made
/// for: an HDL-64E, the sensor of the bundled model, fills three quarters of KITTI's image or more, and a
/// network only knows the images it was trained on.
pub const LOW_IMAGE_FILL: f64 = 0.35;

/// One thing the odometry says about the scans.
#[derive(Debug, Clone, PartialEq)]
pub enum Notice {
    /// The reflectance is divided by its scale's top for the model's [0, 1] scale (`why`: the values
    /// seen, or the config).
    ReflectanceScaled {
        /// The scale.
        scale: ReflectanceScale,
        /// Why this scale.
        why: String,
    },
    /// No usable reflectance: the range-only model runs from this scan on (`scan`: the index of a later
    /// scan that moved it there; `None`: from the first).
    RangeOnlyModel {
        /// The scan that moved the odometry there, when not the first.
        scan: Option<usize>,
        /// Why no reflectance is used.
        why: String,
    },
    /// No usable reflectance and no range-only model: the model runs on zero reflectance, images it never
    /// saw, so its poses cannot be trusted.
    ZeroReflectance {
        /// The scan that moved the odometry there, when not the first.
        scan: Option<usize>,
        /// Why no reflectance is used.
        why: String,
    },
    /// A scan's reflectance is plainly on another scale than the one guessed on an earlier scan (within
    /// [0, 1] under 0–255 or 0–65535, or well beyond the scale guessed): the scan is read on its own.
    ReflectanceRescaled {
        /// The scan.
        scan: usize,
        /// What its values look like.
        values: String,
        /// The scale it is read on.
        scale: ReflectanceScale,
        /// The scale chosen before.
        chosen: ReflectanceScale,
        /// Why that scale.
        why: String,
    },
    /// A pair registered ([`super::Odometry::register_pair`]) with fewer RANSAC inliers than a motion
    /// needs: its motion is not to be trusted (the identity when there are none).
    TooFewInliers {
        /// RANSAC's inliers.
        inliers: usize,
        /// `motion_model.min_inliers`.
        needed: usize,
        /// Matched as a large motion.
        large_motion: bool,
    },
    /// The model is range-only: the scans' reflectance is not read.
    ReflectanceUnused,
    /// A scan's reflectance reaches beyond the scale chosen: it is clipped to the scale's top.
    ReflectanceClipped {
        /// The scan.
        scan: usize,
        /// Its largest reflectance over the scale's top.
        largest: f64,
        /// The scale chosen.
        scale: ReflectanceScale,
        /// Why that scale.
        why: String,
    },
    /// A scan's timestamp is not after the previous scan's: the scan is taken for the next frame.
    TimestampNotAfter {
        /// The scan's timestamp.
        timestamp: f64,
        /// The previous scan's.
        previous: f64,
    },
    /// The scans fill far less of the model's cylinder image than those of the sensor it was trained
    /// for ([`LOW_IMAGE_FILL`]): its poses cannot be trusted.
    SensorMismatch {
        /// The fraction of the image's cells the scan filled.
        image_fill: f64,
        /// The image's rows.
        height: usize,
        /// Its columns.
        width: usize,
    },
}

impl Notice {
    /// The notice's name: `reflectance_scaled`, `range_only_model`, `zero_reflectance`,
    /// `reflectance_rescaled`, `too_few_inliers`, `reflectance_unused`, `reflectance_clipped`,
    /// `timestamp_not_after` or `sensor_mismatch`.
    pub fn kind(&self) -> &'static str {
        match self {
            Notice::ReflectanceScaled { .. } => "reflectance_scaled",
            Notice::RangeOnlyModel { .. } => "range_only_model",
            Notice::ZeroReflectance { .. } => "zero_reflectance",
            Notice::ReflectanceRescaled { .. } => "reflectance_rescaled",
            Notice::TooFewInliers { .. } => "too_few_inliers",
            Notice::ReflectanceUnused => "reflectance_unused",
            Notice::ReflectanceClipped { .. } => "reflectance_clipped",
            Notice::TimestampNotAfter { .. } => "timestamp_not_after",
            Notice::SensorMismatch { .. } => "sensor_mismatch",
        }
    }

    /// What the notice says, in one line.
    pub fn message(&self) -> String {
        let at = |scan: &Option<usize>| scan.map_or(String::new(), |scan| format!("scan {scan}: "));
        match self {
            Notice::ReflectanceScaled { scale, why } => format!(
                "reflectance: {why}: divided by {} for the model's [0, 1] scale",
                divisor(*scale)
            ),
            Notice::RangeOnlyModel { scan, why } => {
                format!("reflectance: {}{why}: the range-only model runs", at(scan))
            }
            Notice::ZeroReflectance { scan, why } => format!(
                "reflectance: {}{why}, and the model has no range-only model beside it (range_only/): it \
                 runs on zero reflectance, so these poses cannot be trusted. Set reflectance in the config \
                 if the scans have one on another scale, or train and export a range-only model (dmlo train \
                 --no-reflectance; dmlo export RUN --out MODEL/range_only)",
                at(scan)
            ),
            Notice::ReflectanceRescaled {
                scan,
                values,
                scale,
                chosen,
                why,
            } => format!(
                "reflectance: scan {scan}: {values}, not the {} scale chosen before ({why}): read on \
                 {}; the config's reflectance (unit, 0-255, 0-65535, none) sets one scale for every \
                 scan",
                chosen.name(),
                scale.name()
            ),
            Notice::TooFewInliers {
                inliers,
                needed,
                large_motion,
            } => format!(
                "the pair has {inliers} RANSAC inliers, fewer than the {needed} a motion needs \
                 (motion_model.min_inliers): its motion is not to be trusted{}{}",
                if *inliers == 0 {
                    " (the identity: RANSAC found none)"
                } else {
                    ""
                },
                if *large_motion {
                    ""
                } else {
                    "; far apart? try large_motion (dmlo register --large-motion, or --loop)"
                }
            ),
            Notice::ReflectanceUnused => {
                "reflectance: the model is range-only: the scans' reflectance is not used".into()
            }
            Notice::ReflectanceClipped {
                scan,
                largest,
                scale,
                why,
            } => format!(
                "reflectance: scan {scan} reaches {}× the top of the {} scale chosen ({why}): clipped to \
                 it; the config's reflectance (unit, 0-255, 0-65535, none) sets the scale",
                shortest(*largest),
                scale.name()
            ),
            Notice::TimestampNotAfter {
                timestamp,
                previous,
            } => format!(
                "scan timestamp {timestamp:?} is not after the previous scan's {previous:?}: taken for \
                 the next frame"
            ),
            Notice::SensorMismatch {
                image_fill,
                height,
                width,
            } => format!(
                "the scans fill only {:.0} % of the model's {height}×{width} cylinder image (the HDL-64E \
                 scans it was trained on fill 75–82 %): it was not made for this sensor, so its poses \
                 cannot be trusted; train a model on drives of this sensor (dmlo train, dmlo simulate \
                 --sensor)",
                100.0 * image_fill
            ),
        }
    }
}

/// A notice in the diagnostics' JSON: its kind and its message.
impl Serialize for Notice {
    fn serialize<S: Serializer>(&self, serializer: S) -> std::result::Result<S::Ok, S::Error> {
        let mut state = serializer.serialize_struct("Notice", 2)?;
        state.serialize_field("kind", self.kind())?;
        state.serialize_field("message", &self.message())?;
        state.end()
    }
}

/// The top of a scale: what its values are divided by for the model's [0, 1] scale.
pub(super) fn divisor(scale: ReflectanceScale) -> f32 {
    match scale {
        ReflectanceScale::ZeroTo255 => 255.0,
        ReflectanceScale::ZeroTo65535 => 65535.0,
        ReflectanceScale::Auto | ReflectanceScale::Unit | ReflectanceScale::Ignored => 1.0,
    }
}

/// A number in its shortest form, as in a message: `4`, `0.5`.
fn shortest(value: f64) -> String {
    format!("{}", (value * 1e6).round() / 1e6)
}
