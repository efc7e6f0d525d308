#![forbid(unsafe_code)]
//! [`OrtEncoder`]: `encoder.onnx` run by onnxruntime through `ort`, the runtime loaded at run time from a
//! shared library the system (or the `onnxruntime` Python wheel, `onnxruntime/capi/libonnxruntime.so.*`)
//! already has: nothing is downloaded at build time. The same runtime as `dmlo run`'s, so the same
//! features to the last bit on the same machine and thread count.

use std::any::Any;
use std::collections::HashMap;
use std::fmt;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;
use std::sync::Mutex;

use ort::session::Session;
use ort::value::TensorRef;

use super::metadata::moving_graph_cylinder;
use super::{check_image, check_moving_images, EncodedScan, Encoder, ModelMetadata};
use crate::error::{Error, Result};
use crate::odometry::moving::MovingObjectNetwork;
use crate::projection::CylinderConfig;

/// The network's encoder (`encoder.onnx`, exported by `dmlo export`) run by onnxruntime.
pub struct OrtEncoder {
    session: Mutex<Session>,
    metadata: ModelMetadata,
    path: String,
}

impl fmt::Debug for OrtEncoder {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("OrtEncoder")
            .field("path", &self.path)
            .field("metadata", &self.metadata)
            .finish_non_exhaustive()
    }
}

/// `ort` reports a library it cannot load, or of an API older than its own, by panicking: a panic in
/// `work` becomes an error naming `library`.
fn without_panics<T>(library: &str, work: impl FnOnce() -> Result<T>) -> Result<T> {
    catch_unwind(AssertUnwindSafe(work)).unwrap_or_else(|panic: Box<dyn Any + Send>| {
        let message = panic
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_else(|| "it panicked".into());
        Err(Error::Model(format!(
            "{library}: not an onnxruntime library ort can use: {message}"
        )))
    })
}

/// A graph opened in the onnxruntime shared library `library` (module docs), with its metadata entries.
fn open_session(
    path: &Path,
    library: &Path,
    threads: usize,
) -> Result<(Session, HashMap<String, String>)> {
    let shown = path.display().to_string();
    let library_shown = library.display().to_string();
    if !library.is_file() {
        return Err(Error::Model(format!(
            "{library_shown}: no such file (the onnxruntime shared library, e.g. the Python wheel's \
             onnxruntime/capi/libonnxruntime.so.*)"
        )));
    }
    if !path.is_file() {
        return Err(Error::Model(format!("{shown}: no such file")));
    }
    let failed = |what: &str, e: ort::Error| Error::Model(format!("{shown}: {what}: {e}"));
    let session = without_panics(&library_shown, || {
        ort::init_from(library_shown.clone())
            .commit()
            .map_err(|e| Error::Model(format!("{library_shown}: {e}")))?;
        Session::builder()
            .and_then(|b| b.with_intra_threads(threads))
            .and_then(|b| b.with_intra_op_spinning(false))
            .and_then(|b| b.commit_from_file(path))
            .map_err(|e| failed("onnxruntime cannot open it", e))
    })?;
    let entries = {
        let metadata = session.metadata().map_err(|e| failed("its metadata", e))?;
        let keys = metadata
            .custom_keys()
            .map_err(|e| failed("its metadata", e))?;
        let mut entries = HashMap::new();
        for key in keys {
            if let Some(value) = metadata
                .custom(&key)
                .map_err(|e| failed("its metadata", e))?
            {
                entries.insert(key, value);
            }
        }
        entries
    };
    Ok((session, entries))
}

impl OrtEncoder {
    /// Opens the encoder graph at `path` in the onnxruntime shared library `library` (loaded once per
    /// process: the first library opened is the one every later encoder runs in). `threads`: onnxruntime's
    /// intra-op threads (0: its choice), idle threads not spinning, as `dmlo run` sets them. Errors
    /// ([`Error::Model`]) name the file and what is wrong: a missing or unusable library, a missing file, not
    /// a dmlo encoder (e.g. `frame.onnx` given: the encoder is `encoder.onnx` beside it), or outputs that are
    /// not the two feature maps the matching stage reads.
    pub fn open(path: impl AsRef<Path>, library: impl AsRef<Path>, threads: usize) -> Result<Self> {
        let path = path.as_ref();
        let shown = path.display().to_string();
        let (session, entries) = open_session(path, library.as_ref(), threads)?;
        let metadata = ModelMetadata::from_entries(&entries, &shown)?;
        if metadata.graph != "encoder" {
            return Err(Error::Model(format!(
                "{shown}: a dmlo {:?} graph, not the encoder (encoder.onnx beside it)",
                metadata.graph
            )));
        }
        if session.outputs.len() != 2 || session.inputs.len() != 1 {
            return Err(Error::Model(format!(
                "{shown}: {} inputs and {} outputs, expected 1 (scan) and 2 (coarse_features, refine_features)",
                session.inputs.len(),
                session.outputs.len()
            )));
        }
        Ok(OrtEncoder {
            session: Mutex::new(session),
            metadata,
            path: shown,
        })
    }
}

