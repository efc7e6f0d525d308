use std::collections::HashMap;
use std::io::Write;
use std::path::PathBuf;

use serde_json::Value;

use super::*;
use crate::odometry::moving::MovingObjectNetwork;
use crate::projection::{project_flat, CylinderConfig};
use crate::scan_file::{kitti_scan_files, read_kitti_scan};

mod model_folder;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn bundled_encoder() -> PathBuf {
    root().join("python/dmlo/models/default/encoder.onnx")
}

/// `found`, what a test needs from outside the repository (`what`), or `None` when it is absent: the test
/// then returns early, and says it skipped past the harness's capture of its output, so that a skip is
/// never read as a pass. Under `CI=true`, where `.ci/setup` provides all of it, an absence fails the test.
fn needed<T>(found: Option<T>, what: &str) -> Option<T> {
    let under_ci = std::env::var("CI").as_deref() == Ok("true");
    // Straight to stderr: the harness captures `eprintln!` of passing tests.
    skip_or_fail(found, what, under_ci, &mut std::io::stderr())
}

/// [`needed`]'s rule, its skip line written to `report`.
fn skip_or_fail<T>(
    found: Option<T>,
    what: &str,
    under_ci: bool,
    report: &mut dyn Write,
) -> Option<T> {
    if found.is_some() {
        return found;
    }
    let test = std::thread::current()
        .name()
        .unwrap_or("a test")
        .to_string();
    assert!(
        !under_ci,
        "{test}: {what} is missing, and under CI=true it must be there"
    );
    let _ = writeln!(report, "SKIPPED {test}: {what} is missing");
    None
}

#[test]
fn a_missing_resource_skips_the_test_but_fails_it_under_ci() {
    let mut report = Vec::new();
    assert_eq!(
        skip_or_fail(None::<()>, "the data", false, &mut report),
        None
    );
    let report = String::from_utf8(report).unwrap();
    assert_eq!(
        report,
        "SKIPPED inference::tests::a_missing_resource_skips_the_test_but_fails_it_under_ci: the data is missing\n"
    );
    let under_ci =
        std::panic::catch_unwind(|| skip_or_fail(None::<()>, "the data", true, &mut Vec::new()));
    assert!(under_ci.is_err());
    let mut silent = Vec::new();
    assert_eq!(
        skip_or_fail(Some(7), "the data", true, &mut silent),
        Some(7)
    );
    assert!(silent.is_empty());
}

/// `../shared/data`, the real scans the tests compare against; `None` (the test skips) without it.
fn shared_data() -> Option<PathBuf> {
    let folder = root().join("../shared/data");
    needed(
        folder.is_dir().then_some(folder),
        "../shared/data (the real scans)",
    )
}

/// The scan `name` under `../shared/data`; `None` (the test skips) without the folder, a panic naming the
/// file when the folder is there without it.
fn shared_scan(name: &str) -> Option<Vec<[f32; 4]>> {
    let path = shared_data()?.join(name);
    Some(read_kitti_scan(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display())))
}

/// The network input `[2, H, W]` (range, reflectance) of a real KITTI scan under `../shared/data/`.
fn real_image(name: &str) -> Option<Vec<f32>> {
    real_scan_images(name).map(|(image, _, _)| image)
}

/// The largest difference between every `step`-th of `values` and a fixture's samples of them
/// (`expected`, as many: checked).
fn worst_sample_difference(values: &[f32], expected: &Value, step: usize, what: &str) -> f64 {
    let expected: Vec<f64> = expected
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let sampled: Vec<f32> = values.iter().step_by(step).copied().collect();
    assert_eq!(sampled.len(), expected.len(), "{what}");
    sampled
        .iter()
        .zip(&expected)
        .map(|(&a, &b)| (a as f64 - b).abs())
        .fold(0.0, f64::max)
}

#[test]
fn tract_features_equal_onnxruntimes_on_a_real_scan() {
    let fixture: Value = serde_json::from_str(
        &std::fs::read_to_string(root().join("tests/fixtures/encoder_features.json")).unwrap(),
    )
    .unwrap();
    let Some(image) = real_image(fixture["scan"].as_str().unwrap()) else {
        return;
    };
    let encoder = TractEncoder::open(bundled_encoder()).unwrap();
    assert_eq!(encoder.input_size(), [64, 1792]);
    let encoded = encoder.encode(&image).unwrap();
    assert_eq!(encoded.coarse_shape, [32, 16, 224]);
    assert_eq!(encoded.refine_shape, [8, 64, 1792]);
    let step = fixture["step"].as_u64().unwrap() as usize;
    for (name, values) in [("coarse", &encoded.coarse), ("refine", &encoded.refine)] {
        let worst = worst_sample_difference(values, &fixture[name], step, name);
        assert!(
            worst < 1e-5,
            "{name}: largest difference from onnxruntime {worst}"
        );
        let sum: f64 = values.iter().map(|&v| v as f64).sum();
        let expected_sum = fixture[format!("{name}_sum")].as_f64().unwrap();
        assert!(
            (sum - expected_sum).abs() < 1e-2,
            "{name}: sum {sum} against {expected_sum}"
        );
    }
}

