#![forbid(unsafe_code)]
//! The settings `dmlo export` writes into a graph's metadata (`metadata_props`), read back.

use std::collections::HashMap;

use serde_json::{Map, Value};

use crate::dense_match::{DenseMatchConfig, OffsetRule, NETWORK_STRIDE};
use crate::error::{Error, Result};
use crate::projection::CylinderConfig;

/// The version of the graphs' interface (inputs, outputs, metadata) this crate reads, as `dmlo export`
/// writes it in `dmlo.interface_version`.
const INTERFACE_VERSION: &str = "1";

/// The names `dmlo.model_config.refine_offset` may hold ([`OffsetRule::from_name`]).
const REFINE_OFFSETS: [&str; 2] = ["window", "peak_centroid"];

/// What a dmlo graph's metadata says about the model: its input size, which graph it is, and the
/// settings of the matching stage.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelMetadata {
    /// `dmlo.graph`: "encoder", "frame", "match", …
    pub graph: String,
    /// Image rows (`dmlo.height`).
    pub height: usize,
    /// Image columns (`dmlo.width`).
    pub width: usize,
    /// Coarse window D (`dmlo.model_config.coarse_window`).
    pub coarse_window: usize,
    /// Refine window (`dmlo.model_config.refine_window`).
    pub refine_window: usize,
    /// `dmlo.model_config.refine_offset`: "window" (the paper's Eq. 11) or "peak_centroid".
    pub refine_offset: String,
    /// The learned softmax scales (`dmlo.similarity_scales`: coarse, refine); None in graphs exported
    /// before they were written.
    pub similarity_scales: Option<[f32; 2]>,
    /// The cylinder image the model was trained on (`dmlo.cylinder_config`), whose size is the input's;
    /// None in graphs exported before it was written.
    pub cylinder: Option<CylinderConfig>,
    /// Whether the model reads the reflectance channel (`dmlo.model_config.use_reflectance`; false: a
    /// range-only model); true when the graph does not say.
    pub use_reflectance: bool,
    /// The whole `dmlo.model_config` (the network's settings: channels, windows, …), by which graphs of
    /// one model's weights are told from another's ([`ModelMetadata::check_export_of`]).
    pub model_config: Map<String, Value>,
}

/// The keys of `dmlo.model_config` chosen at export for the matching stage: graphs of the same weights may
/// differ in them (an encoder serves every window; `frame_wide.onnx` widens the coarse one).
pub const MATCHING_STAGE_KEYS: [&str; 3] = ["coarse_window", "refine_window", "refine_offset"];

