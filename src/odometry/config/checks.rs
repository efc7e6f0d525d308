//! The ranges of the config's settings: [`OdometryConfig::validate`] and the checks it runs, each error
//! naming the key.

use super::OdometryConfig;
use crate::coherence::MAX_RADIUS as MAX_COHERENCE_RADIUS;
use crate::error::{Error, Result};

impl OdometryConfig {
    /// Checks every setting against its range, as Python's schema does; the error names the first bad key.
    pub fn validate(&self) -> Result<()> {
        let m = &self.matching;
        fraction("matching.min_confidence", m.min_confidence)?;
        at_least_u("matching.max_matches", m.max_matches, 3)?;
        if let Some(v) = m.consistency_px {
            check(
                "matching.consistency_px",
                v,
                v >= 0.0 && !v.is_nan(),
                "a number >= 0 or null",
            )?;
        }
        if let Some(v) = m.coherence_px {
            positive("matching.coherence_px", v)?;
        }
        if m.coherence_radius > MAX_COHERENCE_RADIUS as u64 {
            return Err(Error::Config(format!(
                "matching.coherence_radius: must be an integer from 0 to {MAX_COHERENCE_RADIUS}, got {}",
                m.coherence_radius
            )));
        }
        let r = &self.ransac;
        positive("ransac.threshold", r.threshold)?;
        let c = r.confidence;
        check(
            "ransac.confidence",
            c,
            c > 0.0 && c < 1.0,
            "a number > 0 and < 1",
        )?;
        if !(1..=1_000_000).contains(&r.max_iterations) {
            return Err(Error::Config(format!(
                "ransac.max_iterations: must be an integer from 1 to 1000000, got {}",
                r.max_iterations
            )));
        }
        positive("ransac.ray_range_ratio", r.ray_range_ratio)?;
        let b = r.ray_bearing_threshold_deg;
        check(
            "ransac.ray_bearing_threshold_deg",
            b,
            (0.0..90.0).contains(&b),
            "a number >= 0 and < 90",
        )?;
        let v = r.min_vote;
        check(
            "ransac.min_vote",
            v,
            v > 0.0 && v <= 1.0,
            "a number > 0 and <= 1",
        )?;
        if let Some(v) = r.vote_voxel {
            positive("ransac.vote_voxel", v)?;
        }
        let mm = &self.motion_model;
        at_least_u("motion_model.min_inliers", mm.min_inliers, 3)?;
        non_negative("motion_model.min_inlier_votes", mm.min_inlier_votes)?;
        limit_value("motion_model.max_deviation", mm.max_deviation)?;
        limit_value("motion_model.max_deviation_deg", mm.max_deviation_deg)?;
        fraction("motion_model.guided_fraction", mm.guided_fraction)?;
        if let Some(gap) = mm.rematch_gap {
            at_least_u("motion_model.rematch_gap", gap, 1)?;
        }
        at_least_u("motion_model.prediction_horizon", mm.prediction_horizon, 1)?;
        if let Some(v) = mm.match_from_prediction_m {
            positive("motion_model.match_from_prediction_m", v)?;
        }
        if let Some(v) = mm.start_check_m {
            positive("motion_model.start_check_m", v)?;
        }
        if let Some(v) = mm.start_max_reverse_m {
            positive("motion_model.start_max_reverse_m", v)?;
        }
        if let Some(rounds) = mm.prediction_rounds {
            at_least_u("motion_model.prediction_rounds", rounds, 1)?;
        }
        finite(
            "deskew.reference_azimuth_deg",
            self.deskew.reference_azimuth_deg,
        )?;
        let p = &self.mapping;
        positive("mapping.voxel_size", p.voxel_size)?;
        at_least_u("mapping.max_scans", p.max_scans, 1)?;
        limit_value("mapping.keyframe_distance", p.keyframe_distance)?;
        limit_value("mapping.keyframe_angle_deg", p.keyframe_angle_deg)?;
        limit_value("mapping.ring_lock_distance", p.ring_lock_distance)?;
        limit_value(
            "mapping.motion_model_start_distance",
            p.motion_model_start_distance,
        )?;
        limit_value(
            "mapping.motion_model_start_angle_deg",
            p.motion_model_start_angle_deg,
        )?;
        non_negative("mapping.downsample", p.downsample)?;
        non_negative("mapping.downsample_far", p.downsample_far)?;
        limit_value("mapping.far_range", p.far_range)?;
        at_least_u("mapping.max_iterations", p.max_iterations, 1)?;
        let d = p.degeneracy_threshold;
        check(
            "mapping.degeneracy_threshold",
            d,
            (0.0..1.0).contains(&d),
            "a number >= 0 and < 1",
        )?;
        let d = p.rotation_degeneracy_threshold;
        check(
            "mapping.rotation_degeneracy_threshold",
            d,
            (0.0..1.0).contains(&d),
            "a number >= 0 and < 1",
        )?;
        let l = &self.large_motion;
        starts("large_motion.search_ahead_m", &l.search_ahead_m)?;
        starts("large_motion.search_yaw_deg", &l.search_yaw_deg)?;
        at_least_u("large_motion.max_rounds", l.max_rounds, 1)?;
        limit_value("large_motion.min_step", l.min_step)?;
        limit_value("large_motion.min_step_deg", l.min_step_deg)?;
        let t = self.moving_objects.threshold;
        check(
            "moving_objects.threshold",
            t,
            t > 0.0 && t < 1.0,
            "a number > 0 and < 1",
        )?;
        Ok(())
    }
}

fn check(key: &str, value: f64, ok: bool, what: &str) -> Result<()> {
    if ok {
        Ok(())
    } else {
        Err(Error::Config(format!(
            "{key}: must be {what}, got {}",
            shown(value)
        )))
    }
}

fn shown(value: f64) -> String {
    if value == f64::INFINITY {
        "Infinity".into()
    } else if value == f64::NEG_INFINITY {
        "-Infinity".into()
    } else {
        format!("{value}")
    }
}

fn finite(key: &str, value: f64) -> Result<()> {
    check(key, value, value.is_finite(), "a finite number")
}

fn positive(key: &str, value: f64) -> Result<()> {
    check(key, value, value.is_finite() && value > 0.0, "a number > 0")
}

fn non_negative(key: &str, value: f64) -> Result<()> {
    check(
        key,
        value,
        value.is_finite() && value >= 0.0,
        "a number >= 0",
    )
}

fn fraction(key: &str, value: f64) -> Result<()> {
    check(
        key,
        value,
        (0.0..=1.0).contains(&value),
        "a number >= 0 and <= 1",
    )
}

fn limit_value(key: &str, value: f64) -> Result<()> {
    check(
        key,
        value,
        value >= 0.0,
        "a number >= 0 (or Infinity: no limit)",
    )
}

fn at_least_u(key: &str, value: u64, least: u64) -> Result<()> {
    if value >= least {
        Ok(())
    } else {
        Err(Error::Config(format!(
            "{key}: must be an integer >= {least}, got {value}"
        )))
    }
}

fn starts(key: &str, values: &[f64]) -> Result<()> {
    if values.is_empty() || values.iter().any(|v| !v.is_finite()) {
        return Err(Error::Config(format!(
            "{key}: must be a non-empty list of finite numbers, got {values:?}"
        )));
    }
    Ok(())
}
