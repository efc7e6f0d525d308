//! PyO3 bindings: numpy in, numpy out, GIL released around every computation, crate errors mapped to
//! Python exceptions. Only compiled with the `python` feature.

mod core;
mod ndt;
mod pool;
mod sim;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::Error;

impl From<Error> for PyErr {
    fn from(err: Error) -> PyErr {
        match err {
            Error::InvalidArgument { .. } | Error::TooFewPoints { .. } | Error::Degenerate(_) => {
                PyValueError::new_err(err.to_string())
            }
        }
    }
}

#[pymodule]
fn _dmlo_rs(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    core::register(m)?;
    sim::register(m)?;
    ndt::register(m)?;
    Ok(())
}
