//! Python's JSON as `dmlo run` writes it: the bare `Infinity` of an unlimited setting read and written, and
//! serde's errors turned into ones that name the key.

use serde::{Deserialize, Deserializer};

use super::OdometryConfig;
use crate::error::Error;

/// What Python's non-finite tokens become before serde reads the text: a string no finite setting accepts
/// (a control character no config holds; written in the JSON text by its escape).
const INFINITY_MARK: &str = "\u{1}Infinity";
const NEGATIVE_INFINITY_MARK: &str = "\u{1}-Infinity";
const NAN_MARK: &str = "\u{1}NaN";
pub(super) const INFINITY_JSON: &str = "\\u0001Infinity";
const NEGATIVE_INFINITY_JSON: &str = "\\u0001-Infinity";
const NAN_JSON: &str = "\\u0001NaN";

/// The text with Python's bare `Infinity`, `-Infinity` and `NaN` (outside strings) turned into marked strings,
/// which [`limit`] reads and every other setting refuses.
pub(super) fn quote_non_finite_tokens(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    let mut in_string = false;
    while let Some(c) = rest.chars().next() {
        if in_string {
            match c {
                '\\' => {
                    let escaped: String = rest.chars().take(2).collect();
                    out.push_str(&escaped);
                    rest = &rest[escaped.len()..];
                    continue;
                }
                '"' => in_string = false,
                _ => {}
            }
        } else if c == '"' {
            in_string = true;
        } else {
            let token = [
                ("-Infinity", NEGATIVE_INFINITY_JSON),
                ("Infinity", INFINITY_JSON),
                ("NaN", NAN_JSON),
            ]
            .into_iter()
            .find(|(token, _)| rest.starts_with(token));
            if let Some((token, mark)) = token {
                out.push('"');
                out.push_str(mark);
                out.push('"');
                rest = &rest[token.len()..];
                continue;
            }
        }
        out.push(c);
        rest = &rest[c.len_utf8()..];
    }
    out
}

/// A number or the marked `Infinity`; `-Infinity` and `NaN` are refused here, with their names.
pub(super) fn limit<'de, D: Deserializer<'de>>(
    deserializer: D,
) -> std::result::Result<f64, D::Error> {
    struct LimitVisitor;
    impl serde::de::Visitor<'_> for LimitVisitor {
        type Value = f64;
        fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            f.write_str("a number >= 0 (or Infinity: no limit)")
        }
        fn visit_f64<E: serde::de::Error>(self, v: f64) -> std::result::Result<f64, E> {
            Ok(v)
        }
        fn visit_u64<E: serde::de::Error>(self, v: u64) -> std::result::Result<f64, E> {
            Ok(v as f64)
        }
        fn visit_i64<E: serde::de::Error>(self, v: i64) -> std::result::Result<f64, E> {
            Ok(v as f64)
        }
        fn visit_str<E: serde::de::Error>(self, v: &str) -> std::result::Result<f64, E> {
            if v == INFINITY_MARK {
                return Ok(f64::INFINITY);
            }
            Err(E::custom(format!(
                "must be a number >= 0 (or Infinity: no limit), got {}",
                shown_mark(v)
            )))
        }
    }
    deserializer.deserialize_any(LimitVisitor)
}

pub(super) fn optional_limit<'de, D: Deserializer<'de>>(
    deserializer: D,
) -> std::result::Result<Option<f64>, D::Error> {
    #[derive(Deserialize)]
    struct Wrapped(#[serde(deserialize_with = "limit")] f64);
    Ok(Option::<Wrapped>::deserialize(deserializer)?.map(|Wrapped(v)| v))
}

fn shown_mark(mark: &str) -> String {
    match mark {
        INFINITY_MARK => "Infinity".into(),
        NEGATIVE_INFINITY_MARK => "-Infinity".into(),
        NAN_MARK => "NaN".into(),
        other => format!("{other:?}"),
    }
}

/// The error of a key, serde's words with Python's non-finite tokens named as written.
pub(super) fn config_error(path: String, error: &serde_json::Error) -> Error {
    let mut message = error.to_string();
    for mark in [NEGATIVE_INFINITY_MARK, INFINITY_MARK, NAN_MARK] {
        message = message.replace(
            &format!("string {mark:?}"),
            &format!("{} (not finite)", shown_mark(mark)),
        );
        message = message.replace(&format!("\"{mark}\""), &shown_mark(mark));
    }
    for (serde_word, ours) in [
        ("expected f64", "expected a number"),
        ("expected u64", "expected an integer >= 0"),
    ] {
        message = message.replace(serde_word, ours);
    }
    let key = if path == "." || path.is_empty() {
        "config".to_string()
    } else {
        path
    };
    Error::Config(format!("{key}: {message}"))
}

/// The unlimited settings of `config` written back as the mark that [`OdometryConfig::to_json`] turns into
/// `Infinity` (serde_json writes a non-finite number as `null`, which would read back as "no setting").
pub(super) fn restore_infinities(value: &mut serde_json::Value, config: &OdometryConfig) {
    let limits: [(&str, &str, f64); 11] = [
        (
            "motion_model",
            "max_deviation",
            config.motion_model.max_deviation,
        ),
        (
            "motion_model",
            "max_deviation_deg",
            config.motion_model.max_deviation_deg,
        ),
        (
            "mapping",
            "keyframe_distance",
            config.mapping.keyframe_distance,
        ),
        (
            "mapping",
            "keyframe_angle_deg",
            config.mapping.keyframe_angle_deg,
        ),
        (
            "mapping",
            "ring_lock_distance",
            config.mapping.ring_lock_distance,
        ),
        (
            "mapping",
            "motion_model_start_distance",
            config.mapping.motion_model_start_distance,
        ),
        (
            "mapping",
            "motion_model_start_angle_deg",
            config.mapping.motion_model_start_angle_deg,
        ),
        ("mapping", "far_range", config.mapping.far_range),
        ("large_motion", "min_step", config.large_motion.min_step),
        (
            "large_motion",
            "min_step_deg",
            config.large_motion.min_step_deg,
        ),
        (
            "matching",
            "consistency_px",
            config.matching.consistency_px.unwrap_or(0.0),
        ),
    ];
    for (section, key, setting) in limits {
        if setting == f64::INFINITY {
            value[section][key] = serde_json::Value::String(INFINITY_MARK.into());
        }
    }
}
