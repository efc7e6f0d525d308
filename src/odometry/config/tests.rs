use std::path::PathBuf;

use super::*;

fn fixture() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/odometry_config.json")
}

fn error_of(text: &str) -> String {
    OdometryConfig::from_json(text).unwrap_err().to_string()
}

#[test]
fn the_config_python_saves_loads_unchanged() {
    let config = OdometryConfig::load(fixture()).unwrap();
    assert_eq!(config.matching.coherence_px, None);
    assert_eq!(config.matching.max_matches, 800);
    assert_eq!(config.ransac.refit, RefitKind::PointToPoint);
    assert_eq!(config.ransac.seed, 7);
    assert_eq!(config.motion_model.max_deviation, f64::INFINITY);
    assert_eq!(config.motion_model.rematch_gap, None);
    assert_eq!(config.motion_model.prediction_rounds, Some(3));
    assert_eq!(config.motion_model.guided_windows, Some(false));
    assert_eq!(config.motion_model.start_check_m, Some(2.5));
    assert_eq!(config.motion_model.start_max_reverse_m, None);
    assert!(config.deskew.enabled);
    assert_eq!(config.mapping.keyframe_distance, f64::INFINITY);
    assert_eq!(config.mapping.voxel_size, 0.8);
    assert_eq!(config.mapping.far_range, f64::INFINITY);
    assert!(!config.mapping.level_without_far_upright);
    assert_eq!(config.large_motion.search_yaw_deg, vec![0.0, 90.0, -90.0]);
    assert_eq!(config.moving_objects.threshold, 0.7);
    assert_eq!(config.threads, 2);
    assert_eq!(config.matching_stage, MatchingStage::Crate);
    assert_eq!(config.reflectance, ReflectanceScale::Byte);
    // Everything else at its default.
    let expected = OdometryConfig {
        matching: config.matching.clone(),
        ransac: RansacSection {
            refit: RefitKind::PointToPoint,
            seed: 7,
            ..Default::default()
        },
        motion_model: config.motion_model.clone(),
        deskew: DeskewSection {
            enabled: true,
            ..Default::default()
        },
        mapping: MappingSection {
            keyframe_distance: f64::INFINITY,
            voxel_size: 0.8,
            far_range: f64::INFINITY,
            level_without_far_upright: false,
            ..Default::default()
        },
        large_motion: LargeMotionSection {
            search_yaw_deg: vec![0.0, 90.0, -90.0],
            ..Default::default()
        },
        moving_objects: MovingObjectsSection {
            threshold: 0.7,
            ..Default::default()
        },
        threads: 2,
        matching_stage: MatchingStage::Crate,
        reflectance: ReflectanceScale::Byte,
        ..Default::default()
    };
    assert_eq!(config, expected);
}

#[test]
fn written_json_reads_back_as_python_writes_it() {
    let text = std::fs::read_to_string(fixture()).unwrap();
    let config = OdometryConfig::from_json(&text).unwrap();
    let written = config.to_json();
    assert_eq!(OdometryConfig::from_json(&written).unwrap(), config);
    assert!(written.contains("\"max_deviation\": Infinity"), "{written}");
    // Python's json and serde_json format numbers alike; the key order is the sections' declaration order.
    let normalise = |s: &str| s.split_whitespace().collect::<String>();
    assert_eq!(normalise(&written), normalise(&text));
}

#[test]
fn empty_config_is_the_default_and_defaults_pass_validation() {
    assert_eq!(
        OdometryConfig::from_json("{}").unwrap(),
        OdometryConfig::default()
    );
    OdometryConfig::default().validate().unwrap();
    let pair = OdometryConfig::default().pair_config();
    assert_eq!(pair, PairConfig::default());
    assert_eq!(
        OdometryConfig::default().mapping_config(),
        MappingConfig::default()
    );
    assert_eq!(OdometryConfig::default().prediction_rounds(), 1);
    assert!(OdometryConfig::default().guided_windows());
}

