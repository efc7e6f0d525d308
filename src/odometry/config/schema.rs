//! The schema of the odometry's config: every setting declared once ([`settings!`], used in
//! `odometry/config.rs`) with its type, default, rule and doc, and what reads that declaration: the
//! checks of a config given as JSON (every bad key named in one message, with a suggestion for a
//! misspelt one) and the description that `dmlo`'s Python classes are made from.

use serde_json::{Map, Value};

use super::json::{shown_number, FiniteOrMarked};

/// What a setting accepts. A number's bounds are written as the messages say them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Rule {
    /// `true` or `false`.
    Flag,
    /// An integer from `min` to `max` (`u64::MAX`: no upper limit but the crate's integers').
    Integer {
        /// The least value.
        min: u64,
        /// The largest value.
        max: u64,
    },
    /// A number within its bounds; `unlimited`: it may also be `Infinity` (no limit).
    Number {
        /// The lower bound, if any.
        lower: Option<Bound>,
        /// The upper bound, if any.
        upper: Option<Bound>,
        /// `Infinity` is accepted.
        unlimited: bool,
    },
    /// One of these names.
    Choice(&'static [&'static str]),
    /// A non-empty list of finite numbers.
    FiniteList,
    /// `null` (the setting's own default rule, or "never"), or what the inner rule accepts.
    Optional(&'static Rule),
}

/// A bound of a [`Rule::Number`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Bound {
    /// `> value`
    Above(f64),
    /// `>= value`
    AtLeast(f64),
    /// `< value`
    Below(f64),
    /// `<= value`
    AtMost(f64),
}

impl Bound {
    fn holds(self, value: f64) -> bool {
        match self {
            Bound::Above(b) => value > b,
            Bound::AtLeast(b) => value >= b,
            Bound::Below(b) => value < b,
            Bound::AtMost(b) => value <= b,
        }
    }

    fn describe(self) -> String {
        let (op, b) = match self {
            Bound::Above(b) => (">", b),
            Bound::AtLeast(b) => (">=", b),
            Bound::Below(b) => ("<", b),
            Bound::AtMost(b) => ("<=", b),
        };
        format!("{op} {b}")
    }
}

/// Any finite number.
pub const FINITE: Rule = Rule::Number {
    lower: None,
    upper: None,
    unlimited: false,
};
/// A number > 0.
pub const POSITIVE: Rule = Rule::Number {
    lower: Some(Bound::Above(0.0)),
    upper: None,
    unlimited: false,
};
/// A number >= 0.
pub const NON_NEGATIVE: Rule = Rule::Number {
    lower: Some(Bound::AtLeast(0.0)),
    upper: None,
    unlimited: false,
};
/// A number >= 0, or `Infinity`: no limit.
pub const LIMIT: Rule = Rule::Number {
    lower: Some(Bound::AtLeast(0.0)),
    upper: None,
    unlimited: true,
};
/// A number from 0 to 1.
pub const FRACTION: Rule = Rule::Number {
    lower: Some(Bound::AtLeast(0.0)),
    upper: Some(Bound::AtMost(1.0)),
    unlimited: false,
};
/// A number strictly between 0 and 1.
pub const OPEN_FRACTION: Rule = Rule::Number {
    lower: Some(Bound::Above(0.0)),
    upper: Some(Bound::Below(1.0)),
    unlimited: false,
};
/// A number from 0 up to, not including, 1.
pub const BELOW_ONE: Rule = Rule::Number {
    lower: Some(Bound::AtLeast(0.0)),
    upper: Some(Bound::Below(1.0)),
    unlimited: false,
};
/// Any integer >= 0.
pub const COUNT: Rule = Rule::Integer {
    min: 0,
    max: u64::MAX,
};
/// Any integer >= 1.
pub const AT_LEAST_ONE: Rule = Rule::Integer {
    min: 1,
    max: u64::MAX,
};
/// Any integer >= 3: a rigid motion needs three matches.
pub const AT_LEAST_THREE: Rule = Rule::Integer {
    min: 3,
    max: u64::MAX,
};

