use std::cell::Cell;

use nalgebra::{Isometry3, Point3, Vector3};

use super::*;
use crate::ground_truth::ground_truth_flow;
use crate::odometry::config::OdometryConfig;
use crate::odometry::motion::pose_difference;
use crate::test_scenes::yard_scan;

/// A matcher that knows the truth: its "features" are the range image (with the order it was encoded
/// in), its flow the ground-truth flow (Eq. 5–8) under the motion the test sets before each pair (its
/// inverse for a pair matched back, from the newer scan to the older), full confidence where it is
/// defined. Asked for some cells only, it answers as the crate's matching stage does (the others NaN,
/// confidence 0), and counts the cells whose asking differs from whether they hold a point (`asked_amiss`).
struct OracleMatcher {
    cylinder: CylinderConfig,
    truth: Cell<Isometry3<f64>>,
    encoded: Cell<usize>,
    reads_reflectance: bool,
    asked_for_cells: Cell<usize>,
    asked_amiss: Cell<usize>,
    /// Whether it places its windows where it is told (`guided_flow_of_cells`): `None` no; `Some(true)`
    /// yes, and finds the truth; `Some(false)` yes, but its windows lock on standing still.
    guided: Option<bool>,
    /// The expected flows it was given, one mean Δcol a call.
    guides: std::cell::RefCell<Vec<f64>>,
    /// Motions to answer the next flows under, one a call, before the truth again (`None`: no flow, NaN
    /// everywhere): the motion of a moved reference, which the truth between the scans given is not.
    answers: std::cell::RefCell<std::collections::VecDeque<Option<Isometry3<f64>>>>,
}

impl OracleMatcher {
    fn new() -> Self {
        OracleMatcher {
            cylinder: CylinderConfig::kitti(),
            truth: Cell::new(Isometry3::identity()),
            encoded: Cell::new(0),
            reads_reflectance: true,
            asked_for_cells: Cell::new(0),
            asked_amiss: Cell::new(0),
            guided: None,
            guides: Default::default(),
            answers: Default::default(),
        }
    }
}

impl FrameMatcher for OracleMatcher {
    type Features = (usize, Vec<f32>);

    fn cylinder(&self) -> &CylinderConfig {
        &self.cylinder
    }

    fn uses_reflectance(&self) -> bool {
        self.reads_reflectance
    }

    fn encode(&self, image: &[f32]) -> Result<(usize, Vec<f32>)> {
        self.encoded.set(self.encoded.get() + 1);
        Ok((self.encoded.get(), image[..image.len() / 2].to_vec()))
    }

    fn flow(&self, reference: &(usize, Vec<f32>), target: &(usize, Vec<f32>)) -> Result<DenseFlow> {
        let motion = if reference.0 < target.0 {
            self.truth.get()
        } else {
            self.truth.get().inverse()
        };
        true_flow(&reference.1, &target.1, &motion, &self.cylinder)
    }

    fn flow_of_cells(
        &self,
        reference: &(usize, Vec<f32>),
        target: &(usize, Vec<f32>),
        cells: &[bool],
    ) -> Result<DenseFlow> {
        self.asked_for_cells.set(self.asked_for_cells.get() + 1);
        let mut flow = match self.answers.borrow_mut().pop_front() {
            Some(Some(motion)) => true_flow(&reference.1, &target.1, &motion, &self.cylinder)?,
            Some(None) => DenseFlow {
                flow: vec![f32::NAN; 2 * reference.1.len()],
                confidence: vec![0.0; reference.1.len()],
                height: self.cylinder.height,
                width: self.cylinder.width,
            },
            None => self.flow(reference, target)?,
        };
        let cell_count = cells.len();
        for (cell, (&asked, &range)) in cells.iter().zip(&reference.1).enumerate() {
            if asked != (range > 0.0) {
                self.asked_amiss.set(self.asked_amiss.get() + 1);
            }
            if !asked {
                flow.flow[cell] = f32::NAN;
                flow.flow[cell_count + cell] = f32::NAN;
                flow.confidence[cell] = 0.0;
            }
        }
        Ok(flow)
    }

    fn guided_flow_of_cells(
        &self,
        reference: &(usize, Vec<f32>),
        target: &(usize, Vec<f32>),
        cells: &[bool],
        expected: &[[f32; 2]],
    ) -> Result<Option<DenseFlow>> {
        let Some(finds_truth) = self.guided else {
            return Ok(None);
        };
        let columns: Vec<f64> = expected
            .iter()
            .filter(|e| e[1].is_finite())
            .map(|e| e[1] as f64)
            .collect();
        self.guides
            .borrow_mut()
            .push(columns.iter().sum::<f64>() / columns.len() as f64);
        if finds_truth {
            return self.flow_of_cells(reference, target, cells).map(Some);
        }
        true_flow(
            &reference.1,
            &target.1,
            &Isometry3::identity(),
            &self.cylinder,
        )
        .map(Some)
    }
}

/// The ground-truth flow (Eq. 5–8) from the reference's range image to the target's under `motion`, with
/// full confidence where it is defined.
fn true_flow(
    reference: &[f32],
    target: &[f32],
    motion: &Isometry3<f64>,
    cylinder: &CylinderConfig,
) -> Result<DenseFlow> {
    let truth = ground_truth_flow(reference, target, motion, cylinder, 0.3)?;
    Ok(DenseFlow {
        flow: truth.flow,
        confidence: truth
            .valid
            .iter()
            .map(|&v| if v { 1.0 } else { 0.0 })
            .collect(),
        height: cylinder.height,
        width: cylinder.width,
    })
}

const POSTS: [(f64, f64); 3] = [(6.0, 4.0), (9.0, -5.0), (-4.0, 6.0)];

/// `T_yard_sensor` of frame `i`: 0.4 m a frame along x, turning 0.5° a frame.
fn true_pose(i: usize) -> Isometry3<f64> {
    let yaw = (0.5 * i as f64).to_radians();
    Isometry3::new(
        Vector3::new(0.4 * i as f64, 0.05 * i as f64, 0.0),
        Vector3::z() * yaw,
    )
}

fn scan(i: usize) -> Vec<[f32; 4]> {
    let mut points = yard_scan(&true_pose(i), 100 + i as u64, 60_000, &POSTS);
    for (k, p) in points.iter_mut().enumerate() {
        p[3] = 0.2 + 0.6 * ((k % 7) as f32 / 7.0); // reflectance the model can read
    }
    points
}

