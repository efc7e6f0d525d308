#![forbid(unsafe_code)]
//! Where each graph of a model lies in its folder, as `dmlo export` writes it: the folder's layout, known
//! here alone (the runtimes' [`ModelFolder::learned_matcher`] and `Odometry::open` with feature
//! `inference`; Python's onnxruntime path through the binding).
//!
//! ```text
//! MODEL_DIR/
//!   encoder.onnx      the network's encoder: a scan's image in, its features out
//!   frame.onnx        the encoder and the matching stage in one graph (onnxruntime on a GPU)
//!   match.onnx        the matching stage on two scans' cached features (onnxruntime on a GPU)
//!   frame_wide.onnx   the frame graph with the wide coarse window, for pairs re-matched from the prediction
//!   range_only/       a model of this layout trained without reflectance, for scans without usable reflectance
//!   moving.onnx       the moving-object network, whose flagged points are left out of matching
//! ```

use std::path::{Path, PathBuf};

/// A model folder (module docs): the path of each of its graphs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ModelFolder {
    path: PathBuf,
}

impl ModelFolder {
    /// The encoder graph's file name.
    pub const ENCODER: &'static str = "encoder.onnx";
    /// The frame graph's file name: encoder and matching stage in one graph.
    pub const FRAME: &'static str = "frame.onnx";
    /// The match graph's file name: the matching stage on two scans' features.
    pub const MATCH: &'static str = "match.onnx";
    /// The file name of the frame graph exported with the wide coarse window.
    pub const WIDE_WINDOW: &'static str = "frame_wide.onnx";
    /// The sub-folder holding the range-only model.
    pub const RANGE_ONLY: &'static str = "range_only";
    /// The moving-object network's file name.
    pub const MOVING_OBJECTS: &'static str = "moving.onnx";

    /// The model folder at `path` (nothing is read yet).
    pub fn new(path: impl Into<PathBuf>) -> Self {
        ModelFolder { path: path.into() }
    }

    /// The folder.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Its encoder graph.
    pub fn encoder(&self) -> PathBuf {
        self.path.join(Self::ENCODER)
    }

    /// Its frame graph.
    pub fn frame(&self) -> PathBuf {
        self.path.join(Self::FRAME)
    }

    /// Its match graph.
    pub fn match_graph(&self) -> PathBuf {
        self.path.join(Self::MATCH)
    }

    /// Its wide-window graph.
    pub fn wide_window(&self) -> PathBuf {
        self.path.join(Self::WIDE_WINDOW)
    }

    /// Its range-only model's folder.
    pub fn range_only(&self) -> ModelFolder {
        ModelFolder::new(self.path.join(Self::RANGE_ONLY))
    }

    /// Its moving-object network.
    pub fn moving_objects(&self) -> PathBuf {
        self.path.join(Self::MOVING_OBJECTS)
    }
}