#[test]
fn a_scan_matched_with_itself_stays_in_place() {
    let Some(image) = real_image("kitti_real/odometry_03/velodyne/000000.bin") else {
        return;
    };
    let matcher = LearnedMatcher::new(TractEncoder::open(bundled_encoder()).unwrap()).unwrap();
    assert_eq!(matcher.config().coarse_window, 15);
    let encoded = matcher.encoder().encode(&image).unwrap();
    let dense = matcher.flow(&encoded, &encoded).unwrap();
    let cells = dense.height * dense.width;
    let filled: Vec<usize> = (0..cells).filter(|&i| image[i] > 0.0).collect();
    let still = filled
        .iter()
        .filter(|&&i| dense.flow[i].abs() < 1.0 && dense.flow[cells + i].abs() < 1.0)
        .count();
    // The 2×2 window's centroid (Eq. 11) sits up to half a pixel off a sharp peak, so "in place" is within a
    // pixel, and not every cell: flat, featureless patches match loosely even against themselves.
    assert!(
        still as f64 > 0.8 * filled.len() as f64,
        "{still} of {} filled cells stay within a pixel",
        filled.len()
    );
}

#[test]
fn the_wide_window_is_the_bundled_frame_wide_graphs_and_matches_wider() {
    let wide = bundled_encoder().with_file_name("frame_wide.onnx");
    let coarse_window = graph_metadata(&wide).unwrap().coarse_window;
    assert_eq!(coarse_window, 41);
    let matcher = LearnedMatcher::new(TractEncoder::open(bundled_encoder()).unwrap()).unwrap();
    assert!(!FrameMatcher::has_wide_window(&matcher));
    let narrower = LearnedMatcher::new(TractEncoder::open(bundled_encoder()).unwrap())
        .unwrap()
        .with_wide_window(15)
        .unwrap_err();
    assert!(
        narrower.to_string().starts_with("coarse_window:"),
        "{narrower}"
    );
    let matcher = matcher.with_wide_window(coarse_window).unwrap();
    assert!(FrameMatcher::has_wide_window(&matcher));
    let Some((image, _, _)) = real_scan_images("kitti_real/odometry_03/velodyne/000000.bin") else {
        return;
    };
    let Some((target, _, _)) = real_scan_images("kitti_real/odometry_03/velodyne/000001.bin")
    else {
        return;
    };
    let reference = matcher.encoder().encode(&image).unwrap();
    let target_features = matcher.encoder().encode(&target).unwrap();
    let wide = matcher
        .wide_flow(&reference, &target_features, &target)
        .unwrap();
    let expected = crate::dense_match::match_features(
        &reference.features(),
        &target_features.features(),
        &DenseMatchConfig {
            coarse_window,
            ..*matcher.config()
        },
    )
    .unwrap();
    assert_eq!(wide, expected);
    assert!(graph_metadata("no/such/frame_wide.onnx").is_err());

    // The model's own window on the cells that hold a point: the crate's stage asked for those.
    let occupied: Vec<bool> = image[..image.len() / 2].iter().map(|&r| r > 0.0).collect();
    let asked = matcher
        .flow_of_cells(&reference, &target_features, &occupied)
        .unwrap();
    let expected = crate::dense_match::match_features_of_cells(
        &reference.features(),
        &target_features.features(),
        matcher.config(),
        &occupied,
    )
    .unwrap();
    // NaN where not asked: compared bit for bit.
    let bits = |values: &[f32]| values.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&asked.flow), bits(&expected.flow));
    assert_eq!(asked.confidence, expected.confidence);
    assert!(occupied.iter().any(|&o| !o) && asked.flow.iter().any(|v| v.is_nan()));
}