fn config(mapping: bool) -> OdometryConfig {
    let mut config = OdometryConfig::default();
    config.mapping.enabled = mapping;
    // The oracle knows the motion between the scans given, not that of a moved reference.
    config.motion_model.rematch_gap = None;
    config.motion_model.match_from_prediction_m = None;
    config.motion_model.start_check_m = None;
    config
}

/// Registers scan `i` with the oracle told the true motion from `from` (the reference) to `i`.
fn register(
    odometry: &mut Odometry<OracleMatcher>,
    points: &[[f32; 4]],
    from: usize,
    i: usize,
) -> Isometry3<f64> {
    odometry
        .matcher
        .truth
        .set(true_pose(i).inverse() * true_pose(from));
    odometry.register(Scan::new(points)).unwrap()
}

fn error_to_truth(pose: &Isometry3<f64>, i: usize) -> (f64, f64) {
    let truth = (true_pose(0).inverse() * true_pose(i)).to_homogeneous();
    pose_difference(&truth, &pose.to_homogeneous())
}

#[test]
fn a_drive_follows_the_truth_with_and_without_the_map() {
    for mapping in [false, true] {
        let mut odometry = Odometry::new(OracleMatcher::new(), config(mapping)).unwrap();
        for i in 0..6 {
            let pose = register(&mut odometry, &scan(i), i.saturating_sub(1), i);
            let (moved, turned) = error_to_truth(&pose, i);
            assert!(
                moved < 0.02 && turned < 0.1,
                "mapping {mapping}, frame {i}: {moved} m, {turned}°"
            );
        }
        let diagnostics = odometry.diagnostics();
        assert_eq!(diagnostics.len(), 6);
        assert_eq!(diagnostics[0].gap, None);
        for d in &diagnostics[1..] {
            assert_eq!(d.gap, Some(1));
            assert_eq!(d.fallback, None, "{d:?}");
            assert!(
                d.num_inliers >= 10 && d.num_matches >= d.num_inliers,
                "{d:?}"
            );
            assert_eq!(d.ndt_converged.is_some(), mapping);
            assert!(d.timings_ms.contains_key("pair"));
        }
        assert_eq!(diagnostics[0].map_keyframe, mapping.then_some(true));
        assert_eq!(odometry.reflectance_scale(), Some(ReflectanceScale::Unit));
        assert_eq!(odometry.poses().len(), 6);
        // Every pair asked for the flow of the reference's cells that hold a point, and of no other.
        assert_eq!(odometry.matcher.asked_for_cells.get(), 5);
        assert_eq!(odometry.matcher.asked_amiss.get(), 0);
    }
}

#[test]
fn scans_without_enough_points_and_unreadable_ones_are_bridged_by_the_motion_model() {
    let mut odometry = Odometry::new(OracleMatcher::new(), config(false)).unwrap();
    for i in 0..3 {
        register(&mut odometry, &scan(i), i.saturating_sub(1), i);
    }
    let sparse = &scan(3)[..500];
    let pose = register(&mut odometry, sparse, 2, 3);
    assert_eq!(
        odometry.diagnostics()[3].fallback.map(Fallback::name),
        Some("too_few_points")
    );
    let (moved, _) = error_to_truth(&pose, 3);
    assert!(
        moved < 0.05,
        "the constant-velocity prediction, {moved} m off"
    );
    let pose = odometry.predict_skipped(Fallback::UnreadableScan).unwrap();
    assert_eq!(
        odometry.diagnostics()[4].fallback.map(Fallback::name),
        Some("unreadable_scan")
    );
    assert!(error_to_truth(&pose, 4).0 < 0.05);
    // The next scan is matched against the last one matched (frame 2), three frames back.
    let pose = register(&mut odometry, &scan(5), 2, 5);
    assert_eq!(odometry.diagnostics()[5].gap, Some(3));
    assert!(error_to_truth(&pose, 5).0 < 0.02);
}

#[test]
fn timestamps_count_the_scans_the_sensor_dropped() {
    let mut odometry = Odometry::new(OracleMatcher::new(), config(false)).unwrap();
    for (i, time) in [(0, 0.0), (1, 0.1), (2, 0.2), (4, 0.4)] {
        let points = scan(i);
        let from = if i == 4 { 2 } else { i.saturating_sub(1) };
        odometry
            .matcher
            .truth
            .set(true_pose(i).inverse() * true_pose(from));
        let scan = Scan {
            timestamp: Some(time),
            ..Scan::new(&points)
        };
        let pose = odometry.register(scan).unwrap();
        assert!(error_to_truth(&pose, i).0 < 0.02, "frame {i}");
    }
    assert_eq!(odometry.diagnostics()[3].gap, Some(2));
}

#[test]
fn moving_points_are_left_out() {
    let mut odometry = Odometry::new(OracleMatcher::new(), config(false)).unwrap();
    let points = scan(0);
    let all_moving = vec![true; points.len()];
    let scan = Scan {
        moving: Some(&all_moving),
        ..Scan::new(&points)
    };
    odometry.register(scan).unwrap();
    assert_eq!(
        odometry.diagnostics()[0].fallback.map(Fallback::name),
        Some("too_few_points")
    );
}

#[test]
fn bad_input_is_named_and_leaves_the_odometry_as_it_was() {
    let mut odometry = Odometry::new(OracleMatcher::new(), config(true)).unwrap();
    register(&mut odometry, &scan(0), 0, 0);
    let points = scan(1);
    let short = vec![false; 3];
    let error = odometry
        .register(Scan {
            moving: Some(&short),
            ..Scan::new(&points)
        })
        .unwrap_err();
    assert!(error.to_string().starts_with("moving:"), "{error}");
    let error = odometry
        .register(Scan {
            timestamp: Some(f64::NAN),
            ..Scan::new(&points)
        })
        .unwrap_err();
    assert!(error.to_string().contains("timestamp"), "{error}");
    assert_eq!(odometry.poses().len(), 1);
    // Reflectance the model cannot read, mid-drive: named, not run on zeros.
    let dark: Vec<[f32; 4]> = points.iter().map(|&[x, y, z, _]| [x, y, z, 0.0]).collect();
    let error = odometry.register(Scan::new(&dark)).unwrap_err();
    assert!(error.to_string().contains("range-only"), "{error}");
    assert_eq!(odometry.poses().len(), 1);
    // The drive goes on from where it was.
    let pose = register(&mut odometry, &points, 0, 1);
    assert!(error_to_truth(&pose, 1).0 < 0.02);
}

