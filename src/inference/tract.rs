#![forbid(unsafe_code)]
//! [`TractEncoder`]: `encoder.onnx` run by tract.

use std::collections::HashMap;
use std::fmt;
use std::path::Path;
use std::sync::Arc;

use tract_onnx::prelude::tract_linalg::multithread::{multithread_tract_scope, Executor};
use tract_onnx::prelude::*;

use super::metadata::moving_graph_cylinder;
use super::{check_image, check_moving_images, EncodedScan, Encoder, ModelMetadata};
use crate::error::{Error, Result};
use crate::odometry::moving::MovingObjectNetwork;
use crate::projection::CylinderConfig;

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
    let (_, entries) = graph_with_entries(path, &shown)?;
    ModelMetadata::from_entries(&entries, &shown)
}

/// The ONNX graph at `path` (named in errors as `shown`) and its metadata entries.
fn graph_with_entries(
    path: &Path,
    shown: &str,
) -> Result<(tract_onnx::pb::ModelProto, HashMap<String, String>)> {
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
    Ok((proto, entries))
}

/// `proto` optimised for inputs of `shapes` and made runnable; errors name `shown`.
fn runnable(
    proto: &tract_onnx::pb::ModelProto,
    shapes: &[&[usize]],
    shown: &str,
) -> Result<Arc<TypedRunnableModel>> {
    let mut model = tract_onnx::onnx()
        .model_for_proto_model(proto)
        .map_err(|e| Error::Model(format!("{shown}: tract cannot run it: {e:#}")))?;
    for (index, shape) in shapes.iter().enumerate() {
        model = model
            .with_input_fact(index, f32::fact(*shape).into())
            .map_err(|e| Error::Model(format!("{shown}: tract cannot run it: {e:#}")))?;
    }
    model
        .into_optimized()
        .and_then(|model| model.into_runnable())
        .map_err(|e| Error::Model(format!("{shown}: tract cannot run it: {e:#}")))
}

impl TractEncoder {
    /// Opens the encoder graph at `path`. Errors ([`Error::Model`]) name the file and what is wrong: missing,
    /// not ONNX, not a dmlo encoder (e.g. `frame.onnx` given: the encoder is `encoder.onnx` beside it),
    /// or outputs that are not the two feature maps the matching stage reads.
    pub fn open(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let shown = path.display().to_string();
        let (proto, entries) = graph_with_entries(path, &shown)?;
        let metadata = ModelMetadata::from_entries(&entries, &shown)?;
        if metadata.graph != "encoder" {
            return Err(Error::Model(format!(
                "{shown}: a dmlo {:?} graph, not the encoder (encoder.onnx beside it)",
                metadata.graph
            )));
        }
        let plan = runnable(&proto, &[&[1, 2, metadata.height, metadata.width]], &shown)?;
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

/// The moving-object network (`moving.onnx`, exported by `dmlo export` beside the encoder) run by tract,
/// on rayon's global pool as [`TractEncoder`] is.
pub struct TractMovingObjects {
    plan: Arc<TypedRunnableModel>,
    cylinder: CylinderConfig,
    path: String,
}

impl fmt::Debug for TractMovingObjects {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("TractMovingObjects")
            .field("path", &self.path)
            .finish_non_exhaustive()
    }
}

impl TractMovingObjects {
    /// Opens the moving-object graph at `path`. Errors name the file and what is wrong: missing, not ONNX,
    /// not a dmlo moving-object graph, or not one output.
    pub fn open(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let shown = path.display().to_string();
        let (proto, entries) = graph_with_entries(path, &shown)?;
        let cylinder = moving_graph_cylinder(&entries, &shown)?;
        let image = [1, cylinder.height, cylinder.width];
        let plan = runnable(&proto, &[&image, &image], &shown)?;
        if plan.model().outputs.len() != 1 {
            return Err(Error::Model(format!(
                "{shown}: {} outputs, expected 1 (moving_probability)",
                plan.model().outputs.len()
            )));
        }
        Ok(TractMovingObjects {
            plan,
            cylinder,
            path: shown,
        })
    }
}

impl MovingObjectNetwork for TractMovingObjects {
    fn cylinder(&self) -> &CylinderConfig {
        &self.cylinder
    }

    fn probability(&self, range: &[f32], height: &[f32]) -> Result<Vec<f32>> {
        let (rows, columns) = (self.cylinder.height, self.cylinder.width);
        check_moving_images(range, height, [rows, columns])?;
        let tensor = |image: &[f32]| {
            Tensor::from_shape(&[1, rows, columns], image)
                .map_err(|e| Error::Model(format!("{}: input: {e:#}", self.path)))
        };
        let inputs = tvec!(tensor(range)?.into(), tensor(height)?.into());
        let outputs = multithread_tract_scope(Executor::RayonGlobal, || self.plan.run(inputs))
            .map_err(|e| Error::Model(format!("{}: {e:#}", self.path)))?;
        let view = outputs[0]
            .to_plain_array_view::<f32>()
            .map_err(|e| Error::Model(format!("{}: its output: {e:#}", self.path)))?;
        if view.shape() != [1, rows, columns] {
            return Err(Error::Model(format!(
                "{}: output of shape {:?}, expected (1, {rows}, {columns})",
                self.path,
                view.shape()
            )));
        }
        Ok(view.iter().copied().collect())
    }
}