impl Rule {
    /// Whether `value` (a config's JSON, non-finite numbers marked) fits the rule.
    pub fn accepts(&self, value: &Value) -> bool {
        match *self {
            Rule::Flag => value.is_boolean(),
            Rule::Integer { min, max } => value.as_u64().is_some_and(|v| (min..=max).contains(&v)),
            Rule::Number {
                lower,
                upper,
                unlimited,
            } => match FiniteOrMarked::of(value) {
                Some(FiniteOrMarked::Finite(v)) => {
                    lower.is_none_or(|b| b.holds(v)) && upper.is_none_or(|b| b.holds(v))
                }
                Some(FiniteOrMarked::Infinity) => unlimited && upper.is_none(),
                _ => false,
            },
            Rule::Choice(names) => value.as_str().is_some_and(|s| names.contains(&s)),
            Rule::FiniteList => value.as_array().is_some_and(|items| {
                !items.is_empty()
                    && items
                        .iter()
                        .all(|v| matches!(FiniteOrMarked::of(v), Some(FiniteOrMarked::Finite(_))))
            }),
            Rule::Optional(inner) => value.is_null() || inner.accepts(value),
        }
    }

    /// What the rule accepts, in words ("a number > 0", "an integer from 1 to 1000000", "true or
    /// false"), as said to `value`: the crate's integer limit only to an integer beyond it, "finite" to
    /// a number that is not.
    pub fn describe(&self, value: &Value) -> String {
        match *self {
            Rule::Flag => "true or false".into(),
            Rule::Integer { min, max } => {
                let beyond = value.as_f64().is_some_and(|v| v >= u64::MAX as f64);
                if max == u64::MAX && !beyond {
                    format!("an integer >= {min}")
                } else if max == u64::MAX {
                    format!("an integer from {min} to 2^64 - 1")
                } else {
                    format!("an integer from {min} to {max}")
                }
            }
            Rule::Number {
                lower,
                upper,
                unlimited,
            } => {
                let bounds: Vec<String> =
                    lower.iter().chain(&upper).map(|b| b.describe()).collect();
                let not_finite = matches!(
                    FiniteOrMarked::of(value),
                    Some(
                        FiniteOrMarked::Infinity
                            | FiniteOrMarked::NegativeInfinity
                            | FiniteOrMarked::NaN
                    )
                );
                let number = if bounds.is_empty() || (not_finite && !unlimited) {
                    "a finite number"
                } else {
                    "a number"
                };
                let mut text = [number.to_string(), bounds.join(" and ")].join(" ");
                if unlimited {
                    text.push_str(" or Infinity (no limit)");
                }
                text.trim_end().to_string()
            }
            Rule::Choice(names) => format!("one of {}", names.join(", ")),
            Rule::FiniteList => "a non-empty list of finite numbers".into(),
            Rule::Optional(inner) => format!("{} or null", inner.describe(value)),
        }
    }

    /// The type a setting of this rule holds, as the schema names it for other languages: `bool`, `int`,
    /// `float`, `str` or `list[float]`.
    pub fn value_type(&self) -> &'static str {
        match self {
            Rule::Flag => "bool",
            Rule::Integer { .. } => "int",
            Rule::Number { .. } => "float",
            Rule::Choice(_) => "str",
            Rule::FiniteList => "list[float]",
            Rule::Optional(inner) => inner.value_type(),
        }
    }
}

/// One setting as the schema declares it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Setting {
    /// Its key in its section.
    pub key: &'static str,
    /// What it accepts.
    pub rule: Rule,
    /// What it does, and why (the doc comment of its declaration).
    pub doc: &'static str,
}

/// A value as a config's message shows it: JSON's notation, Python's non-finite tokens as written,
/// cut short when long.
pub fn shown(value: &Value) -> String {
    let text = match value {
        Value::Number(_) | Value::String(_) if FiniteOrMarked::of(value).is_some() => {
            shown_number(value)
        }
        Value::Array(items) => {
            format!(
                "[{}]",
                items.iter().map(shown).collect::<Vec<_>>().join(", ")
            )
        }
        Value::Object(map) => format!(
            "{{{}}}",
            map.iter()
                .map(|(k, v)| format!("{}: {}", Value::String(k.clone()), shown(v)))
                .collect::<Vec<_>>()
                .join(", ")
        ),
        other => other.to_string(),
    };
    if text.chars().count() <= 60 {
        text
    } else {
        text.chars().take(57).chain("...".chars()).collect()
    }
}

