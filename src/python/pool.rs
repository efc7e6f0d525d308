//! Where binding work runs: without the GIL, in a rayon pool owned by this module (never the global
//! pool, so a host application's pool settings are untouched), with panics turned into `RuntimeError`.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, Mutex};

use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;

use super::convert::Int;

/// `num_threads` from Python as [`run`] takes it. Values within `i64` are checked by the pool itself;
/// beyond that they are refused here, by the same name and rule.
pub(super) fn threads(num_threads: Option<Int>) -> PyResult<Option<i64>> {
    match num_threads {
        None => Ok(None),
        Some(n) => match n.fitting::<i64>() {
            Some(value) => Ok(Some(value)),
            None if n.is_negative() => Err(PyValueError::new_err(format!(
                "num_threads: must be >= 1 (or None for all cores), got {n}"
            ))),
            None => Err(PyValueError::new_err(format!(
                "num_threads: at most {MAX_THREADS}, got {n}"
            ))),
        },
    }
}

/// The pools of this process by thread count, with the pid that built them: a forked child (PyTorch
/// DataLoader workers fork) has none of the parent's worker threads and builds its own; the parent's
/// pools are leaked in the child, never joined.
static POOLS: Mutex<Option<ProcessPools>> = Mutex::new(None);

/// The most threads a binding call may ask for.
const MAX_THREADS: i64 = 1024;

type ProcessPools = (u32, Vec<(usize, Arc<rayon::ThreadPool>)>);

/// `num_threads` as [`threads`] passes it on: refused by name when below 1 or above [`MAX_THREADS`].
fn thread_pool(num_threads: Option<i64>) -> PyResult<Arc<rayon::ThreadPool>> {
    let threads = match num_threads {
        Some(n) if n < 1 => {
            return Err(PyValueError::new_err(format!(
                "num_threads: must be >= 1 (or None for all cores), got {n}"
            )))
        }
        // Far beyond any machine's cores: a mistyped count must not try to start a million threads.
        Some(n) if n > MAX_THREADS => {
            return Err(PyValueError::new_err(format!(
                "num_threads: at most {MAX_THREADS}, got {n}"
            )))
        }
        Some(n) => n as usize,
        None => std::thread::available_parallelism().map_or(1, |n| n.get()),
    };
    let mut guard = POOLS
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    let pid = std::process::id();
    if guard.as_ref().is_some_and(|(owner, _)| *owner != pid) {
        if let Some((_, pools)) = guard.take() {
            std::mem::forget(pools);
        }
    }
    let (_, pools) = guard.get_or_insert_with(|| (pid, Vec::new()));
    if let Some((_, pool)) = pools.iter().find(|(n, _)| *n == threads) {
        return Ok(pool.clone());
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("dmlo_rs-{i}"))
        .build()
        .map_err(|e| PyRuntimeError::new_err(format!("cannot start {threads} threads: {e}")))?;
    let pool = Arc::new(pool);
    pools.push((threads, pool.clone()));
    Ok(pool)
}

/// Runs `work` without the GIL inside a pool of `num_threads` (None: all cores), mapping crate errors
/// to Python exceptions and panics to `RuntimeError`.
pub(crate) fn run<T: Send>(
    py: Python<'_>,
    num_threads: Option<i64>,
    work: impl FnOnce() -> crate::Result<T> + Send,
) -> PyResult<T> {
    let pool = thread_pool(num_threads)?;
    match py.detach(|| catch_unwind(AssertUnwindSafe(|| pool.install(work)))) {
        Ok(result) => result.map_err(PyErr::from),
        Err(panic) => {
            let message = panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "unknown panic".into());
            Err(PyRuntimeError::new_err(format!(
                "internal error in dmlo_rs (please report): {message}"
            )))
        }
    }
}
