//! The reflectance scale of a sequence, chosen on its first usable scan, and the switch to the
//! range-only model for scans without usable reflectance.

use super::{FrameMatcher, Odometry};
use crate::error::{Error, Result};
use crate::odometry::config::ReflectanceScale;

impl<M: FrameMatcher> Odometry<M> {
    /// The reflectance scale of the sequence, chosen on the first scan with `min_points` finite points
    /// (`finite`: their reflectance; `None` before it); errors when the scans have no reflectance the
    /// model can use.
    pub(super) fn reflectance_for(
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
    pub(super) fn switch_to_range_only(&mut self, why: &str) -> Result<()> {
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

    pub(super) fn no_reflectance(&self, why: &str) -> Error {
        Error::invalid(
            "points",
            format!(
                "{why}, and the model reads reflectance: give the range-only model beside it \
                 (range_only/) to Odometry::with_range_only"
            ),
        )
    }
}

/// The scale a scan's finite reflectance values look like, and why ([`ReflectanceScale::Ignored`]: none
/// usable), as `dmlo.odometry.reflectance.detect`.
pub(super) fn detect_reflectance(values: &[f32]) -> (ReflectanceScale, String) {
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
        (ReflectanceScale::ZeroTo255, 255.0, "0–255"),
        (ReflectanceScale::ZeroTo65535, 65535.0, "0–65535"),
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
pub(super) fn normalised(mut cloud: Vec<[f32; 4]>, scale: ReflectanceScale) -> Vec<[f32; 4]> {
    let divisor: f32 = match scale {
        ReflectanceScale::Auto | ReflectanceScale::Unit => 1.0,
        ReflectanceScale::ZeroTo255 => 255.0,
        ReflectanceScale::ZeroTo65535 => 65535.0,
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