/// The messages of every setting of one section (`prefix`: `"ransac."`, or `""` at the top level) that
/// does not fit its rule, and of every key the section does not have, in the declaration's order and
/// then the given one. `sections`: the keys that hold sections (checked by the caller).
pub(super) fn section_errors(
    prefix: &str,
    values: &Map<String, Value>,
    settings: &[Setting],
    sections: &[&str],
    errors: &mut Vec<String>,
) {
    for setting in settings {
        if let Some(value) = values.get(setting.key) {
            if !setting.rule.accepts(value) {
                errors.push(format!(
                    "{prefix}{}: must be {}, got {}",
                    setting.key,
                    setting.rule.describe(value),
                    shown(value)
                ));
            }
        }
    }
    let known: Vec<&str> = sections
        .iter()
        .copied()
        .chain(settings.iter().map(|s| s.key))
        .collect();
    for key in values.keys().filter(|k| !known.contains(&k.as_str())) {
        errors.push(unknown_key(prefix, key, &known));
    }
}

/// The message of a key the section does not have: the closest known key when one is close, else the
/// section's keys.
fn unknown_key(prefix: &str, key: &str, known: &[&str]) -> String {
    let closest = known
        .iter()
        .map(|k| (strsim::normalized_damerau_levenshtein(key, k), *k))
        .filter(|(similarity, _)| *similarity >= 0.6)
        .max_by(|a, b| a.0.total_cmp(&b.0));
    match closest {
        Some((_, k)) => format!("{prefix}{key}: no such setting (did you mean {prefix}{k}?)"),
        None => {
            let section = prefix.strip_suffix('.').unwrap_or("config");
            format!(
                "{prefix}{key}: no such setting; {section} has {}",
                known.join(", ")
            )
        }
    }
}

/// A setting's value in the config's JSON, and back: what [`settings!`] reads and writes each field
/// with. Non-finite numbers travel as the marks of `config/json.rs`.
pub trait SettingValue: Sized {
    /// The value as the config's JSON holds it.
    fn to_setting(&self) -> Value;
    /// The value of a JSON value that its rule accepted; `None` when it cannot hold one.
    fn from_setting(value: &Value) -> Option<Self>;
}

impl SettingValue for bool {
    fn to_setting(&self) -> Value {
        Value::Bool(*self)
    }
    fn from_setting(value: &Value) -> Option<Self> {
        value.as_bool()
    }
}

impl SettingValue for u64 {
    fn to_setting(&self) -> Value {
        Value::from(*self)
    }
    fn from_setting(value: &Value) -> Option<Self> {
        value.as_u64()
    }
}

impl SettingValue for f64 {
    fn to_setting(&self) -> Value {
        FiniteOrMarked::from_f64(*self).to_value()
    }
    fn from_setting(value: &Value) -> Option<Self> {
        FiniteOrMarked::of(value).map(FiniteOrMarked::to_f64)
    }
}

impl SettingValue for Vec<f64> {
    fn to_setting(&self) -> Value {
        Value::Array(self.iter().map(f64::to_setting).collect())
    }
    fn from_setting(value: &Value) -> Option<Self> {
        value.as_array()?.iter().map(f64::from_setting).collect()
    }
}

impl<T: SettingValue> SettingValue for Option<T> {
    fn to_setting(&self) -> Value {
        self.as_ref().map_or(Value::Null, T::to_setting)
    }
    fn from_setting(value: &Value) -> Option<Self> {
        if value.is_null() {
            Some(None)
        } else {
            T::from_setting(value).map(Some)
        }
    }
}

