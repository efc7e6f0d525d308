//! Bindings of a model folder's layout and of the rules for its graphs' metadata
//! (`crate::inference::{ModelFolder, ModelMetadata}`): Python's onnxruntime path reads a graph's metadata
//! entries itself and has the crate check them, so one set of rules holds for every runtime.

use std::collections::HashMap;

use pyo3::prelude::*;

use crate::inference::{self, ModelFolder, ModelMetadata, MATCHING_STAGE_KEYS};

use super::projection::PyCylinderConfig;

pub(super) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyModelMetadata>()?;
    m.add_class::<PyModelFolder>()?;
    m.add_function(wrap_pyfunction!(moving_graph_cylinder, m)?)?;
    Ok(())
}

/// What a dmlo graph's metadata says about its model, checked whole when made: `ModelMetadata(entries,
/// path)` with the graph's metadata entries (`key → value`, e.g. onnxruntime's `custom_metadata_map`) and
/// its path, named in errors (`ModelError`, naming the key at fault).
#[pyclass(name = "ModelMetadata", module = "dmlo_rs._dmlo_rs", frozen)]
pub struct PyModelMetadata {
    inner: ModelMetadata,
}

#[pymethods]
impl PyModelMetadata {
    #[new]
    fn new(entries: HashMap<String, String>, path: &str) -> PyResult<Self> {
        Ok(PyModelMetadata {
            inner: ModelMetadata::from_entries(&entries, path)?,
        })
    }

    /// `dmlo.graph`: "encoder", "frame", "match", …
    #[getter]
    fn graph(&self) -> &str {
        &self.inner.graph
    }

    /// Image rows of the network's input.
    #[getter]
    fn height(&self) -> usize {
        self.inner.height
    }

    /// Image columns of the network's input.
    #[getter]
    fn width(&self) -> usize {
        self.inner.width
    }

    /// The coarse window D of the matching stage.
    #[getter]
    fn coarse_window(&self) -> usize {
        self.inner.coarse_window
    }

    /// The refine window of the matching stage.
    #[getter]
    fn refine_window(&self) -> usize {
        self.inner.refine_window
    }

    /// How the refine stage places its offset: "window" or "peak_centroid".
    #[getter]
    fn refine_offset(&self) -> &str {
        &self.inner.refine_offset
    }

    /// The learned softmax scales `(coarse, refine)` the crate's matching stage needs; None in graphs
    /// exported before they were written.
    #[getter]
    fn similarity_scales(&self) -> Option<(f32, f32)> {
        self.inner.similarity_scales.map(|[coarse, refine]| (coarse, refine))
    }

    /// The cylinder image the model takes (KITTI's for graphs exported before it was written).
    #[getter]
    fn cylinder(&self) -> PyCylinderConfig {
        PyCylinderConfig {
            inner: self.inner.image_cylinder(),
        }
    }

    /// Whether the model reads the reflectance channel (False: a range-only model).
    #[getter]
    fn use_reflectance(&self) -> bool {
        self.inner.use_reflectance
    }

    /// Raises `ModelError` naming `path` (this graph's) unless this graph is a range-only model that can
    /// stand in for `model` (`model_path`'s) on scans without usable reflectance.
    fn check_range_only_for(&self, model: &PyModelMetadata, path: &str, model_path: &str) -> PyResult<()> {
        Ok(self.inner.check_range_only_for(&model.inner, path, model_path)?)
    }

    /// Raises `ModelError` naming `path` (this graph's) and what differs unless this graph is the `graph`
    /// graph of `model`'s weights (`model_path`'s), up to the model config keys in `ignored` (all of the
    /// matching stage's with `ignore_matching_stage`).
    #[pyo3(signature = (graph, model, path, model_path, *, ignore_matching_stage = false, ignored = Vec::new()))]
    fn check_export_of(
        &self,
        graph: &str,
        model: &PyModelMetadata,
        path: &str,
        model_path: &str,
        ignore_matching_stage: bool,
        ignored: Vec<String>,
    ) -> PyResult<()> {
        let mut keys: Vec<&str> = ignored.iter().map(String::as_str).collect();
        if ignore_matching_stage {
            keys.extend(MATCHING_STAGE_KEYS);
        }
        Ok(self
            .inner
            .check_export_of(graph, &model.inner, &keys, path, model_path)?)
    }
}

/// The file names of a model folder's graphs, as `dmlo export` writes them (class attributes).
#[pyclass(name = "ModelFolder", module = "dmlo_rs._dmlo_rs", frozen)]
pub struct PyModelFolder;

#[pymethods]
impl PyModelFolder {
    #[classattr]
    const ENCODER: &'static str = ModelFolder::ENCODER;
    #[classattr]
    const FRAME: &'static str = ModelFolder::FRAME;
    #[classattr]
    const MATCH: &'static str = ModelFolder::MATCH;
    #[classattr]
    const WIDE_WINDOW: &'static str = ModelFolder::WIDE_WINDOW;
    #[classattr]
    const RANGE_ONLY: &'static str = ModelFolder::RANGE_ONLY;
    #[classattr]
    const MOVING_OBJECTS: &'static str = ModelFolder::MOVING_OBJECTS;
}

/// The cylinder image of a moving-object graph (`moving.onnx`) from its metadata entries; `ModelError`
/// naming `path` when it is not a dmlo moving-object graph or its image is not its input's.
#[pyfunction]
fn moving_graph_cylinder(entries: HashMap<String, String>, path: &str) -> PyResult<PyCylinderConfig> {
    Ok(PyCylinderConfig {
        inner: inference::moving_graph_cylinder(&entries, path)?,
    })
}
