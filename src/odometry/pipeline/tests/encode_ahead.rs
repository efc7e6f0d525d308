//! [`EncodeAhead`]: the next scan encoded on another thread changes nothing but where the work runs.

use std::sync::{Arc, Mutex};
use std::thread::ThreadId;

use super::*;

/// A matcher that knows the drive: it recognises each scan's range image among those of the drive
/// (so it needs no state set between pairs, and any thread may run it), its flow the ground truth
/// between the two frames, and it notes the thread of every encode.
struct DriveOracle {
    cylinder: CylinderConfig,
    ranges: Vec<Vec<f32>>,
    encoders: Mutex<Vec<ThreadId>>,
}

impl DriveOracle {
    fn new(scans: &[Vec<[f32; 4]>]) -> Self {
        let cylinder = CylinderConfig::kitti();
        let ranges = scans
            .iter()
            .map(|scan| project(scan, &cylinder).unwrap().range)
            .collect();
        DriveOracle {
            cylinder,
            ranges,
            encoders: Mutex::new(Vec::new()),
        }
    }
}

impl FrameMatcher for DriveOracle {
    type Features = (usize, Vec<f32>);

    fn cylinder(&self) -> &CylinderConfig {
        &self.cylinder
    }

    fn encode(&self, image: &[f32]) -> Result<(usize, Vec<f32>)> {
        self.encoders
            .lock()
            .unwrap()
            .push(std::thread::current().id());
        let range = &image[..image.len() / 2];
        let frame = self
            .ranges
            .iter()
            .position(|known| known == range)
            .expect("a scan of the drive");
        Ok((frame, range.to_vec()))
    }

    fn flow(&self, reference: &(usize, Vec<f32>), target: &(usize, Vec<f32>)) -> Result<DenseFlow> {
        let motion = true_pose(target.0).inverse() * true_pose(reference.0);
        true_flow(&reference.1, &target.1, &motion, &self.cylinder)
    }
}

fn without_timings(diagnostics: &[FrameDiagnostics]) -> Vec<FrameDiagnostics> {
    diagnostics
        .iter()
        .map(|d| FrameDiagnostics {
            timings_ms: Default::default(),
            ..d.clone()
        })
        .collect()
}

#[test]
fn encoding_ahead_gives_the_serial_loops_poses_from_another_thread() {
    let scans: Vec<Vec<[f32; 4]>> = (0..6).map(scan).collect();
    for mapping in [false, true] {
        let mut serial = Odometry::new(DriveOracle::new(&scans), config(mapping)).unwrap();
        let mut ahead =
            Odometry::new(EncodeAhead::new(DriveOracle::new(&scans)), config(mapping)).unwrap();
        for (i, points) in scans.iter().enumerate() {
            let expected = serial.register(Scan::new(points)).unwrap();
            let next = scans.get(i + 1).map(|next| Scan::new(next));
            let pose = ahead.register_ahead(Scan::new(points), next).unwrap();
            assert_eq!(pose, expected, "mapping {mapping}, scan {i}");
        }
        assert_eq!(
            without_timings(ahead.diagnostics()),
            without_timings(serial.diagnostics())
        );
        assert!(error_to_truth(&ahead.poses().last().unwrap(), 5).0 < 0.02);
        // Scans 0 and 1 are encoded here (the reflectance scale is chosen on scan 0); 2–5 ahead.
        let here = std::thread::current().id();
        let threads = ahead.matcher().matcher().encoders.lock().unwrap().clone();
        assert_eq!(threads.len(), 6, "each scan encoded once");
        assert_eq!(threads.iter().filter(|&&t| t != here).count(), 4);
    }
}

#[test]
fn a_next_scan_that_does_not_come_is_encoded_in_vain_and_nothing_changes() {
    let scans: Vec<Vec<[f32; 4]>> = (0..5).map(scan).collect();
    let mut serial = Odometry::new(DriveOracle::new(&scans), config(false)).unwrap();
    let mut ahead =
        Odometry::new(EncodeAhead::new(DriveOracle::new(&scans)), config(false)).unwrap();
    // Announced next scans that are not the ones registered next: 3 after 1, nothing after 2, a scan
    // too sparse to be matched after 3, and scan 4 whose announced successor never comes.
    let sparse = &scans[0][..100];
    let announced = [
        Some(&scans[1][..]),
        Some(&scans[3][..]),
        None,
        Some(sparse),
        Some(&scans[0][..]),
    ];
    for (i, points) in scans.iter().enumerate() {
        let expected = serial.register(Scan::new(points)).unwrap();
        let next = announced[i].map(Scan::new);
        assert_eq!(
            ahead.register_ahead(Scan::new(points), next).unwrap(),
            expected,
            "scan {i}"
        );
    }
    assert_eq!(
        without_timings(ahead.diagnostics()),
        without_timings(serial.diagnostics())
    );
}