#[test]
fn reflectance_on_another_scale_is_brought_to_the_models() {
    let mut odometry = Odometry::new(OracleMatcher::new(), config(false)).unwrap();
    let bright: Vec<[f32; 4]> = scan(0)
        .iter()
        .map(|&[x, y, z, r]| [x, y, z, r * 255.0])
        .collect();
    odometry.register(Scan::new(&bright)).unwrap();
    assert_eq!(
        odometry.reflectance_scale(),
        Some(ReflectanceScale::ZeroTo255)
    );
    let first = OdometryConfig {
        reflectance: ReflectanceScale::Ignored,
        ..config(false)
    };
    let mut odometry = Odometry::new(OracleMatcher::new(), first).unwrap();
    let error = odometry.register(Scan::new(&bright)).unwrap_err();
    assert!(error.to_string().contains("reflectance none"), "{error}");
}

#[test]
fn allowed_zero_reflectance_runs_the_reflectance_model_on_zeros() {
    let mut odometry = Odometry::new(OracleMatcher::new(), config(false))
        .unwrap()
        .allowing_zero_reflectance();
    for i in 0..3 {
        let dark: Vec<[f32; 4]> = scan(i).iter().map(|&[x, y, z, _]| [x, y, z, 0.0]).collect();
        if i > 0 {
            odometry
                .matcher
                .truth
                .set(true_pose(i).inverse() * true_pose(i - 1));
        }
        let pose = odometry.register(Scan::new(&dark)).unwrap();
        assert!(error_to_truth(&pose, i).0 < 0.02, "frame {i}");
    }
    assert_eq!(
        odometry.reflectance_scale(),
        Some(ReflectanceScale::Ignored)
    );
    assert!(odometry.matcher.uses_reflectance() && odometry.matcher.encoded.get() == 3);
}

#[test]
fn bad_settings_and_a_matching_stage_the_matcher_does_not_run_are_named() {
    for (change, key) in [
        (
            (|c: &mut OdometryConfig| c.ransac.threshold = -1.0) as fn(&mut OdometryConfig),
            "ransac.threshold",
        ),
        (
            |c: &mut OdometryConfig| c.matching_stage = MatchingStage::Graph,
            "matching_stage",
        ),
    ] {
        let mut config = OdometryConfig::default();
        change(&mut config);
        let error = Odometry::new(OracleMatcher::new(), config).err().unwrap();
        assert!(error.to_string().contains(key), "{error}");
    }
}

#[test]
fn symmetric_matching_follows_the_truth_both_ways() {
    let mut config = config(false);
    config.matching.symmetric = true;
    let mut odometry = Odometry::new(OracleMatcher::new(), config).unwrap();
    for i in 0..4 {
        let pose = register(&mut odometry, &scan(i), i.saturating_sub(1), i);
        let (moved, turned) = error_to_truth(&pose, i);
        assert!(
            moved < 0.02 && turned < 0.1,
            "frame {i}: {moved} m, {turned}°"
        );
    }
    for d in &odometry.diagnostics()[1..] {
        assert!(d.backward_inliers.is_some_and(|n| n >= 10), "{d:?}");
        assert!(d.timings_ms.contains_key("network_backward"), "{d:?}");
    }
}

#[test]
fn symmetric_pairs_take_the_midpoint_of_both_directions_or_the_one_with_inliers() {
    let pair = |transform: Isometry3<f64>, inliers: usize| {
        let points = vec![Point3::new(1.0, 2.0, 3.0); inliers];
        Matched::new(PairMotion {
            transform,
            source: points.clone(),
            target: points,
            cells: vec![[0, 0]; inliers],
            inliers: vec![true; inliers],
            num_inliers: inliers,
            inlier_votes: Some(inliers as f64),
        })
    };
    let forward = Isometry3::new(Vector3::new(1.0, 0.0, 0.0), Vector3::z() * 0.02);
    let backward = Isometry3::new(Vector3::new(-1.2, 0.0, 0.0), Vector3::z() * -0.04).inverse();
    let both = symmetric(pair(forward, 20), pair(backward.inverse(), 30), 10);
    // The translations' mean, half way round about z.
    let mean = (forward.translation.vector + backward.translation.vector) / 2.0;
    let expected = Isometry3::new(mean, Vector3::z() * 0.03);
    let (moved, turned) = pose_difference(&expected.to_homogeneous(), &both.transform);
    assert!(moved < 1e-12 && turned < 1e-9, "{moved} m, {turned}°");
    assert_eq!(
        (both.motion.num_inliers, both.motion.source.len()),
        (50, 50)
    );
    assert_eq!(both.motion.inlier_votes, Some(50.0));
    // A direction without enough inliers is left out.
    let forward_only = symmetric(pair(forward, 20), pair(backward.inverse(), 5), 10);
    assert_eq!(forward_only.transform, forward.to_homogeneous());
    let backward_only = symmetric(pair(forward, 5), pair(backward.inverse(), 30), 10);
    let (moved, _) = pose_difference(&backward.to_homogeneous(), &backward_only.transform);
    assert!(moved < 1e-12);
}

#[test]
fn deskewing_a_sweep_taken_at_one_moment_changes_nothing() {
    let mut plain = Odometry::new(OracleMatcher::new(), config(false)).unwrap();
    let mut config = config(false);
    config.deskew.enabled = true;
    let mut deskewed = Odometry::new(OracleMatcher::new(), config).unwrap();
    for i in 0..4 {
        let points = scan(i);
        let at_once = vec![0.0; points.len()];
        let expected = register(&mut plain, &points, i.saturating_sub(1), i);
        deskewed
            .matcher
            .truth
            .set(true_pose(i).inverse() * true_pose(i.saturating_sub(1)));
        let pose = deskewed
            .register(Scan {
                point_times: Some(&at_once),
                ..Scan::new(&points)
            })
            .unwrap();
        let difference = pose_difference(&expected.to_homogeneous(), &pose.to_homogeneous());
        assert!(difference.0 < 1e-6, "frame {i}");
    }
    let flags: Vec<bool> = deskewed.diagnostics().iter().map(|d| d.deskewed).collect();
    assert_eq!(flags, [false, false, true, true]);
    let points = scan(4);
    let error = deskewed
        .register(Scan {
            point_times: Some(&[0.0; 3]),
            ..Scan::new(&points)
        })
        .unwrap_err();
    assert!(error.to_string().starts_with("point_times:"), "{error}");
}

