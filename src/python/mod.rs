//! PyO3 bindings: numpy in, numpy out, GIL released around every computation, crate errors mapped to
//! Python exceptions. Only compiled with the `python` feature.
//!
//! Every function checks dtype, shape and finiteness at the boundary (naming the argument; helpers in
//! [`convert`]), copies non-contiguous or float64 input where a float32 buffer is needed, releases the
//! GIL around the work, runs rayon work in a pool owned by the bindings ([`pool`]: recreated after
//! `fork()`, never the global pool), and turns any panic into a `RuntimeError`. One file per topic.

mod convert;
mod dense_match;
mod deskew;
mod diagnostics;
mod mapping;
mod matches;
mod model;
mod moving;
mod ndt;
mod odometry;
mod odometry_loop;
mod pair;
mod pool;
mod projection;
mod projective;
mod registration;
mod sim;
mod surface;

use pyo3::exceptions::{PyOSError, PyValueError};
use pyo3::prelude::*;

use crate::Error;

pyo3::create_exception!(
    dmlo_rs,
    RegistrationError,
    PyValueError,
    "Valid arguments whose data admit no solution: too few point pairs or correspondences, or points \
     that do not determine a unique motion. A subclass of ValueError, so callers can tell such \
     data-dependent failures apart from wrong arguments (plain ValueError) and fall back."
);

pyo3::create_exception!(
    dmlo_rs,
    ConfigError,
    PyValueError,
    "A config that does not fit the odometry's schema: one message naming every bad key. A subclass of \
     ValueError."
);

pyo3::create_exception!(
    dmlo_rs,
    ModelError,
    PyValueError,
    "A model file that is missing, not a dmlo export, or does not fit the input: the message names the \
     file and what is wrong. A subclass of ValueError."
);

impl From<Error> for PyErr {
    fn from(err: Error) -> PyErr {
        match err {
            Error::InvalidArgument { .. } => PyValueError::new_err(err.to_string()),
            // The exception's type says what the Rust message's "model: " prefix does.
            Error::Model(message) => ModelError::new_err(message),
            Error::Config(_) => ConfigError::new_err(err.to_string()),
            Error::TooFewPoints { .. } | Error::Degenerate(_) => {
                RegistrationError::new_err(err.to_string())
            }
            Error::File { .. } => PyOSError::new_err(err.to_string()),
        }
    }
}

#[pymodule]
fn _dmlo_rs(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("RegistrationError", m.py().get_type::<RegistrationError>())?;
    m.add("ConfigError", m.py().get_type::<ConfigError>())?;
    m.add("ModelError", m.py().get_type::<ModelError>())?;
    projection::register(m)?;
    registration::register(m)?;
    matches::register(m)?;
    deskew::register(m)?;
    dense_match::register(m)?;
    sim::register(m)?;
    ndt::register(m)?;
    surface::register(m)?;
    pair::register(m)?;
    odometry::register(m)?;
    odometry_loop::register(m)?;
    mapping::register(m)?;
    projective::register(m)?;
    moving::register(m)?;
    model::register(m)?;
    diagnostics::register(m)?;
    Ok(())
}
