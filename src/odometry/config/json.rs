//! The config's JSON as Python's `json` writes it: the bare `Infinity` of an unlimited setting (and
//! `-Infinity`, `NaN`), which JSON itself has no words for, read and written.
//!
//! serde_json holds no non-finite number, so before the text is parsed each such token becomes a marked
//! string that no setting takes as text (a control character no config holds), and the settings' rules
//! read the marks as the numbers they stand for.

use serde_json::Value;

const INFINITY_MARK: &str = "\u{1}Infinity";
const NEGATIVE_INFINITY_MARK: &str = "\u{1}-Infinity";
const NAN_MARK: &str = "\u{1}NaN";

/// Python's tokens and their marks, `-Infinity` before `Infinity` so that the longer token is found first.
const TOKENS: [(&str, &str); 3] = [
    ("-Infinity", NEGATIVE_INFINITY_MARK),
    ("Infinity", INFINITY_MARK),
    ("NaN", NAN_MARK),
];

/// The text with Python's bare `Infinity`, `-Infinity` and `NaN` (outside strings) turned into marked
/// strings.
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
        } else if let Some((token, mark)) = TOKENS.iter().find(|(token, _)| rest.starts_with(token))
        {
            out.push_str(&Value::String((*mark).into()).to_string());
            rest = &rest[token.len()..];
            continue;
        }
        out.push(c);
        rest = &rest[c.len_utf8()..];
    }
    out
}

/// The JSON text of a value holding marks, each mark written back as Python's bare token.
pub(super) fn with_tokens(text: String) -> String {
    TOKENS.iter().fold(text, |text, (token, mark)| {
        text.replace(&Value::String((*mark).into()).to_string(), token)
    })
}

/// A number as the config's JSON holds it: finite, or one of the marked non-finite tokens.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum FiniteOrMarked {
    Finite(f64),
    Infinity,
    NegativeInfinity,
    NaN,
}

impl FiniteOrMarked {
    /// The number a JSON value holds (`None`: not a number).
    pub(super) fn of(value: &Value) -> Option<Self> {
        match value {
            Value::Number(n) => n.as_f64().map(FiniteOrMarked::Finite),
            Value::String(s) => match s.as_str() {
                INFINITY_MARK => Some(FiniteOrMarked::Infinity),
                NEGATIVE_INFINITY_MARK => Some(FiniteOrMarked::NegativeInfinity),
                NAN_MARK => Some(FiniteOrMarked::NaN),
                _ => None,
            },
            _ => None,
        }
    }

    pub(super) fn from_f64(value: f64) -> Self {
        match value {
            v if v.is_nan() => FiniteOrMarked::NaN,
            f64::INFINITY => FiniteOrMarked::Infinity,
            f64::NEG_INFINITY => FiniteOrMarked::NegativeInfinity,
            v => FiniteOrMarked::Finite(v),
        }
    }

    pub(super) fn to_f64(self) -> f64 {
        match self {
            FiniteOrMarked::Finite(v) => v,
            FiniteOrMarked::Infinity => f64::INFINITY,
            FiniteOrMarked::NegativeInfinity => f64::NEG_INFINITY,
            FiniteOrMarked::NaN => f64::NAN,
        }
    }

    pub(super) fn to_value(self) -> Value {
        let mark = match self {
            FiniteOrMarked::Finite(v) => {
                return serde_json::Number::from_f64(v).map_or(Value::Null, Value::Number)
            }
            FiniteOrMarked::Infinity => INFINITY_MARK,
            FiniteOrMarked::NegativeInfinity => NEGATIVE_INFINITY_MARK,
            FiniteOrMarked::NaN => NAN_MARK,
        };
        Value::String(mark.into())
    }
}

/// A number as written: Python's token for a non-finite one, every digit of an integer too large for
/// the crate's integers (which JSON's parser reads as a float).
pub(super) fn shown_number(value: &Value) -> String {
    match FiniteOrMarked::of(value) {
        Some(FiniteOrMarked::Finite(v))
            if !value.is_u64()
                && !value.is_i64()
                && v.abs() >= 2f64.powi(63)
                && v.fract() == 0.0 =>
        {
            format!("{v:.0}")
        }
        Some(FiniteOrMarked::Infinity) => "Infinity".into(),
        Some(FiniteOrMarked::NegativeInfinity) => "-Infinity".into(),
        Some(FiniteOrMarked::NaN) => "NaN".into(),
        _ => value.to_string(),
    }
}