#[test]
fn guided_windows_follow_the_mapping_unless_set() {
    let mut config = OdometryConfig::default();
    config.mapping.enabled = false;
    assert!(!config.guided_windows());
    config.motion_model.guided_windows = Some(true);
    assert!(config.guided_windows());
    config.mapping.enabled = true;
    config.motion_model.guided_windows = Some(false);
    assert!(!config.guided_windows());
    let read = OdometryConfig::from_json(r#"{"motion_model": {"guided_windows": false}}"#).unwrap();
    assert_eq!(read.motion_model.guided_windows, Some(false));
}

#[test]
fn unknown_keys_are_named_with_their_section() {
    let message = error_of(r#"{"ransac": {"treshold": 0.2}}"#);
    assert!(message.contains("ransac.treshold"), "{message}");
    assert!(message.contains("threshold"), "{message}");
    let message = error_of(r#"{"rasnac": {}}"#);
    assert!(message.contains("rasnac"), "{message}");
}

#[test]
fn types_are_strict_and_errors_name_the_key() {
    for (text, key) in [
        (r#"{"matching": {"symmetric": 1}}"#, "matching.symmetric"),
        (
            r#"{"matching": {"symmetric": "false"}}"#,
            "matching.symmetric",
        ),
        (
            r#"{"matching": {"nms_radius": 1.5}}"#,
            "matching.nms_radius",
        ),
        (r#"{"matching": {"nms_radius": -1}}"#, "matching.nms_radius"),
        (r#"{"ransac": {"threshold": "0.1"}}"#, "ransac.threshold"),
        (r#"{"ransac": {"threshold": null}}"#, "ransac.threshold"),
        (r#"{"ransac": {"refit": "icp"}}"#, "ransac.refit"),
        (r#"{"reflectance": "bright"}"#, "reflectance"),
        (
            r#"{"large_motion": {"search_ahead_m": 3}}"#,
            "large_motion.search_ahead_m",
        ),
        (r#"{"mapping": []}"#, "mapping"),
    ] {
        let message = error_of(text);
        assert!(message.contains(key), "{text}: {message}");
    }
    assert!(
        error_of("[]").starts_with("config: must be a mapping"),
        "{}",
        error_of("[]")
    );
    assert!(error_of(r#"{"threads": 1} x"#).contains("config"));
}

#[test]
fn ranges_are_checked_and_named() {
    for (text, key) in [
        (
            r#"{"ransac": {"threshold": 0}}"#,
            "ransac.threshold: must be a number > 0, got 0",
        ),
        (r#"{"ransac": {"confidence": 1}}"#, "ransac.confidence"),
        (
            r#"{"ransac": {"max_iterations": 2000000}}"#,
            "ransac.max_iterations",
        ),
        (
            r#"{"matching": {"max_matches": 2}}"#,
            "matching.max_matches: must be an integer >= 3, got 2",
        ),
        (
            r#"{"matching": {"coherence_radius": 99}}"#,
            "matching.coherence_radius",
        ),
        (
            r#"{"motion_model": {"guided_fraction": 1.5}}"#,
            "motion_model.guided_fraction",
        ),
        (
            r#"{"mapping": {"keyframe_distance": -1}}"#,
            "mapping.keyframe_distance",
        ),
        (
            r#"{"mapping": {"degeneracy_threshold": 1}}"#,
            "mapping.degeneracy_threshold",
        ),
        (
            r#"{"large_motion": {"search_ahead_m": []}}"#,
            "large_motion.search_ahead_m",
        ),
        (
            r#"{"moving_objects": {"threshold": 0}}"#,
            "moving_objects.threshold",
        ),
    ] {
        let message = error_of(text);
        assert!(message.contains(key), "{text}: {message}");
    }
}

#[test]
fn infinity_only_where_a_setting_may_be_unlimited() {
    let config = OdometryConfig::from_json(
        r#"{"mapping": {"ring_lock_distance": Infinity}, "matching": {"consistency_px": Infinity}}"#,
    )
    .unwrap();
    assert_eq!(config.mapping.ring_lock_distance, f64::INFINITY);
    assert_eq!(config.matching.consistency_px, Some(f64::INFINITY));
    for (text, key) in [
        (r#"{"ransac": {"threshold": Infinity}}"#, "ransac.threshold"),
        (
            r#"{"mapping": {"keyframe_distance": -Infinity}}"#,
            "mapping.keyframe_distance",
        ),
        (
            r#"{"mapping": {"keyframe_distance": NaN}}"#,
            "mapping.keyframe_distance",
        ),
        (
            r#"{"deskew": {"reference_azimuth_deg": NaN}}"#,
            "deskew.reference_azimuth_deg",
        ),
        (
            r#"{"large_motion": {"search_ahead_m": [0, Infinity]}}"#,
            "large_motion.search_ahead_m",
        ),
    ] {
        let message = error_of(text);
        assert!(message.contains(key), "{text}: {message}");
        assert!(
            !message.contains('\u{1}'),
            "the internal mark leaked: {message}"
        );
    }
    // Inside a string the token is text, not a number.
    let message = error_of(r#"{"reflectance": "Infinity"}"#);
    assert!(
        message.contains("reflectance") && message.contains("Infinity"),
        "{message}"
    );
}

#[test]
fn a_missing_file_is_named() {
    let message = OdometryConfig::load("/nonexistent/config.json")
        .unwrap_err()
        .to_string();
    assert!(message.contains("/nonexistent/config.json"), "{message}");
}
