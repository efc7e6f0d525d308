//! Scans that are not what they seem (issue 53): refused, bridged or said, never a silently wrong pose.

use super::*;

/// Scan `i` with `extra` rows at the origin (no returns, as some drivers write them) appended.
fn with_origin_rows(i: usize, extra: usize) -> Vec<[f32; 4]> {
    let mut points = scan(i);
    points.extend(std::iter::repeat_n([0.0, 0.0, 0.0, 0.0], extra));
    points
}

#[test]
fn points_at_the_origin_are_no_returns() {
    let mut plain = Odometry::new(OracleMatcher::new(), config(true)).unwrap();
    let mut padded = Odometry::new(OracleMatcher::new(), config(true)).unwrap();
    for i in 0..3 {
        let expected = register(&mut plain, &scan(i), i.saturating_sub(1), i);
        let pose = register(
            &mut padded,
            &with_origin_rows(i, 5000),
            i.saturating_sub(1),
            i,
        );
        assert_eq!(pose, expected, "frame {i}");
    }
    // A scan of zeros has no point to match: bridged, and it decides nothing (no reflectance scale, no
    // switch to the range-only model) nor becomes the reference.
    let zeros = vec![[0.0f32; 4]; 60_000];
    let mut odometry = Odometry::new(OracleMatcher::new(), config(false)).unwrap();
    register(&mut odometry, &zeros, 0, 0);
    assert_eq!(
        odometry.diagnostics()[0].fallback,
        Some(Fallback::TooFewPoints)
    );
    assert_eq!(odometry.reflectance_scale(), None);
    register(&mut odometry, &scan(1), 1, 1);
    register(&mut odometry, &zeros, 1, 2);
    let pose = register(&mut odometry, &scan(3), 1, 3);
    assert_eq!(odometry.diagnostics()[3].gap, Some(2));
    let truth = (true_pose(1).inverse() * true_pose(3)).to_homogeneous();
    assert!(pose_difference(&truth, &pose.to_homogeneous()).0 < 0.02);
    assert_eq!(odometry.reflectance_scale(), Some(ReflectanceScale::Unit));
    assert!(notice_kinds(&odometry).concat().is_empty());
}

#[test]
fn a_scan_not_in_metres_in_the_sensor_frame_is_refused_and_changes_nothing() {
    let mut odometry = Odometry::new(OracleMatcher::new(), config(false)).unwrap();
    register(&mut odometry, &scan(0), 0, 0);
    for (what, changed) in [
        ("millimetres", [1000.0, 1000.0, 1000.0, 1.0], [0.0; 4]),
        ("far", [1.0; 4], [1e6, 0.0, 0.0, 0.0]),
    ]
    .map(|(what, scale, offset)| {
        let points: Vec<[f32; 4]> = scan(1)
            .iter()
            .map(|p| std::array::from_fn(|k| p[k] * scale[k] + offset[k]))
            .collect();
        (what, points)
    }) {
        let error = odometry.register(Scan::new(&changed)).unwrap_err();
        assert!(
            error
                .to_string()
                .starts_with("points: not a plausible LiDAR scan: 0 of its"),
            "{what}: {error}"
        );
        let error = odometry
            .register_pair(Scan::new(&scan(0)), Scan::new(&changed), false)
            .unwrap_err();
        assert!(
            error
                .to_string()
                .starts_with("target: not a plausible LiDAR scan"),
            "{what}: {error}"
        );
    }
    assert_eq!(odometry.poses().len(), 1);
    // Coordinates decide, as the file readers' check does: points far away with a NaN reflectance still
    // count against the scan.
    let mut far_without_reflectance = scan(1);
    far_without_reflectance
        .iter_mut()
        .enumerate()
        .filter(|(k, _)| k % 3 != 0)
        .for_each(|(_, p)| *p = [p[0] + 1e6, p[1], p[2], f32::NAN]);
    let error = odometry
        .register(Scan::new(&far_without_reflectance))
        .unwrap_err();
    assert!(error.to_string().contains("plausible"), "{error}");
    // A few rows out there are left out, and the scan registers.
    let mut some_far = scan(1);
    some_far[..100].iter_mut().for_each(|p| p[0] = 3e38);
    let pose = register(&mut odometry, &some_far, 0, 1);
    assert!(error_to_truth(&pose, 1).0 < 0.02);
}

#[test]
fn a_scan_that_cannot_be_matched_does_not_become_the_reference() {
    let mut odometry = Odometry::new(OracleMatcher::new(), config(false)).unwrap();
    for i in 0..3 {
        register(&mut odometry, &scan(i), i.saturating_sub(1), i);
    }
    // Scan 3 finds no match: bridged by the motion model; scan 4 is matched against scan 2.
    odometry.matcher.answers.borrow_mut().push_back(None);
    register(&mut odometry, &scan(3), 2, 3);
    assert_eq!(
        odometry.diagnostics()[3].fallback,
        Some(Fallback::ConstantVelocity)
    );
    let pose = register(&mut odometry, &scan(4), 2, 4);
    assert_eq!(odometry.diagnostics()[4].gap, Some(2));
    assert_eq!(odometry.diagnostics()[4].fallback, None);
    assert!(error_to_truth(&pose, 4).0 < 0.02);
    // Two in a row: the reference may be what cannot be matched, and the second becomes it.
    odometry.matcher.answers.borrow_mut().push_back(None);
    register(&mut odometry, &scan(5), 4, 5);
    odometry.matcher.answers.borrow_mut().push_back(None);
    register(&mut odometry, &scan(6), 4, 6);
    register(&mut odometry, &scan(7), 6, 7);
    let gaps: Vec<_> = odometry.diagnostics()[5..]
        .iter()
        .map(|d| (d.gap, d.fallback))
        .collect();
    assert_eq!(
        gaps,
        [
            (Some(1), Some(Fallback::ConstantVelocity)),
            (Some(2), Some(Fallback::ConstantVelocity)),
            (Some(1), None)
        ]
    );
}