#[test]
fn reflectance_detection_follows_python() {
    assert_eq!(
        detect_reflectance(Some(&[0.1, 0.9])).0,
        ReflectanceScale::Unit
    );
    assert_eq!(
        detect_reflectance(Some(&[0.0, 200.0])).0,
        ReflectanceScale::ZeroTo255
    );
    assert_eq!(
        detect_reflectance(Some(&[0.0, 4000.0])).0,
        ReflectanceScale::ZeroTo65535
    );
    assert_eq!(
        detect_reflectance(Some(&[0.0, 70000.0])).0,
        ReflectanceScale::Ignored
    );
    assert_eq!(
        detect_reflectance(Some(&[3.0, 3.0])).0,
        ReflectanceScale::Ignored
    );
    assert_eq!(
        detect_reflectance(Some(&[-1.0, 3.0])).0,
        ReflectanceScale::Ignored
    );
    assert_eq!(detect_reflectance(Some(&[])).0, ReflectanceScale::Ignored);
    let cloud = normalised(
        vec![[0.0, 0.0, 0.0, 300.0], [0.0, 0.0, 0.0, 51.0]],
        ReflectanceScale::ZeroTo255,
    );
    assert_eq!((cloud[0][3], cloud[1][3]), (1.0, 0.2));
}

#[test]
fn scans_without_reflectance_switch_to_the_range_only_model() {
    let range_only = || OracleMatcher {
        reads_reflectance: false,
        ..OracleMatcher::new()
    };
    let odometry = Odometry::new(OracleMatcher::new(), config(true)).unwrap();
    let mut odometry = odometry.with_range_only(range_only()).unwrap();
    for i in 0..3 {
        register(&mut odometry, &scan(i), i.saturating_sub(1), i);
    }
    assert_eq!(odometry.reflectance_scale(), Some(ReflectanceScale::Unit));
    for i in 3..6 {
        let dark: Vec<[f32; 4]> = scan(i).iter().map(|&[x, y, z, _]| [x, y, z, 0.0]).collect();
        odometry
            .matcher
            .truth
            .set(true_pose(i).inverse() * true_pose(i - 1));
        let pose = odometry.register(Scan::new(&dark)).unwrap();
        assert!(error_to_truth(&pose, i).0 < 0.02, "frame {i}");
    }
    assert!(!odometry.matcher.uses_reflectance());
    // The range-only model encoded the reference again and then each new scan.
    assert_eq!(odometry.matcher.encoded.get(), 4);
    assert_eq!(
        odometry.reflectance_scale(),
        Some(ReflectanceScale::Ignored)
    );
    // Not a range-only model; a model already range-only needs none.
    let error = Odometry::new(OracleMatcher::new(), config(false))
        .unwrap()
        .with_range_only(OracleMatcher::new())
        .err()
        .unwrap();
    assert!(error.to_string().starts_with("range_only:"), "{error}");
    let mut alone = Odometry::new(range_only(), config(false)).unwrap();
    let dark: Vec<[f32; 4]> = scan(0).iter().map(|&[x, y, z, _]| [x, y, z, 0.0]).collect();
    alone.register(Scan::new(&dark)).unwrap();
    assert_eq!(alone.reflectance_scale(), Some(ReflectanceScale::Ignored));
}

#[test]
fn a_reset_starts_the_drive_afresh_and_the_history_stays_bounded() {
    let range_only = OracleMatcher {
        reads_reflectance: false,
        ..OracleMatcher::new()
    };
    let mut odometry = Odometry::new(OracleMatcher::new(), config(true))
        .unwrap()
        .with_range_only(range_only)
        .unwrap()
        .keeping_history(3);
    // Both models told the truth: the range-only one takes over within a frame.
    let drive = |odometry: &mut Odometry<OracleMatcher>| -> Vec<Isometry3<f64>> {
        (0..7)
            .map(|i| {
                let truth = true_pose(i).inverse() * true_pose(i.saturating_sub(1));
                odometry.matcher.truth.set(truth);
                odometry.range_only.as_ref().unwrap().truth.set(truth);
                let points = scan(i);
                let dark: Vec<[f32; 4]> =
                    points.iter().map(|&[x, y, z, _]| [x, y, z, 0.0]).collect();
                odometry
                    .register(Scan::new(if i < 4 { &points } else { &dark }))
                    .unwrap()
            })
            .collect()
    };
    let first = drive(&mut odometry);
    assert_eq!(odometry.frames(), 7);
    assert!(odometry.poses().len() <= 5 && odometry.poses().len() >= 3);
    assert_eq!(odometry.pose(), Some(first[6]));
    assert_eq!(odometry.diagnostics().last().unwrap().index, 6);
    let delta = odometry.delta().unwrap();
    let expected = first[5].inverse() * first[6];
    assert!((delta.to_homogeneous() - expected.to_homogeneous()).abs().max() < 1e-12);
    assert!(odometry.runs_range_only());
    odometry.reset();
    assert_eq!(
        (odometry.frames(), odometry.pose(), odometry.delta()),
        (0, None, None)
    );
    assert!(!odometry.runs_range_only() && odometry.reflectance_scale().is_none());
    // The same drive again gives the same poses: nothing of the first is left.
    let again = drive(&mut odometry);
    assert_eq!(again, first);
    assert_eq!(notice_kinds(&odometry).concat(), ["range_only_model"]);
}

/// The kinds of the notices of every frame so far, frame by frame.
fn notice_kinds<M: FrameMatcher>(odometry: &Odometry<M>) -> Vec<Vec<&'static str>> {
    odometry
        .diagnostics()
        .iter()
        .map(|d| d.notices.iter().map(Notice::kind).collect())
        .collect()
}

