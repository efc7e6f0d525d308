#![forbid(unsafe_code)]
//! A model folder ([`ModelFolder`]) opened in one call: [`Odometry::open`]. It needs the encoder; the
//! wide window, the range-only model and the moving-object network are attached when the folder has them.
//!
//! The other graphs of an export (`frame.onnx`, `match.onnx`) are the ones `dmlo run` runs on a GPU; the
//! crate matches in its own stage and does not read them. Of `frame_wide.onnx` only the metadata is read:
//! its coarse window, applied to the encoder's features.
//!
//! ```no_run
//! # fn main() -> dmlo_rs::Result<()> {
//! use dmlo_rs::odometry::{Odometry, OdometryConfig, Scan};
//!
//! let mut odometry = Odometry::open("python/dmlo/models/default", OdometryConfig::default())?;
//! let points: Vec<[f32; 4]> = Vec::new(); // x, y, z, reflectance of one scan
//! let t_world_lidar = odometry.register(Scan::new(&points))?;
//! # let _ = t_world_lidar;
//! # Ok(())
//! # }
//! ```

use std::path::{Path, PathBuf};


use super::{
    graph_metadata, EncodedScan, Encoder, LearnedMatcher, ModelFolder, ModelMetadata,
    TractEncoder, TractMovingObjects,
};
use crate::error::{Error, Result};
use crate::odometry::config::OdometryConfig;
use crate::odometry::moving::MovingObjectNetwork;
use crate::odometry::pipeline::{EncodeAhead, FrameMatcher, Odometry};
use crate::projection::CylinderConfig;

impl ModelFolder {
    /// The learned matcher of this folder's model in `runtime`: its encoder, with the wide window of its
    /// `frame_wide.onnx` when there is one. Errors ([`Error::Model`]) name the file at fault.
    pub fn learned_matcher(&self, runtime: &Runtime) -> Result<LearnedMatcher<RuntimeEncoder>> {
        let shown = self.path().display();
        if !self.path().is_dir() {
            let what = if self.path().exists() {
                "not a folder"
            } else {
                "no such folder"
            };
            return Err(Error::Model(format!(
                "{shown}: {what}: a model folder holds {} (written by `dmlo export CHECKPOINT --out DIR`)",
                Self::ENCODER
            )));
        }
        let encoder = self.encoder();
        if !encoder.is_file() {
            return Err(Error::Model(format!(
                "{}: no such file: every model folder holds its encoder (written by `dmlo export CHECKPOINT --out DIR`)",
                encoder.display()
            )));
        }
        // The matching stage's settings come from the graph's metadata: an error there names the graph.
        let matcher =
            LearnedMatcher::new(RuntimeEncoder::open(&encoder, runtime)?).map_err(|e| match e {
                Error::Model(message) => Error::Model(format!("{}: {message}", encoder.display())),
                other => other,
            })?;
        let wide = self.wide_window();
        if !wide.is_file() {
            return Ok(matcher);
        }
        let coarse_window = wide_coarse_window(matcher.encoder().metadata(), &wide)?;
        matcher
            .with_wide_window(coarse_window)
            .map_err(|e| Error::Model(format!("{}: {e}", wide.display())))
    }

    /// The range-only model beside `model` in `runtime`, checked to take `model`'s image and not to read
    /// reflectance; `None` when the folder has no `range_only/`.
    fn range_only_matcher(
        &self,
        runtime: &Runtime,
        model: &LearnedMatcher<RuntimeEncoder>,
    ) -> Result<Option<LearnedMatcher<RuntimeEncoder>>> {
        let folder = self.range_only();
        if !folder.path().exists() {
            return Ok(None);
        }
        let encoder = folder.encoder();
        if encoder.is_file() {
            graph_metadata(&encoder)?.check_range_only_for(
                model.encoder().metadata(),
                &encoder.display().to_string(),
                &self.encoder().display().to_string(),
            )?;
        }
        folder.learned_matcher(runtime).map(Some)
    }
}

/// The coarse window of the wide-window graph at `path`, checked to be the frame graph of the encoder's
/// model (`encoder`: its metadata) but for its coarse window, since the wide window runs on the encoder's
/// features with the encoder's other settings.
fn wide_coarse_window(encoder: &ModelMetadata, path: &Path) -> Result<usize> {
    let wide = graph_metadata(path)?;
    let encoder_path = path.with_file_name(ModelFolder::ENCODER);
    wide.check_export_of(
        "frame",
        encoder,
        &["coarse_window"],
        &path.display().to_string(),
        &encoder_path.display().to_string(),
    )?;
    Ok(wide.coarse_window)
}

/// Which runtime runs a model folder's graphs.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
#[non_exhaustive]
pub enum Runtime {
    /// tract: pure Rust, nothing to install; its convolutions run on rayon's pool.
    #[default]
    Tract,
    /// onnxruntime, loaded from its shared library at `library` (a system install, or the Python wheel's
    /// `onnxruntime/capi/libonnxruntime.so.*`; a process loads one library, the first opened), with
    /// `threads` intra-op threads (0: its choice).
    #[cfg(feature = "onnxruntime")]
    Onnxruntime {
        /// The shared library.
        library: PathBuf,
        /// onnxruntime's intra-op threads; 0: its choice.
        threads: usize,
    },
}

/// An encoder in the runtime its model folder was opened with ([`Runtime`]).
#[derive(Debug)]
#[non_exhaustive]
pub enum RuntimeEncoder {
    /// Run by tract.
    Tract(TractEncoder),
    /// Run by onnxruntime.
    #[cfg(feature = "onnxruntime")]
    Onnxruntime(super::OrtEncoder),
}