impl ModelMetadata {
    /// Reads the metadata entries (`key → value`) of the graph at `path` (named in errors), checked whole:
    /// the interface version this crate reads, positive input sizes, odd windows of at least 3 cells, a
    /// known `refine_offset`, a boolean `use_reflectance` (absent: true), positive similarity scales and a
    /// cylinder image of the input's size (both may be absent in older exports). Every error is an
    /// [`Error::Model`] naming `path` and the key at fault.
    pub fn from_entries(entries: &HashMap<String, String>, path: &str) -> Result<Self> {
        let missing = |key: &str| {
            Error::Model(format!(
                "{path}: no {key} in the graph's metadata: not a dmlo export"
            ))
        };
        let text = |key: &str| entries.get(key).ok_or_else(|| missing(key));
        let json = |key: &str| -> Result<Value> {
            serde_json::from_str(text(key)?)
                .map_err(|e| Error::Model(format!("{path}: {key} is not JSON: {e}")))
        };
        // A window is centred on a cell: an odd count of at least 3 cells a side.
        let window = |key: &str, value: Option<&Value>| -> Result<usize> {
            value
                .and_then(Value::as_u64)
                .and_then(|v| usize::try_from(v).ok())
                .filter(|&v| v >= 3 && v % 2 == 1)
                .ok_or_else(|| {
                    let got = value.map_or("it lacks it".to_string(), |v| format!("got {v}"));
                    Error::Model(format!("{path}: {key} must be an odd integer >= 3; {got}"))
                })
        };
        let size = |key: &str| -> Result<usize> {
            let value = text(key)?;
            value
                .trim()
                .parse::<usize>()
                .ok()
                .filter(|&v| v > 0)
                .ok_or_else(|| {
                    Error::Model(format!(
                        "{path}: {key} = {value:?} is not a positive integer"
                    ))
                })
        };
        match text("dmlo.interface_version")?.as_str() {
            INTERFACE_VERSION => {}
            other => {
                return Err(Error::Model(format!(
                    "{path}: dmlo.interface_version {other:?}: this crate reads version \"{INTERFACE_VERSION}\" \
                     (export the model again with the `dmlo export` of this release)"
                )))
            }
        }
        let config = match json("dmlo.model_config")? {
            Value::Object(config) => config,
            _ => {
                return Err(Error::Model(format!(
                    "{path}: dmlo.model_config must be a JSON object"
                )))
            }
        };
        let coarse_window = window(
            "dmlo.model_config.coarse_window",
            config.get("coarse_window"),
        )?;
        let refine_window = window(
            "dmlo.model_config.refine_window",
            config.get("refine_window"),
        )?;
        let refine_offset = match config.get("refine_offset") {
            Some(Value::String(name)) if OffsetRule::from_name(name).is_some() => name.clone(),
            other => {
                let got = other.map_or("it lacks it".to_string(), |v| format!("got {v}"));
                return Err(Error::Model(format!(
                    "{path}: dmlo.model_config.refine_offset must be one of {}; {got}",
                    REFINE_OFFSETS.join(", ")
                )));
            }
        };
        let use_reflectance = match config.get("use_reflectance") {
            // Models exported before the setting was written read reflectance.
            None => true,
            Some(Value::Bool(reads)) => *reads,
            Some(other) => {
                return Err(Error::Model(format!(
                    "{path}: dmlo.model_config.use_reflectance must be true or false; got {other}"
                )))
            }
        };
        let similarity_scales = match entries.get("dmlo.similarity_scales") {
            None => None,
            Some(_) => {
                let scales = json("dmlo.similarity_scales")?;
                if !scales.is_object() {
                    return Err(Error::Model(format!(
                        "{path}: dmlo.similarity_scales must be a JSON object"
                    )));
                }
                let scale = |stage: &str| -> Result<f32> {
                    let value = scales.get(stage);
                    value
                        .and_then(Value::as_f64)
                        .filter(|v| v.is_finite() && *v > 0.0)
                        .map(|v| v as f32)
                        .ok_or_else(|| {
                            let got = value.map_or("it lacks it".to_string(), |v| format!("got {v}"));
                            Error::Model(format!(
                                "{path}: dmlo.similarity_scales.{stage} must be a finite number > 0; {got}"
                            ))
                        })
                };
                Some([scale("coarse")?, scale("refine")?])
            }
        };
        let (height, width) = (size("dmlo.height")?, size("dmlo.width")?);
        let cylinder = match entries.get("dmlo.cylinder_config") {
            None => None,
            Some(_) => Some(cylinder_config(&json("dmlo.cylinder_config")?, path)?),
        };
        if let Some(cylinder) = &cylinder {
            if (cylinder.height, cylinder.width) != (height, width) {
                return Err(Error::Model(format!(
                    "{path}: dmlo.cylinder_config is {} × {}, the input {height} × {width}",
                    cylinder.height, cylinder.width
                )));
            }
        }
        Ok(ModelMetadata {
            graph: text("dmlo.graph")?.clone(),
            height,
            width,
            coarse_window,
            refine_window,
            refine_offset,
            similarity_scales,
            cylinder,
            use_reflectance,
            model_config: config,
        })
    }

    /// The cylinder image the model takes: its `dmlo.cylinder_config`, or KITTI's for graphs exported
    /// before it was written (the only one then).
    pub fn image_cylinder(&self) -> CylinderConfig {
        self.cylinder.unwrap_or_else(CylinderConfig::kitti)
    }

    /// Checks that this graph (at `path`) is a range-only model that can stand in for `model`
    /// (`model_path`'s) on scans without usable reflectance: it reads no reflectance and takes the same
    /// images (size and cylinder). The error ([`Error::Model`]) names `path` and what is wrong.
    pub fn check_range_only_for(
        &self,
        model: &ModelMetadata,
        path: &str,
        model_path: &str,
    ) -> Result<()> {
        let differs = if [self.height, self.width] != [model.height, model.width] {
            format!(
                "takes {} × {} images, the model {} × {}",
                self.height, self.width, model.height, model.width
            )
        } else if self.image_cylinder() != model.image_cylinder() {
            "takes the images of another cylinder (dmlo.cylinder_config) than the model".to_string()
        } else if self.use_reflectance {
            return Err(Error::Model(format!(
                "{path}: reads the reflectance channel (dmlo.model_config.use_reflectance): not a \
                 range-only model"
            )));
        } else {
            return Ok(());
        };
        Err(Error::Model(format!(
            "{path}: the range-only model {differs} ({model_path}): every graph of a model folder reads \
             the same images"
        )))
    }

