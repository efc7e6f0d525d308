//! `Odometry::open`: the bundled model folder opened in one call, and broken folders named.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use prost::Message;

use super::{real_drive, root};
use crate::error::Error;
use crate::inference::{
    graph_metadata, LearnedMatcher, ModelFolder, TractEncoder, TractMovingObjects,
};
use crate::odometry::config::OdometryConfig;
use crate::odometry::pipeline::{FrameMatcher, Odometry, Scan};

fn bundled_folder() -> PathBuf {
    root().join("python/dmlo/models/default")
}

/// The learned matcher of `folder` built by hand, as the examples built it before `Odometry::open`.
fn matcher_by_hand(folder: &Path) -> LearnedMatcher<TractEncoder> {
    let wide = graph_metadata(folder.join("frame_wide.onnx")).unwrap();
    LearnedMatcher::new(TractEncoder::open(folder.join("encoder.onnx")).unwrap())
        .unwrap()
        .with_wide_window(wide.coarse_window)
        .unwrap()
}

/// A scratch model folder for one test, empty, removed when dropped.
struct ScratchFolder(PathBuf);

impl ScratchFolder {
    fn new(name: &str) -> Self {
        let path =
            std::env::temp_dir().join(format!("dmlo_model_folder_{name}_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&path);
        std::fs::create_dir_all(&path).unwrap();
        ScratchFolder(path)
    }

    /// The bundled graph `name` copied to `to` (in this folder), its metadata entries changed by `edit`.
    fn graph(&self, name: &str, to: &str, edit: impl FnOnce(&mut HashMap<String, String>)) {
        let bytes = std::fs::read(bundled_folder().join(name)).unwrap();
        let mut graph = tract_onnx::pb::ModelProto::decode(bytes.as_slice()).unwrap();
        let mut entries: HashMap<String, String> = graph
            .metadata_props
            .iter()
            .map(|entry| (entry.key.clone(), entry.value.clone()))
            .collect();
        edit(&mut entries);
        graph.metadata_props = entries
            .into_iter()
            .map(|(key, value)| tract_onnx::pb::StringStringEntryProto { key, value })
            .collect();
        let to = self.0.join(to);
        std::fs::create_dir_all(to.parent().unwrap()).unwrap();
        std::fs::write(to, graph.encode_to_vec()).unwrap();
    }
}

impl Drop for ScratchFolder {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn model_error(error: Error) -> String {
    match error {
        Error::Model(message) => message,
        other => panic!("expected Error::Model, got {other:?}"),
    }
}

fn open_error(folder: &Path) -> String {
    model_error(
        Odometry::open(folder, OdometryConfig::default())
            .err()
            .unwrap(),
    )
}

#[test]
fn the_bundled_folder_registers_real_scans_as_the_pipeline_built_by_hand() {
    let Some(scans) = real_drive("odometry_03") else {
        return;
    };
    let folder = bundled_folder();
    let mut opened = Odometry::open(&folder, OdometryConfig::default()).unwrap();
    assert!(opened.matcher().has_wide_window());
    let mut by_hand = Odometry::new(matcher_by_hand(&folder), OdometryConfig::default())
        .unwrap()
        .with_range_only(matcher_by_hand(&folder.join("range_only")))
        .unwrap()
        .with_moving_objects(TractMovingObjects::open(folder.join("moving.onnx")).unwrap())
        .unwrap();
    // The fourth scan without reflectance: both switch to the range-only model.
    let mut without_reflectance = scans[3].clone();
    without_reflectance.iter_mut().for_each(|p| p[3] = 0.0);
    for points in [&scans[0], &scans[1], &scans[2], &without_reflectance] {
        let pose = opened.register(Scan::new(points)).unwrap();
        assert_eq!(pose, by_hand.register(Scan::new(points)).unwrap());
    }
    for (opened, by_hand) in opened.diagnostics().iter().zip(by_hand.diagnostics()) {
        assert!(opened.num_moving_predicted.is_some_and(|n| n > 0));
        assert_eq!(opened.num_moving_predicted, by_hand.num_moving_predicted);
        assert_eq!(opened.num_inliers, by_hand.num_inliers);
    }
    assert!(opened.diagnostics()[1].num_inliers > 100);

    let mut config = OdometryConfig::default();
    config.moving_objects.detect = false;
    let mut without_network = Odometry::open(&folder, config).unwrap();
    without_network.register(Scan::new(&scans[0])).unwrap();
    assert_eq!(without_network.diagnostics()[0].num_moving_predicted, None);
}

#[test]
fn a_folder_without_a_range_only_model_refuses_scans_without_reflectance() {
    let folder = ScratchFolder::new("no_range_only");
    folder.graph("encoder.onnx", "encoder.onnx", |_| {});
    let mut odometry = Odometry::open(&folder.0, OdometryConfig::default()).unwrap();
    assert!(!odometry.matcher().has_wide_window());
    let dark: Vec<[f32; 4]> = (0..20_000)
        .map(|i| {
            let angle = i as f32 * 0.001;
            [
                10.0 * angle.cos(),
                10.0 * angle.sin(),
                (i % 40) as f32 * 0.1 - 1.7,
                0.0,
            ]
        })
        .collect();
    let error = odometry.register(Scan::new(&dark)).unwrap_err().to_string();
    assert!(error.contains("range-only"), "{error}");
}

#[test]
fn a_missing_folder_or_encoder_is_a_named_error() {
    let missing = root().join("no/such/model");
    let error = open_error(&missing);
    assert!(error.contains("no/such/model: no such folder"), "{error}");
    let file = open_error(&bundled_folder().join(ModelFolder::ENCODER));
    assert!(file.contains("encoder.onnx: not a folder"), "{file}");

    let empty = ScratchFolder::new("empty");
    let error = open_error(&empty.0);
    assert!(
        error.contains(&format!(
            "{}: no such file",
            empty.0.join("encoder.onnx").display()
        )),
        "{error}"
    );
    // A range-only folder without its encoder is a broken folder, not an absent model.
    let no_range_only_encoder = ScratchFolder::new("empty_range_only");
    no_range_only_encoder.graph("encoder.onnx", "encoder.onnx", |_| {});
    std::fs::create_dir(no_range_only_encoder.0.join("range_only")).unwrap();
    let error = open_error(&no_range_only_encoder.0);
    assert!(
        error.contains("range_only/encoder.onnx: no such file"),
        "{error}"
    );
}

#[test]
fn a_range_only_model_of_another_image_size_is_a_named_error() {
    let folder = ScratchFolder::new("range_only_size");
    folder.graph("encoder.onnx", "encoder.onnx", |_| {});
    folder.graph(
        "range_only/encoder.onnx",
        "range_only/encoder.onnx",
        |entries| {
            entries.insert("dmlo.width".into(), "896".into());
            entries.insert(
                "dmlo.cylinder_config".into(),
                r#"{"fov_up_deg": 2.0, "fov_down_deg": -24.9, "vertical_resolution_deg": 0.4,
                "horizontal_resolution_deg": 0.4, "height": 64, "width": 896}"#
                    .into(),
            );
        },
    );
    let error = open_error(&folder.0);
    assert!(
        error.contains("range_only/encoder.onnx: the range-only model takes 64 × 896 images, the model 64 × 1792"),
        "{error}"
    );
}

#[test]
fn a_graph_that_is_not_a_dmlo_export_is_a_named_error() {
    let folder = ScratchFolder::new("not_dmlo");
    folder.graph("encoder.onnx", "encoder.onnx", |entries| entries.clear());
    let error = open_error(&folder.0);
    assert!(
        error.contains(
            "encoder.onnx: no dmlo.interface_version in the graph's metadata: not a dmlo export"
        ),
        "{error}"
    );
}

#[test]
fn an_even_window_is_a_named_error() {
    let folder = ScratchFolder::new("even_window");
    folder.graph("encoder.onnx", "encoder.onnx", |entries| {
        let config =
            entries["dmlo.model_config"].replace("\"coarse_window\": 15", "\"coarse_window\": 14");
        entries.insert("dmlo.model_config".into(), config);
    });
    let error = open_error(&folder.0);
    assert!(
        error.contains(
            "encoder.onnx: dmlo.model_config.coarse_window must be an odd integer >= 3; got 14"
        ),
        "{error}"
    );
}

#[test]
fn a_wide_window_of_another_model_is_a_named_error() {
    let folder = ScratchFolder::new("other_wide");
    folder.graph("encoder.onnx", "encoder.onnx", |_| {});
    folder.graph("range_only/frame_wide.onnx", "frame_wide.onnx", |_| {});
    let error = open_error(&folder.0);
    assert!(
        error.contains("frame_wide.onnx: not the frame graph of")
            && error.contains("encoder.onnx's model")
            && error.contains("dmlo.similarity_scales"),
        "{error}"
    );
    let not_frame = ScratchFolder::new("wide_not_frame");
    not_frame.graph("encoder.onnx", "encoder.onnx", |_| {});
    not_frame.graph("encoder.onnx", "frame_wide.onnx", |_| {});
    let error = open_error(&not_frame.0);
    assert!(
        error.contains("frame_wide.onnx: a dmlo \"encoder\" graph, not the frame graph"),
        "{error}"
    );
}

#[cfg(feature = "onnxruntime")]
#[test]
fn the_bundled_folder_opened_in_onnxruntime_registers_as_the_pipeline_built_by_hand() {
    use crate::inference::{OrtEncoder, OrtMovingObjects, Runtime};

    let Some(library) = super::onnxruntime_library() else {
        return;
    };
    let Some(scans) = real_drive("odometry_03") else {
        return;
    };
    let folder = bundled_folder();
    let runtime = Runtime::Onnxruntime {
        library: library.clone(),
        threads: 0,
    };
    let mut opened =
        Odometry::open_with_runtime(&folder, OdometryConfig::default(), &runtime).unwrap();
    let by_hand_matcher = |folder: &Path| {
        let wide = graph_metadata(folder.join("frame_wide.onnx")).unwrap();
        LearnedMatcher::new(OrtEncoder::open(folder.join("encoder.onnx"), &library, 0).unwrap())
            .unwrap()
            .with_wide_window(wide.coarse_window)
            .unwrap()
    };
    let moving = OrtMovingObjects::open(folder.join("moving.onnx"), &library, 0).unwrap();
    let mut by_hand = Odometry::new(by_hand_matcher(&folder), OdometryConfig::default())
        .unwrap()
        .with_range_only(by_hand_matcher(&folder.join("range_only")))
        .unwrap()
        .with_moving_objects(moving)
        .unwrap();
    for points in &scans[..3] {
        let pose = opened.register(Scan::new(points)).unwrap();
        assert_eq!(pose, by_hand.register(Scan::new(points)).unwrap());
    }
    assert!(opened.diagnostics()[2].num_moving_predicted.is_some());
}
