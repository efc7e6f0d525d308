#![forbid(unsafe_code)]
//! The learned matcher from Rust: the network's encoder run on the exported `encoder.onnx` by
//! [tract](https://github.com/sonos/tract) (feature `inference`: pure Rust, no C/C++ runtime,
//! cross-compiles to ARM robots) or by onnxruntime (feature `onnxruntime`: `ort` loading the shared
//! library the system or the `onnxruntime` Python wheel has, `dmlo run`'s own runtime), and the crate's
//! own matching stage ([`crate::dense_match`]) on its features — the flow and confidence of every
//! reference cell, as `dmlo run` computes them, without Python.
//!
//! The moving-object network beside the encoder (`moving.onnx`) runs in the same runtimes
//! ([`TractMovingObjects`], [`OrtMovingObjects`]) for [`crate::odometry::pipeline::Odometry::with_moving_objects`].
//!
//! The model is found by an explicit path (nothing is downloaded); its settings travel in the graph's
//! metadata, written by `dmlo export`: the input size, the windows of the matching stage
//! (`dmlo.model_config`) and its two learned softmax scales (`dmlo.similarity_scales`), checked by
//! [`ModelMetadata::from_entries`]. A whole model folder — the encoder, its wide window, the range-only
//! model and the moving-object network — opens in one call, `Odometry::open` ([`ModelFolder`], which alone
//! knows the folder's layout); the pieces below are for a runtime or pipeline of one's own.
//!
//! ```no_run
//! # #[cfg(feature = "inference")]
//! # fn main() -> dmlo_rs::error::Result<()> {
//! use dmlo_rs::inference::{Encoder, LearnedMatcher, TractEncoder};
//!
//! let matcher = LearnedMatcher::new(TractEncoder::open("python/dmlo/models/default/encoder.onnx")?)?;
//! let [height, width] = matcher.encoder().input_size();
//! // Two scans' images: range (m) then reflectance ([0, 1]), channel-major, 0 where empty
//! // (`projection::project`).
//! let (reference, target) = (vec![0.0f32; 2 * height * width], vec![0.0f32; 2 * height * width]);
//! let reference = matcher.encoder().encode(&reference)?;
//! let target = matcher.encoder().encode(&target)?;
//! let flow = matcher.flow(&reference, &target)?; // then `matches::decode_matches`, NMS, RANSAC
//! # let _ = flow;
//! # Ok(())
//! # }
//! # #[cfg(not(feature = "inference"))]
//! # fn main() {}
//! ```

mod folder;
mod metadata;
#[cfg(feature = "inference")]
mod model_folder;
#[cfg(feature = "onnxruntime")]
mod onnxruntime;
#[cfg(feature = "inference")]
mod tract;

pub use folder::ModelFolder;
pub use metadata::{moving_graph_cylinder, ModelMetadata, MATCHING_STAGE_KEYS};
#[cfg(feature = "inference")]
pub use model_folder::{FolderMatcher, Runtime, RuntimeEncoder};
#[cfg(feature = "onnxruntime")]
pub use onnxruntime::{OrtEncoder, OrtMovingObjects};
#[cfg(feature = "inference")]
pub use tract::{graph_metadata, TractEncoder, TractMovingObjects};

use crate::dense_match::{self, DenseFlow, DenseMatchConfig, FeatureMap, ScanFeatures};
use crate::error::{Error, Result};
use crate::odometry::pipeline::FrameMatcher;
use crate::projection::CylinderConfig;

/// One scan encoded by the network: coarse features `(C, H / stride, W / stride)` and refine features
/// `(Cr, H, W)`, channel-major as the graph writes them. Cache it: a scan is the target of one pair and
/// the reference of the next.
#[derive(Debug, Clone, PartialEq)]
pub struct EncodedScan {
    /// Coarse features, `coarse_shape[0] · coarse_shape[1] · coarse_shape[2]` values.
    pub coarse: Vec<f32>,
    /// `(channels, rows, columns)` of the coarse features.
    pub coarse_shape: [usize; 3],
    /// Refine features at full resolution.
    pub refine: Vec<f32>,
    /// `(channels, rows, columns)` of the refine features.
    pub refine_shape: [usize; 3],
}