#[test]
fn bad_models_are_named_errors() {
    let missing = TractEncoder::open("no/such/encoder.onnx").unwrap_err();
    assert!(
        matches!(&missing, Error::Model(m) if m.contains("no/such/encoder.onnx") && m.contains("no such file"))
    );
    let frame = bundled_encoder().with_file_name("frame.onnx");
    let not_encoder = TractEncoder::open(&frame).unwrap_err();
    assert!(
        matches!(&not_encoder, Error::Model(m) if m.contains("frame.onnx") && m.contains("not the encoder")),
        "{not_encoder}"
    );
    let text = std::env::temp_dir().join(format!("dmlo_not_onnx_{}.onnx", std::process::id()));
    std::fs::write(&text, b"not a graph").unwrap();
    let garbage = TractEncoder::open(&text).unwrap_err();
    std::fs::remove_file(&text).unwrap();
    assert!(
        matches!(&garbage, Error::Model(m) if m.contains("not an ONNX graph")),
        "{garbage}"
    );
}

#[test]
fn bad_images_are_named_errors() {
    let encoder = TractEncoder::open(bundled_encoder()).unwrap();
    let short = encoder.encode(&[0.0; 10]).unwrap_err();
    assert!(
        matches!(&short, Error::InvalidArgument { argument: "image", reason } if reason.contains("229376"))
    );
    let mut image = vec![0.0f32; 2 * 64 * 1792];
    image[64 * 1792 + 3 * 1792 + 7] = f32::NAN;
    let nan = encoder.encode(&image).unwrap_err();
    assert!(
        matches!(&nan, Error::InvalidArgument { reason, .. } if reason.contains("channel 1, row 3, column 7")),
        "{nan}"
    );
}

fn entries(pairs: &[(&str, &str)]) -> HashMap<String, String> {
    pairs
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect()
}

#[test]
fn metadata_is_read_and_checked() {
    let good = [
        ("dmlo.interface_version", "1"),
        ("dmlo.graph", "encoder"),
        ("dmlo.height", "64"),
        ("dmlo.width", "1792"),
        (
            "dmlo.model_config",
            r#"{"coarse_window": 15, "refine_window": 7, "refine_offset": "window"}"#,
        ),
        (
            "dmlo.similarity_scales",
            r#"{"coarse": 13.2, "refine": 11.1}"#,
        ),
    ];
    let metadata = ModelMetadata::from_entries(&entries(&good), "m.onnx").unwrap();
    assert_eq!(metadata.cylinder, None); // exported before the cylinder was written
    let config = metadata.dense_match_config().unwrap();
    assert_eq!(
        (config.coarse_window, config.refine_window, config.stride),
        (15, 7, [4, 8])
    );
    assert_eq!((config.coarse_scale, config.refine_scale), (13.2, 11.1));

    let without = |key: &str| {
        entries(
            &good
                .iter()
                .copied()
                .filter(|(k, _)| *k != key)
                .collect::<Vec<_>>(),
        )
    };
    let err = ModelMetadata::from_entries(&without("dmlo.height"), "m.onnx").unwrap_err();
    assert!(
        matches!(&err, Error::Model(m) if m.contains("m.onnx") && m.contains("dmlo.height")),
        "{err}"
    );
    let old = ModelMetadata::from_entries(&without("dmlo.similarity_scales"), "m.onnx").unwrap();
    assert!(
        matches!(old.dense_match_config(), Err(Error::Model(m)) if m.contains("export the model again"))
    );

    let mut bad = entries(&good);
    bad.insert(
        "dmlo.model_config".into(),
        r#"{"coarse_window": -1, "refine_window": 7}"#.into(),
    );
    assert!(
        matches!(ModelMetadata::from_entries(&bad, "m.onnx"), Err(Error::Model(m)) if m.contains("coarse_window"))
    );
    bad.insert("dmlo.model_config".into(), "{not json".into());
    assert!(
        matches!(ModelMetadata::from_entries(&bad, "m.onnx"), Err(Error::Model(m)) if m.contains("not JSON"))
    );
    let mut scales = entries(&good);
    scales.insert(
        "dmlo.similarity_scales".into(),
        r#"{"coarse": 0, "refine": 11.1}"#.into(),
    );
    assert!(
        matches!(ModelMetadata::from_entries(&scales, "m.onnx"), Err(Error::Model(m)) if m.contains("coarse"))
    );
    // The matching stage's settings, each named with what it must be.
    let with_config = |config: &str| {
        let mut entries = entries(&good);
        entries.insert("dmlo.model_config".into(), config.into());
        ModelMetadata::from_entries(&entries, "m.onnx")
    };
    for (config, message) in [
        (
            r#"{"coarse_window": 14, "refine_window": 7, "refine_offset": "window"}"#,
            "m.onnx: dmlo.model_config.coarse_window must be an odd integer >= 3; got 14",
        ),
        (
            r#"{"coarse_window": 15, "refine_window": 1, "refine_offset": "window"}"#,
            "m.onnx: dmlo.model_config.refine_window must be an odd integer >= 3; got 1",
        ),
        (
            r#"{"refine_window": 7, "refine_offset": "window"}"#,
            "m.onnx: dmlo.model_config.coarse_window must be an odd integer >= 3; it lacks it",
        ),
        (
            r#"{"coarse_window": 15, "refine_window": 7, "refine_offset": "x"}"#,
            "m.onnx: dmlo.model_config.refine_offset must be one of window, peak_centroid; got \"x\"",
        ),
        (
            r#"{"coarse_window": 15, "refine_window": 7}"#,
            "m.onnx: dmlo.model_config.refine_offset must be one of window, peak_centroid; it lacks it",
        ),
        (
            r#"{"coarse_window": 15, "refine_window": 7, "refine_offset": "window", "use_reflectance": 1}"#,
            "m.onnx: dmlo.model_config.use_reflectance must be true or false; got 1",
        ),
        ("[15, 7]", "m.onnx: dmlo.model_config must be a JSON object"),
    ] {
        let error = with_config(config).unwrap_err();
        assert_eq!(error, Error::Model(message.into()));
    }
    let range_only = with_config(
        r#"{"coarse_window": 15, "refine_window": 7, "refine_offset": "peak_centroid", "use_reflectance": false}"#,
    )
    .unwrap();
    assert!(!range_only.use_reflectance);
    assert_eq!(
        range_only.dense_match_config().unwrap().refine_offset,
        crate::dense_match::OffsetRule::PeakCentroid
    );

    let mut version = entries(&good);
    version.insert("dmlo.interface_version".into(), "2".into());
    let error = ModelMetadata::from_entries(&version, "m.onnx").unwrap_err();
    assert!(
        matches!(&error, Error::Model(m) if m.starts_with("m.onnx: dmlo.interface_version \"2\"")),
        "{error}"
    );
    let error =
        ModelMetadata::from_entries(&without("dmlo.interface_version"), "m.onnx").unwrap_err();
    assert!(
        matches!(&error, Error::Model(m) if m.contains("no dmlo.interface_version") && m.contains("not a dmlo export")),
        "{error}"
    );
}