#[test]
fn errors_are_registers_and_leave_nothing_queued() {
    let scans: Vec<Vec<[f32; 4]>> = (0..4).map(scan).collect();
    let mut ahead =
        Odometry::new(EncodeAhead::new(DriveOracle::new(&scans)), config(false)).unwrap();
    for i in 0..2 {
        ahead
            .register_ahead(Scan::new(&scans[i]), Some(Scan::new(&scans[i + 1])))
            .unwrap();
    }
    let wrong_mask = [false; 3];
    let bad = Scan {
        moving: Some(&wrong_mask),
        ..Scan::new(&scans[2])
    };
    let error = ahead
        .register_ahead(bad, Some(Scan::new(&scans[3])))
        .unwrap_err();
    assert!(error.to_string().contains("moving"), "{error}");
    assert!(ahead.matcher().queued.lock().unwrap().is_none());
    // Scan 2 again, well formed: its features computed ahead are still the right ones.
    ahead
        .register_ahead(Scan::new(&scans[2]), Some(Scan::new(&scans[3])))
        .unwrap();
    let pose = ahead.register_ahead(Scan::new(&scans[3]), None).unwrap();
    assert!(error_to_truth(&pose, 3).0 < 0.02);
    assert_eq!(ahead.diagnostics().len(), 4);
}

/// [`TallThings`], noting the thread of every call.
struct NotedNetwork {
    inner: TallThings,
    callers: Arc<Mutex<Vec<ThreadId>>>,
}

impl crate::odometry::moving::MovingObjectNetwork for NotedNetwork {
    fn cylinder(&self) -> &CylinderConfig {
        self.inner.cylinder()
    }

    fn probability(&self, range: &[f32], height: &[f32]) -> Result<Vec<f32>> {
        self.callers
            .lock()
            .unwrap()
            .push(std::thread::current().id());
        self.inner.probability(range, height)
    }
}

#[test]
fn the_next_scans_moving_points_are_flagged_ahead_once() {
    let scans: Vec<Vec<[f32; 4]>> = (0..6).map(scan).collect();
    // The oracle recognises the images the odometry encodes: those of the points left unflagged.
    let unflagged: Vec<Vec<[f32; 4]>> = scans
        .iter()
        .map(|points| {
            let moving =
                crate::odometry::moving::moving_points(&TallThings::new(), points, 0.5).unwrap();
            kept_rows(points, &moving.iter().map(|m| !m).collect::<Vec<_>>())
        })
        .collect();
    let callers = Arc::new(Mutex::new(Vec::new()));
    let mut serial = Odometry::new(DriveOracle::new(&unflagged), config(true))
        .unwrap()
        .with_moving_objects(TallThings::new())
        .unwrap();
    let mut ahead = Odometry::new(EncodeAhead::new(DriveOracle::new(&unflagged)), config(true))
        .unwrap()
        .with_moving_objects(NotedNetwork {
            inner: TallThings::new(),
            callers: Arc::clone(&callers),
        })
        .unwrap();
    for (i, points) in scans.iter().enumerate() {
        let expected = serial.register(Scan::new(points)).unwrap();
        let next = scans.get(i + 1).map(|next| Scan::new(next));
        assert_eq!(
            ahead.register_ahead(Scan::new(points), next).unwrap(),
            expected,
            "scan {i}"
        );
    }
    assert_eq!(
        without_timings(ahead.diagnostics()),
        without_timings(serial.diagnostics())
    );
    assert!(ahead.diagnostics()[5].num_moving_predicted.unwrap() > 1000);
    // Scans 0 and 1 are flagged and encoded here; 2–5 on the thread ahead, each once.
    let here = std::thread::current().id();
    let flagged = callers.lock().unwrap().clone();
    assert_eq!(flagged.len(), 6, "each scan flagged once");
    assert_eq!(flagged.iter().filter(|&&t| t != here).count(), 4);
    let encoded = ahead.matcher().matcher().encoders.lock().unwrap().clone();
    assert_eq!(encoded.len(), 6, "each scan encoded once");
    assert_eq!(encoded.iter().filter(|&&t| t != here).count(), 4);
    // An announced scan that does not come: its flags and features are not taken for another.
    let mut ahead = Odometry::new(EncodeAhead::new(DriveOracle::new(&unflagged)), config(true))
        .unwrap()
        .with_moving_objects(TallThings::new())
        .unwrap();
    let mut serial = Odometry::new(DriveOracle::new(&unflagged), config(true))
        .unwrap()
        .with_moving_objects(TallThings::new())
        .unwrap();
    for i in 0..4 {
        let announced = Scan::new(&scans[(i + 2) % 6]);
        assert_eq!(
            ahead
                .register_ahead(Scan::new(&scans[i]), Some(announced))
                .unwrap(),
            serial.register(Scan::new(&scans[i])).unwrap(),
            "scan {i}"
        );
    }
}