    /// Checks that this graph (at `path`) is the `graph` graph ("encoder", "frame", "match") of `model`'s
    /// weights (`model_path`'s): the same input size and cylinder image, the same `dmlo.model_config` but
    /// for the keys in `ignored` (e.g. [`MATCHING_STAGE_KEYS`]), and the same similarity scales where both
    /// graphs have them. The error ([`Error::Model`]) names `path` and what differs.
    pub fn check_export_of(
        &self,
        graph: &str,
        model: &ModelMetadata,
        ignored: &[&str],
        path: &str,
        model_path: &str,
    ) -> Result<()> {
        if self.graph != graph {
            return Err(Error::Model(format!(
                "{path}: a dmlo {:?} graph, not the {graph} graph of {model_path}'s model",
                self.graph
            )));
        }
        let mut differing = Vec::new();
        if [self.height, self.width] != [model.height, model.width] {
            differing.push("its input size".to_string());
        }
        if self.image_cylinder() != model.image_cylinder() {
            differing.push("its cylinder image".to_string());
        }
        let keys = self.model_config.keys().chain(model.model_config.keys());
        for key in keys.filter(|key| !ignored.contains(&key.as_str())) {
            let name = format!("dmlo.model_config.{key}");
            if self.model_config.get(key) != model.model_config.get(key) && !differing.contains(&name) {
                differing.push(name);
            }
        }
        if let (Some(ours), Some(theirs)) = (self.similarity_scales, model.similarity_scales) {
            if ours != theirs {
                differing.push("dmlo.similarity_scales".to_string());
            }
        }
        if differing.is_empty() {
            return Ok(());
        }
        Err(Error::Model(format!(
            "{path}: not the {graph} graph of {model_path}'s model ({} differ)",
            differing.join(", ")
        )))
    }

    /// The matching stage's settings for this model. Errors when the graph has no similarity scales
    /// (export the model again) or names an unknown `refine_offset`.
    pub fn dense_match_config(&self) -> Result<DenseMatchConfig> {
        let [coarse_scale, refine_scale] = self.similarity_scales.ok_or_else(|| {
            Error::Model("the graph has no dmlo.similarity_scales: export the model again with `dmlo export`".into())
        })?;
        let refine_offset = OffsetRule::from_name(&self.refine_offset).ok_or_else(|| {
            Error::Model(format!(
                "dmlo.model_config.refine_offset: expected \"window\" or \"peak_centroid\", got {:?}",
                self.refine_offset
            ))
        })?;
        Ok(DenseMatchConfig {
            coarse_window: self.coarse_window,
            refine_window: self.refine_window,
            stride: NETWORK_STRIDE,
            coarse_scale,
            refine_scale,
            refine_offset,
        })
    }
}

/// The cylinder image of a moving-object graph (`moving.onnx`) from its metadata entries (`key → value`);
/// errors name `path` and what is wrong: not a dmlo moving-object graph, or its image is not its input's.
pub fn moving_graph_cylinder(
    entries: &HashMap<String, String>,
    path: &str,
) -> Result<CylinderConfig> {
    match entries.get("dmlo.graph").map(String::as_str) {
        Some("moving") => {}
        Some(other) => {
            return Err(Error::Model(format!(
                "{path}: a dmlo {other:?} graph, not the moving-object network (moving.onnx)"
            )))
        }
        None => {
            return Err(Error::Model(format!(
                "{path}: no dmlo.graph in the graph's metadata: not a dmlo export"
            )))
        }
    }
    let text = |key: &str| {
        entries.get(key).ok_or_else(|| {
            Error::Model(format!(
                "{path}: no {key} in the graph's metadata: export it again with `dmlo export`"
            ))
        })
    };
    let value: Value = serde_json::from_str(text("dmlo.cylinder_config")?)
        .map_err(|e| Error::Model(format!("{path}: dmlo.cylinder_config is not JSON: {e}")))?;
    let cylinder = cylinder_config(&value, path)?;
    for (key, expected) in [
        ("dmlo.height", cylinder.height),
        ("dmlo.width", cylinder.width),
    ] {
        let size = text(key)?;
        if size.trim().parse::<usize>().ok() != Some(expected) {
            return Err(Error::Model(format!(
                "{path}: {key} = {size:?}, but its cylinder image (dmlo.cylinder_config) is {} × {}",
                cylinder.height, cylinder.width
            )));
        }
    }
    Ok(cylinder)
}

/// The cylinder of `dmlo.cylinder_config` (the fields `CylinderConfig` has; the derived ones it also
/// holds, such as the crop, follow from them), checked as the projection checks it.
fn cylinder_config(value: &Value, path: &str) -> Result<CylinderConfig> {
    let number = |key: &str| -> Result<f64> {
        value.get(key).and_then(Value::as_f64).ok_or_else(|| {
            Error::Model(format!(
                "{path}: dmlo.cylinder_config.{key} must be a number"
            ))
        })
    };
    let count = |key: &str| -> Result<usize> {
        value
            .get(key)
            .and_then(Value::as_u64)
            .and_then(|v| usize::try_from(v).ok())
            .ok_or_else(|| {
                Error::Model(format!(
                    "{path}: dmlo.cylinder_config.{key} must be a count"
                ))
            })
    };
    let cylinder = CylinderConfig {
        fov_up_deg: number("fov_up_deg")?,
        fov_down_deg: number("fov_down_deg")?,
        vertical_resolution_deg: number("vertical_resolution_deg")?,
        horizontal_resolution_deg: number("horizontal_resolution_deg")?,
        height: count("height")?,
        width: count("width")?,
    };
    cylinder
        .validate()
        .map_err(|e| Error::Model(format!("{path}: dmlo.cylinder_config: {e}")))?;
    Ok(cylinder)
}