#[test]
fn the_cylinder_is_read_from_the_metadata_and_checked() {
    let kitti = r#"{"col_of_zero_azimuth": 896.0, "crop_left": 4, "fov_down_deg": -24.9, "fov_up_deg": 2.0,
        "height": 64, "horizontal_resolution_deg": 0.2, "vertical_resolution_deg": 0.4, "width": 1792}"#;
    let with = |cylinder: &str, width: &str| {
        entries(&[
            ("dmlo.interface_version", "1"),
            ("dmlo.graph", "encoder"),
            ("dmlo.height", "64"),
            ("dmlo.width", width),
            (
                "dmlo.model_config",
                r#"{"coarse_window": 15, "refine_window": 7, "refine_offset": "window"}"#,
            ),
            ("dmlo.cylinder_config", cylinder),
        ])
    };
    let metadata = ModelMetadata::from_entries(&with(kitti, "1792"), "m.onnx").unwrap();
    assert_eq!(metadata.cylinder, Some(CylinderConfig::kitti()));
    let named = |entries: HashMap<String, String>, what: &str| {
        let err = ModelMetadata::from_entries(&entries, "m.onnx").unwrap_err();
        assert!(matches!(&err, Error::Model(m) if m.contains(what)), "{err}");
    };
    named(with(kitti, "896"), "the input 64 × 896");
    named(
        with(&kitti.replace("0.4,", "\"x\","), "1792"),
        "vertical_resolution_deg",
    );
    named(
        with(&kitti.replace("0.4,", "-0.4,"), "1792"),
        "dmlo.cylinder_config",
    );
    let bundled = TractEncoder::open(bundled_encoder()).unwrap();
    assert_eq!(bundled.metadata().cylinder, Some(CylinderConfig::kitti()));
}

/// A real KITTI scan under `../shared/data`: its network image (range, then reflectance), its range
/// image and its point image (each cell's kept point, NaN where empty).
fn real_scan_images(name: &str) -> Option<(Vec<f32>, Vec<f32>, Vec<f32>)> {
    let scan = shared_scan(name)?;
    let points: &[f32] = scan.as_flattened();
    let projection = project_flat(points, 4, &CylinderConfig::kitti()).unwrap();
    let cell_points = projection
        .index
        .iter()
        .flat_map(|&i| match usize::try_from(i) {
            Ok(i) => [points[4 * i], points[4 * i + 1], points[4 * i + 2]],
            Err(_) => [f32::NAN; 3],
        })
        .collect();
    let image = [&projection.range[..], &projection.reflectance].concat();
    Some((image, projection.range, cell_points))
}

