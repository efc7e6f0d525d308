//! PyO3 bindings: numpy in, numpy out, GIL released around every computation, crate errors mapped to
//! Python exceptions. Only compiled with the `python` feature.

mod core;
mod dense_match;
mod ndt;
mod pool;
mod sim;
mod surface;

use pyo3::exceptions::PyValueError;
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

impl From<Error> for PyErr {
    fn from(err: Error) -> PyErr {
        match err {
            Error::InvalidArgument { .. } => PyValueError::new_err(err.to_string()),
            Error::TooFewPoints { .. } | Error::Degenerate(_) => {
                RegistrationError::new_err(err.to_string())
            }
        }
    }
}

#[pymodule]
fn _dmlo_rs(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("RegistrationError", m.py().get_type::<RegistrationError>())?;
    core::register(m)?;
    dense_match::register(m)?;
    sim::register(m)?;
    ndt::register(m)?;
    surface::register(m)?;
    Ok(())
}