/// A type that is one of several names (a setting's choices, [`Rule::Choice`]; a frame's fallback): its
/// variants and their names.
pub trait Named: Sized + Copy + PartialEq + 'static {
    /// Every variant with its name in the config.
    const NAMES: &'static [(Self, &'static str)];

    /// The variant's name in the config.
    fn name(self) -> &'static str {
        Self::NAMES
            .iter()
            .find(|(v, _)| *v == self)
            .map_or("", |(_, name)| name)
    }

    /// The variant of a name, if any.
    fn from_name(name: &str) -> Option<Self> {
        Self::NAMES
            .iter()
            .find(|(_, n)| *n == name)
            .map(|(v, _)| *v)
    }
}

/// The names of a [`Named`] type's `N` variants, for its [`Rule::Choice`].
pub const fn names<const N: usize, T: Copy>(named: &[(T, &'static str)]) -> [&'static str; N] {
    let mut out = [""; N];
    let mut i = 0;
    while i < N {
        out[i] = named[i].1;
        i += 1;
    }
    out
}

impl<T: Named> SettingValue for T {
    fn to_setting(&self) -> Value {
        Value::String(self.name().into())
    }
    fn from_setting(value: &Value) -> Option<Self> {
        T::from_name(value.as_str()?)
    }
}

/// Declares a section of the config once: the struct with its documented fields, its `Default`, the
/// schema of its settings (`SETTINGS`, what checks a config and what Python's class is made from), and
/// its reading from and writing to the config's JSON. A leading `[key: Type, …]` nests other sections.
macro_rules! settings {
    (
        $(#[doc = $doc:literal])*
        pub struct $name:ident {
            $( [ $( $section:ident : $section_type:ty, )* ] )?
            $(
                $(#[doc = $field_doc:literal])*
                $key:ident : $type:ty = $default:expr, $rule:expr;
            )*
        }
    ) => {
        $(#[doc = $doc])*
        #[derive(Debug, Clone, PartialEq)]
        pub struct $name {
            $($( #[doc = concat!("The `", stringify!($section), "` section.")] pub $section: $section_type, )*)?
            $( $(#[doc = $field_doc])* pub $key: $type, )*
        }

        impl Default for $name {
            fn default() -> Self {
                $name {
                    $($( $section: <$section_type>::default(), )*)?
                    $( $key: $default, )*
                }
            }
        }

        impl $name {
            /// What the section is for (its doc comment).
            pub const DOC: &'static str = concat!($($doc, "\n"),*);
            /// Every setting of the section, in declaration order.
            pub const SETTINGS: &'static [$crate::odometry::config::schema::Setting] = &[
                $( $crate::odometry::config::schema::Setting {
                    key: stringify!($key),
                    rule: $rule,
                    doc: concat!($($field_doc, "\n"),*),
                }, )*
            ];

            /// The section as the config's JSON holds it, every key with its value.
            pub(super) fn to_values(&self) -> serde_json::Map<String, serde_json::Value> {
                use $crate::odometry::config::schema::SettingValue;
                let mut values = serde_json::Map::new();
                $($( values.insert(stringify!($section).into(), serde_json::Value::Object(self.$section.to_values())); )*)?
                $( values.insert(stringify!($key).into(), self.$key.to_setting()); )*
                values
            }

            /// The section of checked values (`check`): every key left out at its default; the key of a
            /// value that its field cannot hold.
            pub(super) fn from_values(
                values: &serde_json::Map<String, serde_json::Value>,
                prefix: &str,
            ) -> std::result::Result<Self, String> {
                use $crate::odometry::config::schema::SettingValue;
                let mut section = Self::default();
                $($(
                    if let Some(serde_json::Value::Object(inner)) = values.get(stringify!($section)) {
                        section.$section = <$section_type>::from_values(inner, concat!(stringify!($section), "."))?;
                    }
                )*)?
                $(
                    if let Some(value) = values.get(stringify!($key)) {
                        section.$key = SettingValue::from_setting(value)
                            .ok_or_else(|| format!("{prefix}{}", stringify!($key)))?;
                    }
                )*
                Ok(section)
            }
        }
    };
}

pub(crate) use settings;