#[test]
fn the_learned_pair_from_rust_equals_the_python_odometrys() {
    use crate::pair::{match_pair, PairConfig, PairImages};

    let fixture: Value = serde_json::from_str(
        &std::fs::read_to_string(root().join("tests/fixtures/pair_motion.json")).unwrap(),
    )
    .unwrap();
    let scans = fixture["scans"].as_array().unwrap();
    let (Some(reference), Some(target)) = (
        real_scan_images(scans[0].as_str().unwrap()),
        real_scan_images(scans[1].as_str().unwrap()),
    ) else {
        return;
    };
    let matcher = LearnedMatcher::new(TractEncoder::open(bundled_encoder()).unwrap()).unwrap();
    let flow = matcher
        .flow(
            &matcher.encoder().encode(&reference.0).unwrap(),
            &matcher.encoder().encode(&target.0).unwrap(),
        )
        .unwrap();
    let images = PairImages {
        ref_points: Some(&reference.2),
        ..PairImages::new(&reference.1, &target.1, &flow.flow, &flow.confidence)
    };
    let cylinder = CylinderConfig::kitti();
    let pair = match_pair(&images, &cylinder, &PairConfig::default(), true).unwrap();
    let expected: Vec<f64> = fixture["T_tgt_ref"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|row| row.as_array().unwrap().iter().map(|v| v.as_f64().unwrap()))
        .collect();
    let expected = nalgebra::Matrix4::from_row_slice(&expected);
    let got = pair.transform.to_homogeneous();
    // tract's features differ from onnxruntime's in the last float32 digits: the same matches, the same
    // consensus, the motion within a micrometre and a microradian.
    let translation = (got.fixed_view::<3, 1>(0, 3) - expected.fixed_view::<3, 1>(0, 3)).norm();
    let rotation = (got.fixed_view::<3, 3>(0, 0) - expected.fixed_view::<3, 3>(0, 0)).norm();
    assert!(
        translation < 1e-6 && rotation < 1e-6,
        "{translation} m, {rotation}"
    );
    assert_eq!(
        pair.source.len() as u64,
        fixture["num_matches"].as_u64().unwrap()
    );
    assert_eq!(
        pair.num_inliers as u64,
        fixture["num_inliers"].as_u64().unwrap()
    );
}

/// The `.bin` scans of a real set under `../shared/data/kitti_real`, in name order; None without them.
fn real_drive(name: &str) -> Option<Vec<Vec<[f32; 4]>>> {
    let folder = shared_data()?
        .join("kitti_real")
        .join(name)
        .join("velodyne");
    let files = kitti_scan_files(&folder).unwrap_or_else(|e| panic!("{e}"));
    Some(
        files
            .iter()
            .map(|path| read_kitti_scan(path).unwrap())
            .collect(),
    )
}

/// The runs of `odometry_poses.json` whose chains tract's features keep (within `assert_pose_is`'s bound).
const TRACT_AGREES: [&str; 4] = [
    "odometry_03/mapping",
    "odometry_03/frame_to_frame",
    "odometry_01/mapping",
    "odometry_01/frame_to_frame",
];

#[test]
fn the_rust_odometry_over_tract_equals_the_python_odometry_on_real_drives() {
    use crate::odometry::config::OdometryConfig;
    use crate::odometry::pipeline::{Odometry, Scan};

    let fixture: Value = serde_json::from_str(
        &std::fs::read_to_string(root().join("tests/fixtures/odometry_poses.json")).unwrap(),
    )
    .unwrap();
    // Where no RANSAC inlier flips between tract's features and onnxruntime's (docs/measurements.md).
    for key in TRACT_AGREES {
        let expected = &fixture[key];
        let (name, mode) = key.split_once('/').unwrap();
        let Some(scans) = real_drive(name) else {
            return;
        };
        let mut config = OdometryConfig::default();
        config.mapping.enabled = mode == "mapping";
        let matcher = LearnedMatcher::new(TractEncoder::open(bundled_encoder()).unwrap()).unwrap();
        let mut odometry = Odometry::new(matcher, config).unwrap();
        let expected = expected.as_array().unwrap();
        assert_eq!(expected.len(), scans.len(), "{key}");
        for (i, (points, row)) in scans.iter().zip(expected).enumerate() {
            let pose = odometry.register(Scan::new(points)).unwrap();
            assert_pose_is(&pose, row, &format!("{key}, scan {i}"));
        }
    }
}

/// The onnxruntime shared library `dmlo run` uses: `ORT_DYLIB_PATH`, else the Python wheel's in `.venv`
/// (`.ci/setup` installs it); `None` (the test skips) without one.
#[cfg(feature = "onnxruntime")]
fn onnxruntime_library() -> Option<PathBuf> {
    needed(
        find_onnxruntime_library(),
        "the onnxruntime library (ORT_DYLIB_PATH, or .venv's onnxruntime wheel)",
    )
}