impl EncodedScan {
    /// The encoder graph's two outputs (values and `(channels, rows, columns)`), the refine features
    /// checked to be at the input's `[rows, columns]`; errors name the graph (`path`).
    #[cfg(any(feature = "inference", feature = "onnxruntime"))]
    pub(crate) fn from_outputs(
        path: &str,
        (coarse, coarse_shape): (Vec<f32>, [usize; 3]),
        (refine, refine_shape): (Vec<f32>, [usize; 3]),
        [rows, columns]: [usize; 2],
    ) -> Result<Self> {
        if refine_shape[1..] != [rows, columns] {
            return Err(Error::Model(format!(
                "{path}: refine features {refine_shape:?} are not at the input's resolution {rows} × {columns}"
            )));
        }
        Ok(EncodedScan {
            coarse,
            coarse_shape,
            refine,
            refine_shape,
        })
    }

    /// The features as the matching stage reads them.
    pub fn features(&self) -> ScanFeatures<'_> {
        ScanFeatures {
            coarse: feature_map(&self.coarse, self.coarse_shape),
            refine: feature_map(&self.refine, self.refine_shape),
        }
    }
}

fn feature_map(data: &[f32], [channels, height, width]: [usize; 3]) -> FeatureMap<'_> {
    FeatureMap {
        data,
        channels,
        height,
        width,
    }
}

/// A network's encoder: a scan's image in, its features out. [`TractEncoder`] runs the exported graph;
/// another runtime (onnxruntime, a GPU) plugs in behind the same trait.
pub trait Encoder {
    /// The settings the graph was exported with.
    fn metadata(&self) -> &ModelMetadata;
    /// `[rows, columns]` of the images the encoder takes.
    fn input_size(&self) -> [usize; 2] {
        let metadata = self.metadata();
        [metadata.height, metadata.width]
    }
    /// Encodes one image, `(2, rows, columns)` channel-major: range in metres, then reflectance in
    /// [0, 1]; 0 where a cell is empty. Errors name a wrong length or a non-finite value.
    fn encode(&self, image: &[f32]) -> Result<EncodedScan>;
}

/// The learned matcher: an [`Encoder`] and the crate's matching stage with the model's windows and scales.
#[derive(Debug)]
pub struct LearnedMatcher<E: Encoder> {
    encoder: E,
    config: DenseMatchConfig,
    cylinder: CylinderConfig,
    wide: Option<DenseMatchConfig>,
}

impl<E: Encoder> LearnedMatcher<E> {
    /// The matcher of `encoder`'s model, its matching stage set from the graph's metadata.
    pub fn new(encoder: E) -> Result<Self> {
        let config = encoder.metadata().dense_match_config()?;
        let cylinder = encoder.metadata().image_cylinder();
        Ok(LearnedMatcher {
            encoder,
            config,
            cylinder,
            wide: None,
        })
    }

    /// The matcher with the wide coarse window of the model's `frame_wide.onnx` (its metadata's
    /// `coarse_window`, [`graph_metadata`]) for pairs re-matched from the prediction: the same weights,
    /// a wider search.
    pub fn with_wide_window(mut self, coarse_window: usize) -> Result<Self> {
        if coarse_window <= self.config.coarse_window {
            return Err(Error::invalid(
                "coarse_window",
                format!(
                    "{coarse_window} is not wider than the model's window ({})",
                    self.config.coarse_window
                ),
            ));
        }
        self.wide = Some(DenseMatchConfig {
            coarse_window,
            ..self.config
        });
        Ok(self)
    }

    /// The encoder, to encode scans (and cache their features).
    pub fn encoder(&self) -> &E {
        &self.encoder
    }

    /// The matching stage's settings (windows, stride, softmax scales).
    pub fn config(&self) -> &DenseMatchConfig {
        &self.config
    }