#[test]
fn each_notice_is_said_once_at_the_frame_it_arose_in() {
    let range_only = OracleMatcher {
        reads_reflectance: false,
        ..OracleMatcher::new()
    };
    let mut odometry = Odometry::new(OracleMatcher::new(), config(false))
        .unwrap()
        .with_range_only(range_only)
        .unwrap();
    let bright = |i: usize| -> Vec<[f32; 4]> {
        scan(i)
            .iter()
            .map(|&[x, y, z, r]| [x, y, z, r * 255.0])
            .collect()
    };
    // Frame 0: the scale; 1: a timestamp going back; 2: beyond the scale; 3: no reflectance (N×3).
    let first = bright(0);
    odometry
        .register(Scan {
            timestamp: Some(1.0),
            ..Scan::new(&first)
        })
        .unwrap();
    let second = bright(1);
    odometry
        .register(Scan {
            timestamp: Some(0.5),
            ..Scan::new(&second)
        })
        .unwrap();
    let third: Vec<[f32; 4]> = bright(2)
        .iter()
        .map(|&[x, y, z, r]| [x, y, z, r * 4.0])
        .collect();
    odometry
        .register(Scan {
            timestamp: Some(0.4),
            ..Scan::new(&third)
        })
        .unwrap();
    let fourth = scan(3);
    odometry
        .register(Scan {
            has_reflectance: false,
            ..Scan::new(&fourth)
        })
        .unwrap();
    let fifth: Vec<[f32; 4]> = scan(4)
        .iter()
        .map(|&[x, y, z, r]| [x, y, z, r * 1000.0])
        .collect();
    odometry.register(Scan::new(&fifth)).unwrap();
    assert_eq!(
        notice_kinds(&odometry),
        [
            vec!["reflectance_scaled"],
            vec!["timestamp_not_after"],
            vec!["reflectance_clipped"],
            vec!["range_only_model"],
            vec![],
        ]
    );
    let said: Vec<String> = odometry
        .diagnostics()
        .iter()
        .flat_map(|d| d.notices.iter().map(Notice::message))
        .collect();
    assert!(
        said[0].starts_with("reflectance: values up to")
            && said[0].contains("look like 0–255: divided by 255"),
        "{}",
        said[0]
    );
    assert_eq!(
        said[1],
        "scan timestamp 0.5 is not after the previous scan's 1.0: taken for the next frame"
    );
    assert!(
        said[2].starts_with("reflectance: scan 2 reaches") && said[2].contains("clipped"),
        "{}",
        said[2]
    );
    assert_eq!(said[3], "reflectance: scan 3: the scans have no reflectance (N×3 points): the range-only model runs");
    let json = serde_json::to_value(&odometry.diagnostics()[1]).unwrap();
    assert_eq!(json["notices"][0]["kind"], "timestamp_not_after");
    assert!(serde_json::to_value(&odometry.diagnostics()[4])
        .unwrap()
        .get("notices")
        .is_none());
}

#[test]
fn a_scan_far_emptier_than_the_models_sensor_is_said_once() {
    let mut odometry = Odometry::new(OracleMatcher::new(), config(false)).unwrap();
    // Every other ring of the yard dropped: still plenty of points, but far less of the image.
    let sparse = |i: usize| -> Vec<[f32; 4]> { scan(i).into_iter().step_by(4).collect() };
    for i in 0..3 {
        odometry.register(Scan::new(&sparse(i))).unwrap();
    }
    let fill = odometry.diagnostics()[0].image_fill.unwrap();
    if fill < LOW_IMAGE_FILL {
        assert_eq!(
            notice_kinds(&odometry),
            [vec!["sensor_mismatch"], vec![], vec![]]
        );
        let message = odometry.diagnostics()[0].notices[0].message();
        assert!(message.contains("cannot be trusted"), "{message}");
    } else {
        panic!("the sparse yard fills {fill}: not a test of the sensor check");
    }
    let mut full = Odometry::new(OracleMatcher::new(), config(false)).unwrap();
    full.register(Scan::new(&scan(0))).unwrap();
    assert!(full.diagnostics()[0].image_fill.unwrap() >= LOW_IMAGE_FILL);
    assert_eq!(notice_kinds(&full), [Vec::<&str>::new()]);
}

#[test]
fn a_model_without_reflectance_and_no_range_only_model_says_its_poses_cannot_be_trusted() {
    let mut odometry = Odometry::new(OracleMatcher::new(), config(false))
        .unwrap()
        .allowing_zero_reflectance();
    let points = scan(0);
    odometry
        .register(Scan {
            has_reflectance: false,
            ..Scan::new(&points)
        })
        .unwrap();
    let notices = &odometry.diagnostics()[0].notices;
    assert_eq!(notices.len(), 1);
    assert_eq!(notices[0].kind(), "zero_reflectance");
    assert!(notices[0].message().contains("cannot be trusted"));
    let range_only = OracleMatcher {
        reads_reflectance: false,
        ..OracleMatcher::new()
    };
    let mut alone = Odometry::new(range_only, config(false)).unwrap();
    alone.register(Scan::new(&points)).unwrap();
    assert_eq!(notice_kinds(&alone), [vec!["reflectance_unused"]]);
}

/// `register_pair` of yard scans `from` and `to` with the oracle told their true motion.
fn register_pair(
    odometry: &mut Odometry<OracleMatcher>,
    from: usize,
    to: usize,
) -> Result<RegisteredPair> {
    odometry
        .matcher
        .truth
        .set(true_pose(to).inverse() * true_pose(from));
    odometry.register_pair(Scan::new(&scan(from)), Scan::new(&scan(to)), false)
}

#[test]
fn a_pair_follows_the_truth_one_way_both_ways_and_refined_by_ndt() {
    let truth = (true_pose(2).inverse() * true_pose(0)).to_homogeneous();
    for (mapping, symmetric) in [(false, false), (true, false), (false, true), (true, true)] {
        let mut config = config(mapping);
        config.matching.symmetric = symmetric;
        let mut odometry = Odometry::new(OracleMatcher::new(), config).unwrap();
        let pair = register_pair(&mut odometry, 0, 2).unwrap();
        let (moved, turned) = pose_difference(&truth, &pair.transform);
        let context = format!("mapping {mapping}, symmetric {symmetric}");
        assert!(
            moved < 0.02 && turned < 0.1,
            "{context}: {moved} m, {turned}°"
        );
        assert_eq!(pair.map_refined, mapping.then_some(true), "{context}");
        assert_eq!(pair.rounds, 1);
        let matches = &pair.matches;
        assert!(
            matches.num_inliers >= 10,
            "{context}: {}",
            matches.num_inliers
        );
        assert_eq!(matches.source.len(), matches.target.len());
        assert_eq!(matches.inliers.len(), matches.source.len());
        // The matches are in the frames of the scans given: the motion carries the inliers over.
        for (p, q) in matches
            .source
            .iter()
            .zip(&matches.target)
            .zip(&matches.inliers)
            .filter(|(_, &inlier)| inlier)
            .map(|(pair, _)| pair)
        {
            let carried = truth.transform_point(p);
            assert!((carried - q).norm() < 0.3, "{context}: {p} → {q}");
        }
        // The drive is untouched; the reflectance scale is chosen as a drive's first scan chooses it.
        assert!(odometry.poses().len() == 0 && odometry.diagnostics().is_empty());
        assert_eq!(odometry.reflectance_scale(), Some(ReflectanceScale::Unit));
    }
}

