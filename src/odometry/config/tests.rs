use std::path::PathBuf;

use super::*;

fn fixture() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/odometry_config.json")
}

fn error_of(text: &str) -> String {
    OdometryConfig::from_json(text).unwrap_err().to_string()
}

#[test]
fn a_saved_config_loads_unchanged() {
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
    assert_eq!(config.reflectance, ReflectanceScale::ZeroTo255);
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
        reflectance: ReflectanceScale::ZeroTo255,
        ..Default::default()
    };
    assert_eq!(config, expected);
}

#[test]
fn written_json_reads_back_as_it_was_saved() {
    let text = std::fs::read_to_string(fixture()).unwrap();
    let config = OdometryConfig::from_json(&text).unwrap();
    let written = config.to_json();
    assert_eq!(OdometryConfig::from_json(&written).unwrap(), config);
    assert!(written.contains("\"max_deviation\": Infinity"), "{written}");
    // The key order is the sections' declaration order.
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

#[test]
fn each_bad_value_gets_the_message_that_names_it() {
    for (text, message) in [
        (r#"{"ransac": {"threshold": "abc"}}"#, r#"ransac.threshold: must be a number > 0, got "abc""#),
        (r#"{"ransac": {"threshold": 0}}"#, "ransac.threshold: must be a number > 0, got 0"),
        (r#"{"ransac": {"threshold": null}}"#, "ransac.threshold: must be a number > 0, got null"),
        (r#"{"ransac": {"threshold": Infinity}}"#, "ransac.threshold: must be a finite number > 0, got Infinity"),
        (r#"{"ransac": {"confidence": 1.0}}"#, "ransac.confidence: must be a number > 0 and < 1, got 1.0"),
        (r#"{"ransac": {"max_iterations": 10.5}}"#, "ransac.max_iterations: must be an integer from 1 to 1000000, got 10.5"),
        (r#"{"ransac": {"max_iterations": 9223372036854775808}}"#, "ransac.max_iterations: must be an integer from 1 to 1000000, got 9223372036854775808"),
        (r#"{"ransac": {"seed": -1}}"#, "ransac.seed: must be an integer >= 0, got -1"),
        (r#"{"ransac": {"seed": 18446744073709551616}}"#, "ransac.seed: must be an integer from 0 to 2^64 - 1, got 18446744073709551616"),
        (r#"{"matching": {"max_matches": 2.0}}"#, "matching.max_matches: must be an integer >= 3, got 2.0"),
        (r#"{"matching": {"min_confidence": NaN}}"#, "matching.min_confidence: must be a finite number >= 0 and <= 1, got NaN"),
        (r#"{"matching": {"coherence_radius": 99}}"#, "matching.coherence_radius: must be an integer from 0 to 15, got 99"),
        (r#"{"matching": {"consistency_px": "1"}}"#, r#"matching.consistency_px: must be a number >= 0 or Infinity (no limit) or null, got "1""#),
        (r#"{"motion_model": {"max_deviation": NaN}}"#, "motion_model.max_deviation: must be a number >= 0 or Infinity (no limit), got NaN"),
        (r#"{"motion_model": {"guided_windows": 0}}"#, "motion_model.guided_windows: must be true or false or null, got 0"),
        (r#"{"mapping": {"enabled": "false"}}"#, r#"mapping.enabled: must be true or false, got "false""#),
        (r#"{"deskew": {"reference_azimuth_deg": -Infinity}}"#, "deskew.reference_azimuth_deg: must be a finite number, got -Infinity"),
        (r#"{"matching_stage": "gpu"}"#, r#"matching_stage: must be one of auto, crate, graph, got "gpu""#),
        (r#"{"reflectance": "Infinity"}"#, r#"reflectance: must be one of auto, unit, 0-255, 0-65535, none, got "Infinity""#),
        (r#"{"large_motion": {"search_yaw_deg": [0, "90"]}}"#, r#"large_motion.search_yaw_deg: must be a non-empty list of finite numbers, got [0, "90"]"#),
        (r#"{"large_motion": {"search_ahead_m": [0, Infinity]}}"#, "large_motion.search_ahead_m: must be a non-empty list of finite numbers, got [0, Infinity]"),
        (r#"{"mapping": true}"#, "mapping: must be a mapping of settings, got true"),
        (r#"{"mapping": {"colour": "red"}}"#, "mapping.colour: no such setting; mapping has enabled, voxel_size, max_scans, keyframe_distance, keyframe_angle_deg, ring_lock_distance, motion_model_start_distance, motion_model_start_angle_deg, downsample, downsample_far, far_range, level_without_far_upright, max_iterations, degeneracy_threshold, rotation_degeneracy_threshold"),
        (r#"{"rasnac": {}}"#, "rasnac: no such setting (did you mean ransac?)"),
        ("[]", "config: must be a mapping of settings, got []"),
    ] {
        assert_eq!(error_of(text), message, "{text}");
    }
}

#[test]
fn every_bad_key_is_named_in_one_message_in_the_schemas_order() {
    assert_eq!(
        error_of(r#"{"threads": "4", "ransac": {"confidence": 2, "threshold": -1}}"#),
        "ransac.threshold: must be a number > 0, got -1; ransac.confidence: must be a number > 0 and < 1, got 2; \
         threads: must be an integer >= 0, got \"4\""
    );
}

#[test]
fn a_config_set_in_code_is_checked_by_the_same_rules() {
    let mut config = OdometryConfig::default();
    config.ransac.threshold = f64::NAN;
    config.mapping.keyframe_distance = f64::INFINITY; // no limit: fine
    config.matching.max_matches = 2;
    assert_eq!(
        config.validate().unwrap_err().to_string(),
        "matching.max_matches: must be an integer >= 3, got 2; \
         ransac.threshold: must be a finite number > 0, got NaN"
    );
}

#[test]
fn the_schema_describes_every_setting_with_its_default() {
    let schema: serde_json::Value = serde_json::from_str(&json::quote_non_finite_tokens(
        &OdometryConfig::schema_json(),
    ))
    .unwrap();
    let sections = schema["sections"].as_array().unwrap();
    let keys: Vec<&str> = sections
        .iter()
        .map(|s| s["key"].as_str().unwrap())
        .collect();
    assert_eq!(
        keys,
        [
            "matching",
            "ransac",
            "motion_model",
            "deskew",
            "mapping",
            "large_motion",
            "moving_objects"
        ]
    );
    let ransac = &sections[1];
    assert!(ransac["doc"].as_str().unwrap().starts_with("RANSAC around"));
    let threshold = &ransac["settings"][0];
    assert_eq!(threshold["key"], "threshold");
    assert_eq!(threshold["type"], "float");
    assert_eq!(threshold["default"], 0.1);
    assert_eq!(threshold["rule"], "a number > 0");
    assert_eq!(threshold["optional"], false);
    let refit = &ransac["settings"][4];
    assert_eq!(
        refit["choices"],
        serde_json::json!(["point_to_point", "ray_noise"])
    );
    let top: Vec<&str> = schema["settings"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["key"].as_str().unwrap())
        .collect();
    assert_eq!(
        top,
        ["threads", "matching_stage", "min_points", "reflectance"]
    );
    // Every default in the schema reads back as the crate's default config.
    let mut defaults = serde_json::Map::new();
    for section in sections {
        let values: serde_json::Map<_, _> = section["settings"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| (s["key"].as_str().unwrap().to_string(), s["default"].clone()))
            .collect();
        defaults.insert(section["key"].as_str().unwrap().into(), values.into());
    }
    let text = json::with_tokens(serde_json::Value::Object(defaults).to_string());
    assert_eq!(
        OdometryConfig::from_json(&text).unwrap(),
        OdometryConfig::default()
    );
}

#[test]
fn the_lower_layers_defaults_are_the_configs() {
    assert_eq!(
        OdometryConfig::default().pair_config(),
        PairConfig::default()
    );
    assert_eq!(
        OdometryConfig::default().mapping_config(),
        MappingConfig::default()
    );
    let limits = OdometryConfig::default().motion_limits();
    assert_eq!(
        MotionLimits {
            refit: limits.refit.clone(),
            ..MotionLimits::default()
        },
        limits
    );
}