impl Encoder for OrtEncoder {
    fn metadata(&self) -> &ModelMetadata {
        &self.metadata
    }

    fn encode(&self, image: &[f32]) -> Result<EncodedScan> {
        let [rows, columns] = self.input_size();
        check_image(image, [rows, columns])?;
        let failed = |e: ort::Error| Error::Model(format!("{}: {e}", self.path));
        let input =
            TensorRef::from_array_view(([1usize, 2, rows, columns], image)).map_err(failed)?;
        // A poisoned lock only means another thread's encode failed: the session itself is intact.
        let mut session = self.session.lock().unwrap_or_else(|p| p.into_inner());
        let outputs = session.run(ort::inputs![input]).map_err(failed)?;
        let features = |index: usize| -> Result<(Vec<f32>, [usize; 3])> {
            let (shape, values) = outputs[index]
                .try_extract_tensor::<f32>()
                .map_err(|e| Error::Model(format!("{}: output {index}: {e}", self.path)))?;
            match **shape {
                [1, channels, height, width] if channels > 0 && height > 0 && width > 0 => Ok((
                    values.to_vec(),
                    [channels as usize, height as usize, width as usize],
                )),
                ref other => Err(Error::Model(format!(
                    "{}: output {index} has shape {other:?}, expected (1, channels, rows, columns)",
                    self.path
                ))),
            }
        };
        EncodedScan::from_outputs(&self.path, features(0)?, features(1)?, [rows, columns])
    }
}

/// The moving-object network (`moving.onnx`, exported by `dmlo export` beside the encoder) run by
/// onnxruntime.
pub struct OrtMovingObjects {
    session: Mutex<Session>,
    cylinder: CylinderConfig,
    path: String,
}

impl fmt::Debug for OrtMovingObjects {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("OrtMovingObjects")
            .field("path", &self.path)
            .finish_non_exhaustive()
    }
}

impl OrtMovingObjects {
    /// Opens the moving-object graph at `path` in the onnxruntime shared library `library`, as
    /// [`OrtEncoder::open`] opens the encoder. Errors name the file and what is wrong: a missing or
    /// unusable library, a missing file, not a dmlo moving-object graph, or not its two inputs and one
    /// output.
    pub fn open(path: impl AsRef<Path>, library: impl AsRef<Path>, threads: usize) -> Result<Self> {
        let path = path.as_ref();
        let shown = path.display().to_string();
        let (session, entries) = open_session(path, library.as_ref(), threads)?;
        let cylinder = moving_graph_cylinder(&entries, &shown)?;
        if session.inputs.len() != 2 || session.outputs.len() != 1 {
            return Err(Error::Model(format!(
                "{shown}: {} inputs and {} outputs, expected 2 (range, height) and 1 (moving_probability)",
                session.inputs.len(),
                session.outputs.len()
            )));
        }
        Ok(OrtMovingObjects {
            session: Mutex::new(session),
            cylinder,
            path: shown,
        })
    }
}

impl MovingObjectNetwork for OrtMovingObjects {
    fn cylinder(&self) -> &CylinderConfig {
        &self.cylinder
    }

    fn probability(&self, range: &[f32], height: &[f32]) -> Result<Vec<f32>> {
        let (rows, columns) = (self.cylinder.height, self.cylinder.width);
        check_moving_images(range, height, [rows, columns])?;
        let failed = |e: ort::Error| Error::Model(format!("{}: {e}", self.path));
        let range = TensorRef::from_array_view(([1usize, rows, columns], range)).map_err(failed)?;
        let height =
            TensorRef::from_array_view(([1usize, rows, columns], height)).map_err(failed)?;
        let mut session = self.session.lock().unwrap_or_else(|p| p.into_inner());
        let outputs = session
            .run(ort::inputs!["range" => range, "height" => height])
            .map_err(failed)?;
        let (shape, values) = outputs[0]
            .try_extract_tensor::<f32>()
            .map_err(|e| Error::Model(format!("{}: its output: {e}", self.path)))?;
        if **shape != [1, rows as i64, columns as i64] {
            return Err(Error::Model(format!(
                "{}: output of shape {:?}, expected (1, {rows}, {columns})",
                self.path, &**shape
            )));
        }
        Ok(values.to_vec())
    }
}