#[test]
fn a_pair_refuses_too_few_points_and_a_large_motion_without_a_wide_window() {
    let mut odometry = Odometry::new(OracleMatcher::new(), config(true)).unwrap();
    let full = scan(0);
    let few = &full[..500];
    let error = odometry
        .register_pair(Scan::new(few), Scan::new(&full), false)
        .unwrap_err();
    assert!(
        error
            .to_string()
            .starts_with("reference: 500 finite points"),
        "{error}"
    );
    let error = odometry
        .register_pair(Scan::new(&full), Scan::new(few), false)
        .unwrap_err();
    assert!(error.to_string().starts_with("target:"), "{error}");
    let flags = vec![false; 3];
    let moving = Scan {
        moving: Some(&flags),
        ..Scan::new(&full)
    };
    let error = odometry
        .register_pair(moving, Scan::new(&full), false)
        .unwrap_err();
    assert!(error.to_string().starts_with("moving:"), "{error}");
    let error = odometry
        .register_pair(Scan::new(&full), Scan::new(&full), true)
        .unwrap_err();
    assert!(error.to_string().contains("no wide window"), "{error}");
    // Every point flagged moving leaves none to match.
    let all = vec![true; full.len()];
    let error = odometry
        .register_pair(
            Scan {
                moving: Some(&all),
                ..Scan::new(&full)
            },
            Scan::new(&full),
            false,
        )
        .unwrap_err();
    assert!(
        error.to_string().starts_with("reference: 0 finite points"),
        "{error}"
    );
}

#[test]
fn a_moved_scan_keeps_its_reflectance_and_float32_precision() {
    let cloud: Vec<[f32; 4]> = (0..5000)
        .map(|i| {
            let t = i as f32;
            [
                (t * 0.37).sin() * 120.0,
                (t * 0.11).cos() * 120.0,
                (t * 0.05).sin() * 20.0,
                (i % 97) as f32 / 97.0,
            ]
        })
        .collect();
    let transform = Isometry3::new(
        Vector3::new(1.6, -0.3, 0.05),
        Vector3::new(0.012, -0.026, 0.21),
    )
    .to_homogeneous();
    let moved = moved_cloud(&cloud, &transform);
    for (p, q) in cloud.iter().zip(&moved) {
        let expected =
            transform.transform_point(&Point3::new(p[0] as f64, p[1] as f64, p[2] as f64));
        for axis in 0..3 {
            // A few float32 steps at 170 m.
            assert!(
                (q[axis] as f64 - expected[axis]).abs() < 1e-4,
                "{p:?} → {q:?}, not {expected}"
            );
        }
        assert_eq!(q[3], p[3]);
    }
    assert_eq!(moved_cloud(&cloud, &Matrix4::identity()), cloud);
}

#[test]
fn the_round_trip_check_follows_a_loop_over_the_cells() {
    let (height, width) = (12, 20);
    let cells = height * width;
    let flow_of = |values: Vec<f32>| DenseFlow {
        flow: values,
        confidence: vec![1.0; cells],
        height,
        width,
    };
    // A deterministic spread of flows, the backward one undoing it up to a wobble.
    let forward: Vec<f32> = (0..2 * cells)
        .map(|i| ((i * 37 % 101) as f32 - 50.0) * 0.07)
        .collect();
    let backward: Vec<f32> = (0..2 * cells)
        .map(|i| -forward[(i + 21) % (2 * cells)] + ((i % 7) as f32 - 3.0) * 0.1)
        .collect();
    let (forward, backward) = (flow_of(forward), flow_of(backward));
    for wraps in [false, true] {
        for limit in [0.5, 1.0, 3.0] {
            let outliers = round_trip_outliers(&forward, &backward, wraps, limit);
            for row in 0..height {
                for col in 0..width {
                    let cell = row * width + col;
                    let (d_row, d_col) = (forward.flow[cell], forward.flow[cells + cell]);
                    let at_row = (row as f32 + d_row).round_ties_even() as i64;
                    let mut at_col = (col as f32 + d_col).round_ties_even() as i64;
                    if wraps {
                        at_col = at_col.rem_euclid(width as i64);
                    }
                    let inside =
                        (0..height as i64).contains(&at_row) && (0..width as i64).contains(&at_col);
                    let expected = !inside || {
                        let at = at_row as usize * width + at_col as usize;
                        let error = ((d_row + backward.flow[at]) as f64)
                            .hypot((d_col + backward.flow[cells + at]) as f64);
                        error > limit
                    };
                    assert_eq!(
                        outliers[cell], expected,
                        "cell {row},{col}, wraps {wraps}, limit {limit}"
                    );
                }
            }
        }
    }
    // A flow its backward flow undoes exactly is consistent wherever its matches stay in the image.
    let shift = flow_of([vec![1.0; cells], vec![2.0; cells]].concat());
    let back = flow_of([vec![-1.0; cells], vec![-2.0; cells]].concat());
    for wraps in [false, true] {
        let outliers = round_trip_outliers(&shift, &back, wraps, 0.5);
        for row in 0..height {
            for col in 0..width {
                let leaves = row == height - 1 || (!wraps && col >= width - 2);
                assert_eq!(
                    outliers[row * width + col],
                    leaves,
                    "{row},{col}, wraps {wraps}"
                );
            }
        }
    }
}

mod encode_ahead;
mod hostile;

/// A stand-in moving-object network: cells whose kept point stands above `above` (m) are moving; `fails`:
/// it reports an error instead.
struct TallThings {
    cylinder: CylinderConfig,
    above: f32,
    fails: bool,
}

impl TallThings {
    fn new() -> Self {
        TallThings {
            cylinder: CylinderConfig::kitti(),
            above: 0.0,
            fails: false,
        }
    }
}

impl crate::odometry::moving::MovingObjectNetwork for TallThings {
    fn cylinder(&self) -> &CylinderConfig {
        &self.cylinder
    }

    fn probability(&self, range: &[f32], height: &[f32]) -> Result<Vec<f32>> {
        if self.fails {
            return Err(Error::Model("moving.onnx: the network failed".into()));
        }
        Ok(range
            .iter()
            .zip(height)
            .map(|(&r, &z)| if r > 0.0 && z > self.above { 0.8 } else { 0.2 })
            .collect())
    }
}