#[cfg(feature = "onnxruntime")]
fn find_onnxruntime_library() -> Option<PathBuf> {
    if let Some(path) = std::env::var_os("ORT_DYLIB_PATH") {
        return Some(PathBuf::from(path));
    }
    let lib = root().join(".venv/lib");
    std::fs::read_dir(lib)
        .ok()?
        .filter_map(|entry| entry.ok())
        .map(|python| python.path().join("site-packages/onnxruntime/capi"))
        .filter_map(|capi| std::fs::read_dir(capi).ok())
        .flatten()
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .find(|path| {
            path.file_name()
                .and_then(|name| name.to_str())
                .is_some_and(|name| {
                    name.starts_with("libonnxruntime.so.") || name == "libonnxruntime.dylib"
                })
        })
}

#[cfg(feature = "onnxruntime")]
fn ort_encoder(path: PathBuf) -> Option<OrtEncoder> {
    let library = onnxruntime_library()?;
    Some(OrtEncoder::open(path, library, 0).unwrap())
}

#[cfg(feature = "onnxruntime")]
#[test]
fn onnxruntime_features_from_rust_are_pythons() {
    let fixture: Value = serde_json::from_str(
        &std::fs::read_to_string(root().join("tests/fixtures/encoder_features.json")).unwrap(),
    )
    .unwrap();
    let Some(image) = real_image(fixture["scan"].as_str().unwrap()) else {
        return;
    };
    let Some(encoder) = ort_encoder(bundled_encoder()) else {
        return;
    };
    assert_eq!(encoder.input_size(), [64, 1792]);
    let encoded = encoder.encode(&image).unwrap();
    assert_eq!(
        (encoded.coarse_shape, encoded.refine_shape),
        ([32, 16, 224], [8, 64, 1792])
    );
    let step = fixture["step"].as_u64().unwrap() as usize;
    for (name, values) in [("coarse", &encoded.coarse), ("refine", &encoded.refine)] {
        let expected: Vec<f32> = fixture[name]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap() as f32)
            .collect();
        let sampled: Vec<f32> = values.iter().step_by(step).copied().collect();
        assert_eq!(sampled.len(), expected.len(), "{name}");
        // The fixture's onnxruntime session and this one may split the convolutions differently.
        let worst = sampled
            .iter()
            .zip(&expected)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(
            worst < 1e-6,
            "{name}: largest difference from Python's {worst}"
        );
    }
    let dark = vec![0.0f32; image.len()];
    assert!(encoder.encode(&dark).is_ok());
    assert!(encoder
        .encode(&image[1..])
        .unwrap_err()
        .to_string()
        .starts_with("image:"));
    let frame = root().join("python/dmlo/models/default/frame.onnx");
    let error = OrtEncoder::open(frame, onnxruntime_library().unwrap(), 0).unwrap_err();
    assert!(error.to_string().contains("not the encoder"), "{error}");
    let error = OrtEncoder::open(
        root().join("missing.onnx"),
        onnxruntime_library().unwrap(),
        0,
    )
    .unwrap_err();
    assert!(
        error.to_string().contains("missing.onnx: no such file"),
        "{error}"
    );
    let error = OrtEncoder::open(bundled_encoder(), root().join("no_library.so"), 0).unwrap_err();
    assert!(
        error.to_string().contains("no_library.so: no such file"),
        "{error}"
    );
}

/// Every real set and mode of `odometry_poses.json`: with onnxruntime's features the crate's odometry is
/// `dmlo.Odometry`'s, whatever tract's features would flip.
#[cfg(feature = "onnxruntime")]
#[test]
fn the_rust_odometry_over_onnxruntime_equals_the_python_odometry_on_every_real_drive() {
    use crate::odometry::config::OdometryConfig;
    use crate::odometry::pipeline::{Odometry, Scan};

    let fixture: Value = serde_json::from_str(
        &std::fs::read_to_string(root().join("tests/fixtures/odometry_poses.json")).unwrap(),
    )
    .unwrap();
    let Some(library) = onnxruntime_library() else {
        return;
    };
    for (key, expected) in fixture.as_object().unwrap() {
        let (name, mode) = key.split_once('/').unwrap();
        let Some(scans) = real_drive(name) else {
            return;
        };
        let mut config = OdometryConfig::default();
        config.mapping.enabled = mode == "mapping";
        let encoder = OrtEncoder::open(bundled_encoder(), &library, 0).unwrap();
        let mut odometry = Odometry::new(LearnedMatcher::new(encoder).unwrap(), config).unwrap();
        let expected = expected.as_array().unwrap();
        assert_eq!(expected.len(), scans.len(), "{key}");
        for (i, (points, row)) in scans.iter().zip(expected).enumerate() {
            let pose = odometry.register(Scan::new(points)).unwrap();
            assert_pose_is(&pose, row, &format!("{key}, scan {i}"));
        }
    }
}