impl RuntimeEncoder {
    /// Opens the encoder graph at `path` in `runtime` ([`TractEncoder::open`],
    /// [`super::OrtEncoder::open`]).
    pub fn open(path: impl AsRef<Path>, runtime: &Runtime) -> Result<Self> {
        match runtime {
            Runtime::Tract => TractEncoder::open(path).map(RuntimeEncoder::Tract),
            #[cfg(feature = "onnxruntime")]
            Runtime::Onnxruntime { library, threads } => {
                super::OrtEncoder::open(path, library, *threads).map(RuntimeEncoder::Onnxruntime)
            }
        }
    }
}

impl Encoder for RuntimeEncoder {
    fn metadata(&self) -> &ModelMetadata {
        match self {
            RuntimeEncoder::Tract(encoder) => encoder.metadata(),
            #[cfg(feature = "onnxruntime")]
            RuntimeEncoder::Onnxruntime(encoder) => encoder.metadata(),
        }
    }

    fn encode(&self, image: &[f32]) -> Result<EncodedScan> {
        match self {
            RuntimeEncoder::Tract(encoder) => encoder.encode(image),
            #[cfg(feature = "onnxruntime")]
            RuntimeEncoder::Onnxruntime(encoder) => encoder.encode(image),
        }
    }
}

/// The matcher of an odometry opened from a model folder ([`Odometry::open`]): the learned matcher in the
/// folder's runtime, ready to encode the next scan ahead ([`Odometry::register_ahead`]).
pub type FolderMatcher = EncodeAhead<LearnedMatcher<RuntimeEncoder>>;

impl Odometry<FolderMatcher> {
    /// The odometry of the model folder `model_dir` (module docs) with `config`, its graphs run by tract:
    /// the encoder with the wide window of `frame_wide.onnx`, the range-only model of `range_only/` and,
    /// with `moving_objects.detect`, the moving-object network of `moving.onnx`, each when the folder has
    /// it. Every graph's metadata is checked before the first scan: errors ([`Error::Model`]) name the
    /// file and what is wrong with it; a config out of its ranges is an [`Error::Config`].
    pub fn open(model_dir: impl AsRef<Path>, config: OdometryConfig) -> Result<Self> {
        Self::open_with_runtime(model_dir, config, &Runtime::Tract)
    }

    /// [`Odometry::open`] with the graphs run by `runtime`.
    pub fn open_with_runtime(
        model_dir: impl AsRef<Path>,
        config: OdometryConfig,
        runtime: &Runtime,
    ) -> Result<Self> {
        let folder = ModelFolder::new(model_dir.as_ref());
        let matcher = folder.learned_matcher(runtime)?;
        // A model that reads no reflectance runs on every scan: a range-only model beside it is not used.
        let range_only = if FrameMatcher::uses_reflectance(&matcher) {
            folder.range_only_matcher(runtime, &matcher)?
        } else {
            None
        };
        let detect_moving_objects = config.moving_objects.detect;
        let mut odometry = Odometry::new(EncodeAhead::new(matcher), config)?;
        if let Some(range_only) = range_only {
            odometry = odometry.with_range_only(EncodeAhead::new(range_only))?;
        }
        let moving = folder.moving_objects();
        if !detect_moving_objects || !moving.is_file() {
            return Ok(odometry);
        }
        match runtime {
            Runtime::Tract => with_moving_objects(
                odometry,
                TractMovingObjects::open(&moving)?,
                &moving,
                &folder,
            ),
            #[cfg(feature = "onnxruntime")]
            Runtime::Onnxruntime { library, threads } => with_moving_objects(
                odometry,
                super::OrtMovingObjects::open(&moving, library, *threads)?,
                &moving,
                &folder,
            ),
        }
    }
}

/// `odometry` with the moving-object `network` opened from `path`, checked to take the model's image.
fn with_moving_objects(
    odometry: Odometry<FolderMatcher>,
    network: impl MovingObjectNetwork + Send + Sync + 'static,
    path: &Path,
    folder: &ModelFolder,
) -> Result<Odometry<FolderMatcher>> {
    let cylinder = network.cylinder();
    check_same_image(
        path,
        "the moving-object network",
        ([cylinder.height, cylinder.width], cylinder),
        (
            odometry.matcher().matcher().encoder().input_size(),
            FrameMatcher::cylinder(odometry.matcher()),
        ),
        &folder.encoder(),
    )?;
    odometry.with_moving_objects(network)
}

/// An error naming `path` (`what` it holds) when its image — `[rows, columns]` and cylinder — is not the
/// model's, whose encoder is `model_path`: every graph of a folder reads the same scans' images.
fn check_same_image(
    path: &Path,
    what: &str,
    (image, cylinder): ([usize; 2], &CylinderConfig),
    (model_image, model_cylinder): ([usize; 2], &CylinderConfig),
    model_path: &Path,
) -> Result<()> {
    let differs = if image != model_image {
        format!(
            "takes {} × {} images, the model {} × {}",
            image[0], image[1], model_image[0], model_image[1]
        )
    } else if cylinder != model_cylinder {
        "takes the images of another cylinder (dmlo.cylinder_config) than the model".to_string()
    } else {
        return Ok(());
    };
    Err(Error::Model(format!(
        "{}: {what} {differs} ({}): every graph of a model folder reads the same images",
        path.display(),
        model_path.display()
    )))
}