#[test]
fn the_moving_object_network_flags_what_a_callers_mask_would() {
    use crate::odometry::moving::moving_points;

    let mut detected = Odometry::new(OracleMatcher::new(), config(true))
        .unwrap()
        .with_moving_objects(TallThings::new())
        .unwrap();
    let mut masked = Odometry::new(OracleMatcher::new(), config(true)).unwrap();
    for i in 0..4 {
        let points = scan(i);
        let truth = true_pose(i).inverse() * true_pose(i.saturating_sub(1));
        detected.matcher.truth.set(truth);
        masked.matcher.truth.set(truth);
        let pose = detected.register(Scan::new(&points)).unwrap();
        let mask = moving_points(&TallThings::new(), &points, 0.5).unwrap();
        let flagged = mask.iter().filter(|&&m| m).count();
        assert!(flagged > 1000 && flagged < points.len() / 2, "{flagged}");
        let expected = masked
            .register(Scan {
                moving: Some(&mask),
                ..Scan::new(&points)
            })
            .unwrap();
        assert_eq!(pose, expected, "scan {i}");
        let diagnostics = &detected.diagnostics()[i];
        assert_eq!(diagnostics.num_moving_predicted, Some(flagged));
        assert!(diagnostics.timings_ms.contains_key("moving_objects"));
        assert_eq!(masked.diagnostics()[i].num_moving_predicted, None);
    }
    assert!(error_to_truth(&detected.poses().last().unwrap(), 3).0 < 0.02);
}

#[test]
fn the_network_stays_idle_when_told_or_given_a_mask_and_its_errors_change_nothing() {
    let points = scan(0);
    let mut off = config(false);
    off.moving_objects.detect = false;
    let mut odometry = Odometry::new(OracleMatcher::new(), off)
        .unwrap()
        .with_moving_objects(TallThings {
            fails: true,
            ..TallThings::new()
        })
        .unwrap();
    odometry.register(Scan::new(&points)).unwrap();
    assert_eq!(odometry.diagnostics()[0].num_moving_predicted, None);

    let mut odometry = Odometry::new(OracleMatcher::new(), config(false))
        .unwrap()
        .with_moving_objects(TallThings {
            fails: true,
            ..TallThings::new()
        })
        .unwrap();
    let none_moving = vec![false; points.len()];
    odometry
        .register(Scan {
            moving: Some(&none_moving),
            ..Scan::new(&points)
        })
        .unwrap();
    assert_eq!(odometry.diagnostics()[0].num_moving_predicted, None);
    let error = odometry.register(Scan::new(&points)).unwrap_err();
    assert!(error.to_string().contains("the network failed"), "{error}");
    assert_eq!(odometry.poses().len(), 1);
    assert_eq!(odometry.diagnostics().len(), 1);

    let other_image = TallThings {
        cylinder: CylinderConfig {
            width: 1024,
            ..CylinderConfig::kitti()
        },
        ..TallThings::new()
    };
    let error = Odometry::new(OracleMatcher::new(), config(false))
        .unwrap()
        .with_moving_objects(other_image)
        .err()
        .expect("another image is refused");
    assert!(error.to_string().starts_with("moving_objects:"), "{error}");
}

#[test]
fn pairs_beyond_the_window_are_matched_with_windows_the_prediction_places() {
    // 0.4 m a frame, beyond a window that reaches 0.3 m: from the third scan on (a velocity measured)
    // each pair is matched from the prediction.
    let mut config = config(false);
    config.motion_model.match_from_prediction_m = Some(0.3);
    config.motion_model.guided_windows = Some(true);
    let matcher = OracleMatcher {
        guided: Some(true),
        ..OracleMatcher::new()
    };
    let mut odometry = Odometry::new(matcher, config.clone()).unwrap();
    for i in 0..6 {
        let pose = register(&mut odometry, &scan(i), i.saturating_sub(1), i);
        let (moved, turned) = error_to_truth(&pose, i);
        assert!(
            moved < 0.02 && turned < 0.1,
            "frame {i}: {moved} m, {turned}°"
        );
    }
    let diagnostics = odometry.diagnostics();
    for d in &diagnostics[..2] {
        assert_eq!(d.guided_windows, None, "{d:?}");
    }
    for d in &diagnostics[2..] {
        assert_eq!(d.guided_windows, Some(true), "{d:?}");
        assert_eq!(
            (d.rematch_rounds, d.fallback.map(Fallback::name)),
            (None, None)
        );
        assert!(d.timings_ms.contains_key("rematch"));
    }
    // Each scan encoded once: nothing moved and encoded again.
    assert_eq!(odometry.matcher.encoded.get(), 6);
    // The windows went where the prediction takes the points: the scene streams backwards past the car,
    // across columns that grow leftwards (the azimuth decreases with the column), by a few columns on
    // average.
    let guides = odometry.matcher.guides.borrow();
    assert_eq!(guides.len(), 4);
    assert!(guides.iter().all(|&mean| mean.abs() > 0.5), "{guides:?}");

    // Told not to (frame to frame DMLO's default), the odometry moves the reference by the prediction
    // and encodes it again.
    config.motion_model.guided_windows = None;
    let matcher = OracleMatcher {
        guided: Some(true),
        ..OracleMatcher::new()
    };
    let mut reprojected = Odometry::new(matcher, config).unwrap();
    for i in 0..6 {
        register(&mut reprojected, &scan(i), i.saturating_sub(1), i);
    }
    for d in &reprojected.diagnostics()[2..] {
        assert_eq!(d.guided_windows, None);
        assert!(d.rematch_rounds.is_some(), "{d:?}");
    }
    assert!(reprojected.matcher.guides.borrow().is_empty());
    assert!(reprojected.matcher.encoded.get() > 6);
}

#[test]
fn guided_windows_that_lock_on_standing_still_give_way_to_the_moved_reference() {
    let mut config = config(true);
    config.motion_model.match_from_prediction_m = Some(0.3);
    let matcher = OracleMatcher {
        guided: Some(false),
        ..OracleMatcher::new()
    };
    let mut odometry = Odometry::new(matcher, config).unwrap();
    for i in 0..4 {
        register(&mut odometry, &scan(i), i.saturating_sub(1), i);
    }
    for d in &odometry.diagnostics()[2..] {
        // Standing still lies 0.4 m from the prediction: implausible, so the rounds ran.
        assert_eq!(d.guided_windows, Some(false), "{d:?}");
        assert!(d.rematch_rounds.is_some(), "{d:?}");
    }
    assert!(odometry.matcher.encoded.get() > 4);
}