    /// The flow of every `reference` cell into `target` and its confidence (paper §III-C).
    pub fn flow(&self, reference: &EncodedScan, target: &EncodedScan) -> Result<DenseFlow> {
        dense_match::match_features(&reference.features(), &target.features(), &self.config)
    }
}

/// The learned matcher as [`crate::odometry::pipeline::Odometry`] runs it.
impl<E: Encoder> FrameMatcher for LearnedMatcher<E> {
    type Features = EncodedScan;

    fn cylinder(&self) -> &CylinderConfig {
        &self.cylinder
    }

    fn uses_reflectance(&self) -> bool {
        self.encoder.metadata().use_reflectance
    }

    fn encode(&self, image: &[f32]) -> Result<EncodedScan> {
        self.encoder.encode(image)
    }

    fn flow(&self, reference: &EncodedScan, target: &EncodedScan) -> Result<DenseFlow> {
        LearnedMatcher::flow(self, reference, target)
    }

    fn flow_of_cells(
        &self,
        reference: &EncodedScan,
        target: &EncodedScan,
        cells: &[bool],
    ) -> Result<DenseFlow> {
        dense_match::match_features_of_cells(
            &reference.features(),
            &target.features(),
            &self.config,
            cells,
        )
    }

    fn guided_flow_of_cells(
        &self,
        reference: &EncodedScan,
        target: &EncodedScan,
        cells: &[bool],
        expected: &[[f32; 2]],
    ) -> Result<Option<DenseFlow>> {
        dense_match::match_features_guided(
            &reference.features(),
            &target.features(),
            &self.config,
            Some(cells),
            expected,
        )
        .map(Some)
    }

    fn has_wide_window(&self) -> bool {
        self.wide.is_some()
    }

    fn wide_flow(
        &self,
        reference: &EncodedScan,
        target: &EncodedScan,
        _target_image: &[f32],
    ) -> Result<DenseFlow> {
        let wide = self
            .wide
            .as_ref()
            .ok_or_else(|| Error::Model("the matcher has no wide window".into()))?;
        dense_match::match_features(&reference.features(), &target.features(), wide)
    }
}

/// Checks an image for [`Encoder::encode`]: `2 · rows · columns` finite values.
#[cfg(any(feature = "inference", feature = "onnxruntime"))]
pub(crate) fn check_image(image: &[f32], [rows, columns]: [usize; 2]) -> Result<()> {
    let expected = 2 * rows * columns;
    if image.len() != expected {
        return Err(Error::invalid(
            "image",
            format!(
                "expected 2 × {rows} × {columns} = {expected} values (range, then reflectance), got {}",
                image.len()
            ),
        ));
    }
    if let Some(i) = image.iter().position(|v| !v.is_finite()) {
        let (channel, cell) = (i / (rows * columns), i % (rows * columns));
        return Err(Error::invalid(
            "image",
            format!(
                "value {} at channel {channel}, row {}, column {} is not finite",
                image[i],
                cell / columns,
                cell % columns
            ),
        ));
    }
    Ok(())
}

/// Checks the moving-object network's two images (range, height): `rows · columns` finite values each.
#[cfg(any(feature = "inference", feature = "onnxruntime"))]
pub(crate) fn check_moving_images(
    range: &[f32],
    height: &[f32],
    [rows, columns]: [usize; 2],
) -> Result<()> {
    for (name, image) in [("range", range), ("height", height)] {
        if image.len() != rows * columns {
            return Err(Error::invalid(
                name,
                format!(
                    "expected {rows} × {columns} = {} values, got {}",
                    rows * columns,
                    image.len()
                ),
            ));
        }
        if let Some(i) = image.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(
                name,
                format!(
                    "value {} at row {}, column {} is not finite",
                    image[i],
                    i / columns,
                    i % columns
                ),
            ));
        }
    }
    Ok(())
}

#[cfg(all(test, feature = "inference"))]
mod tests;