/// `pose` against a KITTI row of `dmlo.Odometry`'s, within 1e-5 m and 1e-5 rad: the fixture was recorded on
/// another processor, and onnxruntime's CPU kernels differ between processors in the last bits of the
/// features, which a frame-to-frame chain accumulates. The same run on one machine agrees to 1e-6
/// (`tests/odometry/test_rust_example.py`); a flipped inlier parts chains by millimetres and fails here.
fn assert_pose_is(pose: &nalgebra::Isometry3<f64>, row: &Value, context: &str) {
    let row: Vec<f64> = row
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let mut expected = nalgebra::Matrix4::identity();
    expected
        .fixed_view_mut::<3, 4>(0, 0)
        .copy_from(&nalgebra::Matrix3x4::from_row_slice(&row));
    let (moved, turned) =
        crate::odometry::motion::pose_difference(&expected, &pose.to_homogeneous());
    assert!(
        moved < 1e-5 && turned.to_radians() < 1e-5,
        "{context}: {moved} m, {} rad from dmlo.Odometry's pose",
        turned.to_radians()
    );
}

mod matcher_properties {
    use proptest::prelude::*;

    use super::*;

    /// The learned matcher over tract, opened once for the property test's cases.
    fn shared_tract_matcher() -> &'static LearnedMatcher<TractEncoder> {
        static MATCHER: std::sync::OnceLock<LearnedMatcher<TractEncoder>> =
            std::sync::OnceLock::new();
        MATCHER.get_or_init(|| {
            LearnedMatcher::new(TractEncoder::open(bundled_encoder()).unwrap()).unwrap()
        })
    }

    proptest! {
        #![proptest_config(proptest::test_runner::Config { cases: 8, failure_persistence: None, ..Default::default() })]

        /// The learned matcher with any image — ranges anywhere from empty to far beyond the sensor,
        /// reflectance beyond its scale, a non-finite value, a wrong length — encodes it and matches it to
        /// finite flows and confidences in [0, 1], or names what is wrong; never a panic.
        #[test]
        fn the_learned_matcher_takes_any_image_or_names_what_is_wrong(
            seed in any::<u64>(),
            fill in 0.0..1.0f64,
            far in prop_oneof![Just(80.0f32), Just(1e6f32)],
            bright in prop_oneof![Just(1.0f32), Just(1e4f32)],
            bad in proptest::option::of((0usize..2 * 64 * 1792, prop_oneof![Just(f32::NAN), Just(f32::INFINITY), Just(f32::NEG_INFINITY)])),
            cut in prop_oneof![4 => Just(0usize), 1 => 1usize..100],
        ) {
            let matcher = shared_tract_matcher();
            let cells = 64 * 1792;
            let mut state = seed | 1;
            let mut next = move || {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                (state >> 11) as f64 / (1u64 << 53) as f64
            };
            let mut image = vec![0.0f32; 2 * cells];
            for cell in 0..cells {
                if next() < fill {
                    image[cell] = 1.0 + next() as f32 * far;
                    image[cells + cell] = next() as f32 * bright;
                }
            }
            if let Some((at, value)) = bad {
                image[at] = value;
            }
            image.truncate(image.len() - cut);
            match matcher.encoder().encode(&image) {
                Ok(encoded) => {
                    prop_assert!(bad.is_none() && cut == 0);
                    prop_assert!(encoded.coarse.iter().chain(&encoded.refine).all(|v| v.is_finite()));
                    let flow = matcher.flow(&encoded, &encoded).unwrap();
                    prop_assert!(flow.flow.iter().all(|v| v.is_finite()));
                    prop_assert!(flow.confidence.iter().all(|c| (0.0..=1.0 + 1e-6).contains(c)));
                }
                Err(error) => {
                    prop_assert!(bad.is_some() || cut > 0, "{error}");
                    prop_assert!(error.to_string().starts_with("image:"), "{error}");
                }
            }
        }
    }
}