#[test]
fn the_expected_flow_of_a_turn_is_its_angle_in_columns_the_short_way_round() {
    let cylinder = CylinderConfig::kitti();
    let (height, width) = (cylinder.height, cylinder.width);
    // One point per cell of three rows, at the cell's own direction, 10 m away; the rest empty.
    let mut points = vec![f32::NAN; height * width * 3];
    for row in [10, 30, 50] {
        for col in 0..width {
            let p = cylinder.unproject(row as f64, col as f64, 10.0);
            points[(row * width + col) * 3..][..3]
                .copy_from_slice(&[p.x as f32, p.y as f32, p.z as f32]);
        }
    }
    let yaw = 3.0f64;
    let turn = Isometry3::rotation(Vector3::z() * yaw.to_radians()).to_homogeneous();
    let expected = super::rematching::expected_flow(&points, &cylinder, &turn);
    let columns = yaw / cylinder.horizontal_resolution_deg;
    let per_turn = cylinder.columns_per_turn();
    for (cell, [d_row, d_col]) in expected.iter().enumerate() {
        let row = cell / width;
        if ![10, 30, 50].contains(&row) {
            assert!(d_row.is_nan() && d_col.is_nan(), "cell {cell}");
            continue;
        }
        assert!(d_row.abs() < 1e-4, "cell {cell}: {d_row}");
        // Turning left raises the azimuth, which the columns count down; near the seam the short way.
        assert!(
            (*d_col as f64 + columns).abs() < 1e-3,
            "cell {cell}: {d_col}"
        );
        assert!((d_col.abs() as f64) < per_turn / 2.0);
    }
    // A point moved onto the sensor has no direction.
    let onto_sensor = Isometry3::translation(-10.0, 0.0, 0.0).to_homogeneous();
    let mut ahead = vec![f32::NAN; height * width * 3];
    let cell = 30 * width + 900;
    ahead[cell * 3..][..3].copy_from_slice(&[10.0, 0.0, 0.0]);
    let flow = super::rematching::expected_flow(&ahead, &cylinder, &onto_sensor);
    assert!(
        flow[cell][0].is_nan() && flow[cell][1].is_nan(),
        "{:?}",
        flow[cell]
    );
}

/// `T_tgt_ref` of `matrix`, a rigid motion, as an isometry.
fn isometry(matrix: &Matrix4<f64>) -> Isometry3<f64> {
    let rotation =
        nalgebra::Rotation3::from_matrix_unchecked(matrix.fixed_view::<3, 3>(0, 0).into_owned());
    Isometry3::from_parts(
        matrix.fixed_view::<3, 1>(0, 3).into_owned().into(),
        nalgebra::UnitQuaternion::from_rotation_matrix(&rotation),
    )
}

#[test]
fn a_first_pair_that_another_start_explains_as_well_is_flagged_and_a_reversing_one_takes_the_forward_start(
) {
    let mut config = config(false);
    config.motion_model.start_check_m = Some(3.0);
    let truth = true_pose(1).inverse() * true_pose(0);
    let starts = rematching::search_starts(&[3.0, -3.0], &[0.0]);
    // The moved reference's motion to the target, which brings each start back to the truth.
    let from_start = |k: usize| Some(truth * isometry(&starts[k]).inverse());
    let first_pair = |config: &OdometryConfig, answers: Vec<Option<Isometry3<f64>>>| {
        let mut odometry = Odometry::new(OracleMatcher::new(), config.clone()).unwrap();
        register(&mut odometry, &scan(0), 0, 0);
        odometry.matcher.answers.borrow_mut().extend(answers);
        let pose = register(&mut odometry, &scan(1), 0, 1);
        assert!(
            odometry.matcher.answers.borrow().is_empty(),
            "{:?}",
            odometry.diagnostics()[1]
        );
        register(&mut odometry, &scan(2), 1, 2);
        (odometry, pose)
    };

    // From the identity the flow says the scene stood still (an alias); from 3 m ahead the truth, 0.4 m
    // away, holds as well: flagged, and the frame keeps the identity's motion.
    let (odometry, pose) = first_pair(
        &config,
        vec![Some(Isometry3::identity()), from_start(0), None],
    );
    let d = odometry.diagnostics();
    assert_eq!(d[1].ambiguous_start, Some(true), "{:?}", d[1]);
    assert!(d[1].timings_ms.contains_key("start_check"));
    assert!(error_to_truth(&pose, 1).0 > 0.2, "{pose}"); // the identity's (alias) motion, not the start's
    assert_eq!(d[1].fallback, None); // standing still is no reversing: no start is preferred
    assert_eq!((d[0].ambiguous_start, d[2].ambiguous_start), (None, None)); // a velocity is measured
    assert_eq!(odometry.matcher.encoded.get(), 3 + 2);

    // From the identity the car drives backwards as fast as it truly drives forward (the aliases of posts
    // passed at speed reversed so): the start's forward motion is taken, and said so.
    config.motion_model.start_max_reverse_m = Some(0.2); // the truth drives 0.4 m a frame
    let reversing = Some(truth.inverse());
    let (odometry, pose) = first_pair(&config, vec![reversing, from_start(0), from_start(1)]);
    let d = &odometry.diagnostics()[1];
    assert_eq!(d.ambiguous_start, Some(true), "{d:?}");
    assert_eq!(d.fallback.map(Fallback::name), Some("forward_start"));
    assert!(d.num_inliers >= 10, "{d:?}");
    assert!(error_to_truth(&pose, 1).0 < 0.02, "{pose}");
    assert_eq!(odometry.matcher.encoded.get(), 3 + 2);
    // … not when the reversing is within the limit, nor when no limit is set.
    for limit in [Some(0.6), None] {
        config.motion_model.start_max_reverse_m = limit;
        let (odometry, pose) = first_pair(&config, vec![reversing, from_start(0), from_start(1)]);
        let d = &odometry.diagnostics()[1];
        assert_eq!(
            (d.ambiguous_start, d.fallback.map(Fallback::name)),
            (Some(true), None)
        );
        assert!(error_to_truth(&pose, 1).0 > 0.7, "{pose}");
    }
    config.motion_model.start_max_reverse_m = Some(0.5);

    // Both starts come back to the pair's own motion, or find nothing: not ambiguous.
    for answers in [
        vec![Some(truth), from_start(0), from_start(1)],
        vec![Some(truth), None, None],
    ] {
        let (odometry, pose) = first_pair(&config, answers);
        assert_eq!(odometry.diagnostics()[1].ambiguous_start, Some(false));
        assert!(error_to_truth(&pose, 1).0 < 0.02);
        assert_eq!(odometry.matcher.encoded.get(), 3 + 2);
    }

    // Not asked for: nothing matched again.
    config.motion_model.start_check_m = None;
    let (odometry, _) = first_pair(&config, vec![]);
    assert_eq!(odometry.diagnostics()[1].ambiguous_start, None);
    assert_eq!(odometry.matcher.encoded.get(), 3);
}