#[test]
fn a_scan_passed_over_measures_no_velocity() {
    // Scan 1 finds no match before any velocity was measured: its prediction (standing still) is no
    // measurement, or scan 2 — matched against scan 0 — would be judged against standing still.
    let mut odometry = Odometry::new(OracleMatcher::new(), config(false)).unwrap();
    register(&mut odometry, &scan(0), 0, 0);
    odometry.matcher.answers.borrow_mut().push_back(None);
    register(&mut odometry, &scan(1), 0, 1);
    assert!(!odometry.motion.is_measured());
    let pose = register(&mut odometry, &scan(2), 0, 2);
    assert_eq!(odometry.diagnostics()[2].fallback, None);
    assert!(error_to_truth(&pose, 2).0 < 0.02);
}

#[test]
fn a_later_scan_on_the_unit_scale_after_a_guessed_0_255_is_read_on_it() {
    let mut odometry = Odometry::new(OracleMatcher::new(), config(false)).unwrap();
    let bright: Vec<[f32; 4]> = scan(0)
        .iter()
        .map(|&[x, y, z, r]| [x, y, z, r * 255.0])
        .collect();
    register(&mut odometry, &bright, 0, 0);
    register(&mut odometry, &scan(1), 0, 1);
    register(&mut odometry, &scan(2), 1, 2);
    assert_eq!(
        notice_kinds(&odometry),
        [
            vec!["reflectance_scaled"],
            vec!["reflectance_rescaled"],
            vec![]
        ]
    );
    let said = odometry.diagnostics()[1].notices[0].message();
    assert!(
        said.starts_with("reflectance: scan 1: values up to")
            && said.contains("look like [0, 1], not the 0-255 scale chosen before"),
        "{said}"
    );
    // Its image is the image of the scan on [0, 1].
    let (image, _) = odometry.network_image(Scan::new(&scan(1))).unwrap();
    let unit = Odometry::new(OracleMatcher::new(), config(false)).unwrap();
    assert_eq!(image, unit.network_image(Scan::new(&scan(1))).unwrap().0);
    // Values reaching well into a larger scale than the one guessed are read on it; a little beyond it,
    // clipped.
    let mut odometry = Odometry::new(OracleMatcher::new(), config(false)).unwrap();
    register(&mut odometry, &scan(0), 0, 0);
    let times = |k: f32| -> Vec<[f32; 4]> {
        scan(1)
            .iter()
            .map(|&[x, y, z, r]| [x, y, z, r * k])
            .collect()
    };
    register(&mut odometry, &times(255.0), 0, 1);
    register(&mut odometry, &times(1.5), 1, 2);
    assert_eq!(
        notice_kinds(&odometry),
        [
            vec![],
            vec!["reflectance_rescaled"],
            vec!["reflectance_clipped"]
        ]
    );
    let said = odometry.diagnostics()[1].notices[0].message();
    assert!(
        said.contains("look like 0–255, not the unit scale chosen before")
            && said.contains("read on 0-255"),
        "{said}"
    );
    // A scale the config sets is kept.
    let set = OdometryConfig {
        reflectance: ReflectanceScale::ZeroTo255,
        ..config(false)
    };
    let mut odometry = Odometry::new(OracleMatcher::new(), set).unwrap();
    register(&mut odometry, &bright, 0, 0);
    register(&mut odometry, &scan(1), 0, 1);
    assert_eq!(notice_kinds(&odometry)[1], Vec::<&str>::new());
}

#[test]
fn a_pair_without_a_motion_of_its_own_is_said_and_a_scan_with_itself_is_the_identity() {
    let mut odometry = Odometry::new(OracleMatcher::new(), config(false)).unwrap();
    odometry.matcher.answers.borrow_mut().push_back(None);
    let pair = register_pair(&mut odometry, 0, 1).unwrap();
    assert_eq!(pair.matches.num_inliers, 0);
    let kinds: Vec<_> = pair.notices.iter().map(Notice::kind).collect();
    assert_eq!(kinds, ["too_few_inliers"]);
    assert!(pair.notices[0]
        .message()
        .starts_with("the pair has 0 RANSAC inliers, fewer than the 10 a motion needs"));
    assert!(register_pair(&mut odometry, 0, 1)
        .unwrap()
        .notices
        .is_empty());
    for mapping in [false, true] {
        let blurred = OracleMatcher::new();
        blurred.truth.set(Isometry3::translation(0.003, 0.0, 0.0)); // the network's sub-pixel error
        let mut odometry = Odometry::new(blurred, config(mapping)).unwrap();
        let points = scan(0);
        let pair = odometry
            .register_pair(Scan::new(&points), Scan::new(&points.clone()), false)
            .unwrap();
        assert_eq!(pair.transform, Matrix4::identity(), "mapping {mapping}");
    }
}
