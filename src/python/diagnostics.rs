//! Binding of a frame's diagnostics (`crate::odometry::pipeline::FrameDiagnostics`): Python reads the
//! crate's own record, its fields by name and in the form `diagnostics.jsonl` holds them (the same keys and
//! rounding), so no second declaration of them exists.

use pyo3::exceptions::{PyAttributeError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple};
use serde_json::{Map, Value};

use crate::odometry::pipeline::FrameDiagnostics;

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyFrameDiagnostics>()?;
    Ok(())
}

/// What happened to one scan: counts, the fallback taken, the notices said and the time of every stage in
/// ms; its fields are attributes (`diagnostics.fallback`), `to_dict()` is its line of `diagnostics.jsonl`.
/// `FrameDiagnostics(index=3, num_points=1000)` makes one with the other fields at their defaults.
#[pyclass(name = "FrameDiagnostics", module = "dmlo_rs._dmlo_rs", frozen)]
pub struct PyFrameDiagnostics {
    fields: Map<String, Value>,
}

impl PyFrameDiagnostics {
    /// The diagnostics as written; with `encoding_in_matching`, the matching stage's time counted as the
    /// network's (a graph that encodes a scan while matching it cannot time the two apart).
    pub(super) fn new(diagnostics: &FrameDiagnostics, encoding_in_matching: bool) -> PyResult<Self> {
        let mut fields = written(diagnostics)?;
        if encoding_in_matching {
            if let Some(Value::Object(timings)) = fields.get_mut("timings_ms") {
                if let Some(matching) = timings.remove("matching").and_then(|v| v.as_f64()) {
                    let network = timings.get("network").and_then(Value::as_f64).unwrap_or(0.0);
                    let total = (network + matching) * 1e3;
                    timings.insert("network".into(), Value::from(total.round() / 1e3));
                }
            }
        }
        Ok(PyFrameDiagnostics { fields })
    }
}

/// The diagnostics' JSON form, as `diagnostics.jsonl` holds them.
fn written(diagnostics: &FrameDiagnostics) -> PyResult<Map<String, Value>> {
    match serde_json::to_value(diagnostics) {
        Ok(Value::Object(fields)) => Ok(fields),
        Ok(_) => Err(PyValueError::new_err("diagnostics: not a JSON object")),
        Err(e) => Err(PyValueError::new_err(format!("diagnostics: {e}"))),
    }
}

fn to_python<'py>(py: Python<'py>, value: &Value) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(value).map_err(|e| PyValueError::new_err(e.to_string()))?;
    py.import("json")?.getattr("loads")?.call1((text,))
}

#[pymethods]
impl PyFrameDiagnostics {
    #[new]
    #[pyo3(signature = (*args, **fields))]
    fn py_new(args: &Bound<'_, PyTuple>, fields: Option<&Bound<'_, PyDict>>) -> PyResult<Self> {
        if !args.is_empty() {
            return Err(PyTypeError::new_err(
                "FrameDiagnostics: takes its fields by name (e.g. index=3, num_points=1000)",
            ));
        }
        let mut made = written(&FrameDiagnostics::default())?;
        // The notices are left out of a frame that said none.
        made.entry("notices").or_insert_with(|| Value::Array(Vec::new()));
        let json = fields.map(|f| f.py().import("json")).transpose()?;
        for (key, value) in fields.into_iter().flat_map(|f| f.iter()) {
            let name: String = key.extract()?;
            if !made.contains_key(&name) {
                return Err(PyTypeError::new_err(format!(
                    "FrameDiagnostics: no field {name:?}; the fields are {}",
                    made.keys().cloned().collect::<Vec<_>>().join(", ")
                )));
            }
            let text: String = json
                .as_ref()
                .expect("fields were given")
                .getattr("dumps")?
                .call1((value,))?
                .extract()?;
            let parsed = serde_json::from_str(&text)
                .map_err(|e| PyValueError::new_err(format!("FrameDiagnostics: {name}: {e}")))?;
            made.insert(name, parsed);
        }
        if made.get("notices").is_some_and(|n| n.as_array().is_some_and(Vec::is_empty)) {
            made.remove("notices");
        }
        Ok(PyFrameDiagnostics { fields: made })
    }

    fn __getattr__<'py>(&self, py: Python<'py>, name: &str) -> PyResult<Bound<'py, PyAny>> {
        match (self.fields.get(name), name) {
            (Some(value), _) => to_python(py, value),
            // A frame that said nothing has no notices in its line of diagnostics.jsonl.
            (None, "notices") => to_python(py, &Value::Array(Vec::new())),
            (None, _) => Err(PyAttributeError::new_err(format!(
                "FrameDiagnostics has no field {name:?}"
            ))),
        }
    }

    /// The frame's line of `diagnostics.jsonl`, as a dict.
    fn to_dict<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, &Value::Object(self.fields.clone()))
    }

    fn __eq__(&self, other: &Bound<'_, PyAny>) -> bool {
        other
            .cast::<PyFrameDiagnostics>()
            .is_ok_and(|other| other.get().fields == self.fields)
    }

    fn __repr__(&self) -> String {
        format!("FrameDiagnostics({})", Value::Object(self.fields.clone()))
    }
}
