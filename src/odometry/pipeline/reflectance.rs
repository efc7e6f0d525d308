//! The reflectance scale of a sequence, chosen on its first usable scan, and the switch to the
//! range-only model for scans without usable reflectance.

use super::notices::{divisor, Notice};
use super::{FrameMatcher, Odometry};
use crate::error::{Error, Result};
use crate::odometry::config::schema::Named;
use crate::odometry::config::ReflectanceScale;

impl<M: FrameMatcher> Odometry<M> {
    /// The reflectance scale of the sequence, chosen on the first scan with `min_points` finite points
    /// (`values`: their reflectance, `None` for a scan without the channel; `finite_points` of them) with
    /// a notice when the scans are not on the model's scale; `None` before it. A later scan without usable
    /// reflectance moves the odometry to the range-only model, and one beyond the scale chosen is clipped,
    /// each with a notice (`scan`: its index). Errors when the scans have no reflectance the model can use.
    pub(super) fn reflectance_for(
        &mut self,
        values: Option<&[f32]>,
        finite_points: usize,
        min_points: usize,
        scan: usize,
    ) -> Result<Option<ReflectanceScale>> {
        if finite_points < min_points {
            // Not matched (too few points): it decides nothing, and its reflectance is never read.
            return Ok(self.reflectance);
        }
        let (detected, detected_why) = detect_reflectance(values);
        if let Some(chosen) = self.reflectance {
            if chosen != ReflectanceScale::Ignored && detected == ReflectanceScale::Ignored {
                self.switch_to_range_only(Some(scan), detected_why)?;
                self.reflectance = Some(ReflectanceScale::Ignored);
            } else if self.scan_scale(chosen, detected, values) != chosen {
                let scale = self.scan_scale(chosen, detected, values);
                let notice = Notice::ReflectanceRescaled {
                    scan,
                    values: detected_why,
                    scale,
                    chosen,
                    why: self.reflectance_reason.clone(),
                };
                self.say_once(|said| &mut said.rescaled, notice);
                return Ok(Some(scale));
            } else {
                self.notice_clipping(values, scan);
            }
            return Ok(self.reflectance);
        }
        let (choice, why) = self.first_choice(detected, detected_why);
        if !self.matcher.uses_reflectance() {
            self.notices.push(Notice::ReflectanceUnused);
        } else if choice == ReflectanceScale::Ignored {
            self.switch_to_range_only(None, why.clone())?;
        } else if choice != ReflectanceScale::Unit {
            self.notices.push(Notice::ReflectanceScaled {
                scale: choice,
                why: why.clone(),
            });
        }
        self.reflectance = Some(choice);
        self.reflectance_reason = why;
        self.notice_clipping(values, scan);
        Ok(Some(choice))
    }

    /// The scale of the first deciding scan, whose values look like `detected`, and why: none for a
    /// range-only model, else the config's setting, unless that is "auto" or the values are unusable.
    pub(super) fn first_choice(
        &self,
        detected: ReflectanceScale,
        detected_why: String,
    ) -> (ReflectanceScale, String) {
        if !self.matcher.uses_reflectance() {
            return (ReflectanceScale::Ignored, "the model is range-only".into());
        }
        match (self.config.reflectance, detected) {
            (ReflectanceScale::Auto, _) | (_, ReflectanceScale::Ignored) => {
                (detected, detected_why)
            }
            (setting, _) => (
                setting,
                format!("the config says reflectance {}", setting.name()),
            ),
        }
    }

