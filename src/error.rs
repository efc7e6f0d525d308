#![forbid(unsafe_code)]
//! The crate's error type: every failure names the argument or condition at fault.

/// Errors returned by `dmlo_rs`. Bad input is reported, never papered over with a default result.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Error {
    /// An argument has the wrong shape, size or value; `argument` names it as the API does.
    #[error("{argument}: {reason}")]
    InvalidArgument {
        /// The argument's name, as the Rust and Python APIs spell it.
        argument: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// A solve needs more points than it was given.
    #[error("need at least {needed} point pairs, got {got}")]
    TooFewPoints {
        /// The minimum the computation needs.
        needed: usize,
        /// How many (usable) pairs it was given.
        got: usize,
    },
    /// The points do not determine a unique solution (e.g. all collinear).
    #[error("degenerate input: {0}")]
    Degenerate(String),
    /// A model file is missing, unreadable or not what was asked for (`inference`); the message names the
    /// file.
    #[error("model: {0}")]
    Model(String),
    /// A setting of the odometry's config is unknown, of the wrong type or out of its range; the message
    /// names the key (`ransac.threshold: ...`).
    #[error("{0}")]
    Config(String),
    /// A file could not be read or is not laid out as its format says ([`crate::scan_file`]).
    #[error("{path}: {reason}")]
    File {
        /// The file or folder.
        path: String,
        /// What went wrong.
        reason: String,
    },
}

/// `Result` with the crate's [`Error`].
pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    /// Shorthand for [`Error::InvalidArgument`].
    pub fn invalid(argument: &'static str, reason: impl Into<String>) -> Self {
        Error::InvalidArgument {
            argument,
            reason: reason.into(),
        }
    }
}
