#![forbid(unsafe_code)]
//! [`TractEncoder`]: `encoder.onnx` run by tract.

use std::collections::HashMap;
use std::fmt;
use std::path::Path;
use std::sync::Arc;

use tract_onnx::prelude::tract_linalg::multithread::{multithread_tract_scope, Executor};
use tract_onnx::prelude::*;

use super::{check_image, EncodedScan, Encoder, ModelMetadata};
use crate::error::{Error, Result};

/// The network's encoder (`encoder.onnx`, exported by `dmlo export`) run by tract, optimised once for the
/// graph's input size. Its convolutions run on rayon's global pool (`RAYON_NUM_THREADS`, or
/// `rayon::ThreadPoolBuilder::build_global`), as the crate's other parallel stages do.
pub struct TractEncoder {
    plan: Arc<TypedRunnableModel>,
    metadata: ModelMetadata,
    path: String,
}

impl fmt::Debug for TractEncoder {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("TractEncoder")
            .field("path", &self.path)
            .field("metadata", &self.metadata)
            .finish_non_exhaustive()
    }
}

/// The dmlo metadata of any exported graph at `path` (e.g. `frame_wide.onnx`, for its wide coarse
/// window), without building it.
pub fn graph_metadata(path: impl AsRef<Path>) -> Result<ModelMetadata> {
    let path = path.as_ref();
    let shown = path.display().to_string();
    if !path.is_file() {
        return Err(Error::Model(format!("{shown}: no such file")));
    }
    let proto = tract_onnx::onnx()
        .proto_model_for_path(path)
        .map_err(|e| Error::Model(format!("{shown}: not an ONNX graph: {e:#}")))?;
    let entries: HashMap<String, String> = proto
        .metadata_props
        .iter()
        .map(|entry| (entry.key.clone(), entry.value.clone()))
        .collect();
    ModelMetadata::from_entries(&entries, &shown)
}

impl TractEncoder {
    /// Opens the encoder graph at `path`. Errors ([`Error::Model`]) name the file and what is wrong: missing,
    /// not ONNX, not a dmlo encoder (e.g. `frame.onnx` given: the encoder is `encoder.onnx` beside it),
    /// or outputs that are not the two feature maps the matching stage reads.
    pub fn open(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let shown = path.display().to_string();
        if !path.is_file() {
            return Err(Error::Model(format!("{shown}: no such file")));
        }
        let failed = |what: &str, e: TractError| Error::Model(format!("{shown}: {what}: {e:#}"));
        let onnx = tract_onnx::onnx();
        let proto = onnx
            .proto_model_for_path(path)
            .map_err(|e| failed("not an ONNX graph", e))?;
        let entries: HashMap<String, String> = proto
            .metadata_props
            .iter()
            .map(|entry| (entry.key.clone(), entry.value.clone()))
            .collect();
        let metadata = ModelMetadata::from_entries(&entries, &shown)?;
        if metadata.graph != "encoder" {
            return Err(Error::Model(format!(
                "{shown}: a dmlo {:?} graph, not the encoder (encoder.onnx beside it)",
                metadata.graph
            )));
        }
        let input = f32::fact([1, 2, metadata.height, metadata.width]);
        let plan = onnx
            .model_for_proto_model(&proto)
            .and_then(|model| model.with_input_fact(0, input.into()))
            .and_then(|model| model.into_optimized())
            .and_then(|model| model.into_runnable())
            .map_err(|e| failed("tract cannot run it", e))?;
        if plan.model().outputs.len() != 2 {
            return Err(Error::Model(format!(
                "{shown}: {} outputs, expected 2 (coarse_features, refine_features)",
                plan.model().outputs.len()
            )));
        }
        Ok(TractEncoder {
            plan,
            metadata,
            path: shown,
        })
    }
}

impl Encoder for TractEncoder {
    fn metadata(&self) -> &ModelMetadata {
        &self.metadata
    }

    fn encode(&self, image: &[f32]) -> Result<EncodedScan> {
        let [rows, columns] = self.input_size();
        check_image(image, [rows, columns])?;
        let input = Tensor::from_shape(&[1, 2, rows, columns], image)
            .map_err(|e| Error::Model(format!("{}: input: {e:#}", self.path)))?;
        let outputs =
            multithread_tract_scope(Executor::RayonGlobal, || self.plan.run(tvec!(input.into())))
                .map_err(|e| Error::Model(format!("{}: {e:#}", self.path)))?;
        let features = |index: usize| -> Result<(Vec<f32>, [usize; 3])> {
            let view = outputs[index]
                .to_plain_array_view::<f32>()
                .map_err(|e| Error::Model(format!("{}: output {index}: {e:#}", self.path)))?;
            match *view.shape() {
                [1, channels, height, width] => {
                    Ok((view.iter().copied().collect(), [channels, height, width]))
                }
                ref other => Err(Error::Model(format!(
                    "{}: output {index} has shape {other:?}, expected (1, channels, rows, columns)",
                    self.path
                ))),
            }
        };
        EncodedScan::from_outputs(&self.path, features(0)?, features(1)?, [rows, columns])
    }
}