    /// The scale a scan whose values (`values`) look like `detected` is read on, once `chosen` is the
    /// sequence's: `chosen`, unless it was guessed from the values (the config's `"auto"`) and this scan
    /// is plainly on another scale — then its own: its values all lie within [0, 1] while `chosen` is
    /// 0–255 or 0–65535 (divided by that top they would be nearly black; no real scan of such a sensor
    /// stays within [0, 1]), or they reach beyond `chosen` into the upper half of a larger scale (clipped
    /// they would be nearly all white). Values a little beyond the scale chosen stay clipped to it.
    pub(super) fn scan_scale(
        &self,
        chosen: ReflectanceScale,
        detected: ReflectanceScale,
        values: Option<&[f32]>,
    ) -> ReflectanceScale {
        let rank = |scale| match scale {
            ReflectanceScale::Unit => Some(0),
            ReflectanceScale::ZeroTo255 => Some(1),
            ReflectanceScale::ZeroTo65535 => Some(2),
            ReflectanceScale::Auto | ReflectanceScale::Ignored => None,
        };
        if self.config.reflectance != ReflectanceScale::Auto {
            return chosen;
        }
        let (Some(chosen_rank), Some(detected_rank)) = (rank(chosen), rank(detected)) else {
            return chosen;
        };
        let largest = values
            .unwrap_or_default()
            .iter()
            .fold(f32::NEG_INFINITY, |a, &b| a.max(b));
        let below = detected == ReflectanceScale::Unit && chosen_rank > 0;
        let above = detected_rank > chosen_rank && largest > 0.5 * divisor(detected);
        if below || above {
            detected
        } else {
            chosen
        }
    }

    /// A notice, the first time a scan's reflectance reaches beyond the scale chosen (it is clipped).
    fn notice_clipping(&mut self, values: Option<&[f32]>, scan: usize) {
        let Some(scale) = self.reflectance.filter(|&s| s != ReflectanceScale::Ignored) else {
            return;
        };
        if self.said.clipping {
            return;
        }
        let largest = values
            .unwrap_or_default()
            .iter()
            .fold(f32::NEG_INFINITY, |a, &b| a.max(b));
        let largest = f64::from(largest / divisor(scale));
        if largest > 1.0 {
            self.said.clipping = true;
            self.notices.push(Notice::ReflectanceClipped {
                scan,
                largest,
                scale,
                why: self.reflectance_reason.clone(),
            });
        }
    }

    /// Runs the range-only model from now on, the reference scan encoded again by it, with a notice
    /// (`scan`: a later scan that moved it there); without one, the model runs on zero reflectance when
    /// that is allowed (with a notice that its poses cannot be trusted), else an error naming `why`.
    pub(super) fn switch_to_range_only(&mut self, scan: Option<usize>, why: String) -> Result<()> {
        let Some(mut range_only) = self.range_only.take() else {
            if self.zero_reflectance_allowed {
                self.notices.push(Notice::ZeroReflectance { scan, why });
                return Ok(());
            }
            return Err(self.no_reflectance(&why));
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
        std::mem::swap(&mut self.matcher, &mut range_only);
        self.range_only = Some(range_only);
        self.runs_range_only = true;
        self.notices.push(Notice::RangeOnlyModel { scan, why });
        Ok(())
    }

    pub(super) fn no_reflectance(&self, why: &str) -> Error {
        Error::invalid(
            "points",
            format!(
                "{why}, and the model reads reflectance: put a range-only model in the model folder's \
                 range_only/ (Odometry::open attaches it), or give one to Odometry::with_range_only"
            ),
        )
    }
}

/// The scale a scan's finite reflectance values look like (`None`: a scan without the channel), and why
/// ([`ReflectanceScale::Ignored`]: none usable).
pub(super) fn detect_reflectance(values: Option<&[f32]>) -> (ReflectanceScale, String) {
    let Some(values) = values else {
        return (
            ReflectanceScale::Ignored,
            "the scans have no reflectance (N×3 points)".into(),
        );
    };
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

/// The cloud's reflectance divided by the scale's top and clipped to [0, 1] (zeros when ignored).
pub(super) fn normalised(mut cloud: Vec<[f32; 4]>, scale: ReflectanceScale) -> Vec<[f32; 4]> {
    if scale == ReflectanceScale::Ignored {
        cloud.iter_mut().for_each(|p| p[3] = 0.0);
        return cloud;
    }
    let divisor = divisor(scale);
    for p in &mut cloud {
        p[3] = (p[3] / divisor).clamp(0.0, 1.0);
    }
    cloud
}