/// The bundled moving-object network's flags of the fixture's real scans by `network`, against the points
/// `dmlo.Odometry`'s detector flags (`tests/fixtures/moving_flags.json`); `exact`: the same flags, else
/// within a few points at the threshold.
fn assert_flags_are_pythons(
    network: &dyn crate::odometry::moving::MovingObjectNetwork,
    exact: bool,
) {
    use crate::odometry::moving::{moving_points, network_images};

    let fixture: Value = serde_json::from_str(
        &std::fs::read_to_string(root().join("tests/fixtures/moving_flags.json")).unwrap(),
    )
    .unwrap();
    let step = fixture["step"].as_u64().unwrap() as usize;
    for scan in fixture["scans"].as_array().unwrap() {
        let name = scan["scan"].as_str().unwrap();
        let Some(points) = shared_scan(name) else {
            return;
        };
        let (range, height) = network_images(points.as_flattened(), 4, network.cylinder()).unwrap();
        let probability = network.probability(&range, &height).unwrap();
        let worst = worst_sample_difference(&probability, &scan["probability"], step, name);
        assert!(worst < 1e-4, "{name}: probabilities {worst} from Python's");
        let moving =
            moving_points(network, &points, fixture["threshold"].as_f64().unwrap()).unwrap();
        let flagged: Vec<u64> = (0..moving.len() as u64)
            .filter(|&i| moving[i as usize])
            .collect();
        let expected: Vec<u64> = scan["flagged"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap())
            .collect();
        assert!(expected.len() > 1000, "{name}: the scan has cars to flag");
        if exact {
            assert_eq!(flagged, expected, "{name}");
        } else {
            let differing = flagged.len().abs_diff(expected.len())
                + expected
                    .iter()
                    .filter(|i| flagged.binary_search(i).is_err())
                    .count();
            assert!(
                differing * 200 < expected.len(),
                "{name}: {differing} of {} flags differ",
                expected.len()
            );
        }
    }
}

fn bundled_moving_graph() -> PathBuf {
    root().join("python/dmlo/models/default/moving.onnx")
}

#[test]
fn tract_flags_the_moving_points_pythons_detector_flags() {
    let network = TractMovingObjects::open(bundled_moving_graph()).unwrap();
    assert_eq!(network.cylinder(), &CylinderConfig::kitti());
    assert_flags_are_pythons(&network, false);
}

#[test]
fn a_graph_that_is_not_the_moving_object_network_is_a_named_error() {
    let error = TractMovingObjects::open(bundled_encoder())
        .unwrap_err()
        .to_string();
    assert!(error.contains("not the moving-object network"), "{error}");
    let error = TractMovingObjects::open(root().join("no/moving.onnx"))
        .unwrap_err()
        .to_string();
    assert!(error.contains("no such file"), "{error}");
    let network = TractMovingObjects::open(bundled_moving_graph()).unwrap();
    let cells = 64 * 1792;
    let error = network
        .probability(&vec![0.0; cells - 1], &vec![0.0; cells])
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("range") && error.contains("values"),
        "{error}"
    );
    let mut height = vec![0.0; cells];
    height[1792 + 5] = f32::NAN;
    let error = network
        .probability(&vec![0.0; cells], &height)
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("height") && error.contains("row 1, column 5"),
        "{error}"
    );
}

#[cfg(feature = "onnxruntime")]
#[test]
fn onnxruntime_from_rust_flags_the_moving_points_pythons_detector_flags() {
    let Some(library) = onnxruntime_library() else {
        return;
    };
    let network = OrtMovingObjects::open(bundled_moving_graph(), &library, 0).unwrap();
    assert_flags_are_pythons(&network, true);
    let error = OrtMovingObjects::open(bundled_encoder(), &library, 0)
        .unwrap_err()
        .to_string();
    assert!(error.contains("not the moving-object network"), "{error}");
}

#[test]
fn a_moving_object_graph_whose_input_is_not_its_cylinder_image_is_a_named_error() {
    let kitti = r#"{"fov_down_deg": -24.9, "fov_up_deg": 2.0, "height": 64,
        "horizontal_resolution_deg": 0.2, "vertical_resolution_deg": 0.4, "width": 1792}"#;
    let with_width = |width: &str| {
        entries(&[
            ("dmlo.graph", "moving"),
            ("dmlo.height", "64"),
            ("dmlo.width", width),
            ("dmlo.cylinder_config", kitti),
        ])
    };
    let cylinder = metadata::moving_graph_cylinder(&with_width("1792"), "moving.onnx").unwrap();
    assert_eq!(cylinder, CylinderConfig::kitti());
    let error = metadata::moving_graph_cylinder(&with_width("896"), "moving.onnx").unwrap_err();
    assert_eq!(
        error,
        Error::Model(
            "moving.onnx: dmlo.width = \"896\", but its cylinder image (dmlo.cylinder_config) is 64 × 1792"
                .into()
        )
    );
}
