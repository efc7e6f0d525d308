//! Encoding the next scan while the odometry registers this one.
//!
//! Of a frame's time the network takes a good part. Where the back end (matching stage, RANSAC, NDT)
//! does not keep every core busy — the odometry was given fewer threads than the machine has cores —
//! the next scan's encoding can use the idle ones; where every stage already runs on every core, there
//! is nothing to gain. [`EncodeAhead`] wraps a matcher so that [`Odometry::register_ahead`] can give it
//! the next scan: as soon as this scan's own features are in hand, the next scan is projected and
//! encoded on a thread of its own, beside this scan's back end, and the next call takes its features
//! from there. The poses are the serial loop's: features computed ahead are used only for a
//! bitwise-equal image (the odometry projects the scan again itself and compares), and an encoder gives
//! the same features for the same image whichever thread runs it.

use std::sync::mpsc::{channel, Receiver};
use std::sync::{Arc, Mutex, MutexGuard};

use nalgebra::Isometry3;

use super::reflectance::{detect_reflectance, normalised};
use super::scan_points::{kept_points, KeptPoints};
use super::{network_input, FrameMatcher, Odometry, Scan};
use crate::dense_match::DenseFlow;
use crate::error::Result;
use crate::odometry::config::{MatchingStage, ReflectanceScale};
use crate::odometry::moving::{moving_points, MovingObjectNetwork};
use crate::projection::{project, CylinderConfig};

/// A matcher that can encode the next scan ahead, on another thread ([`Odometry::register_ahead`]).
/// Everything else is the wrapped matcher's.
pub struct EncodeAhead<M: FrameMatcher> {
    matcher: Arc<M>,
    /// The next scan, waiting for this scan's features to be taken before it starts.
    pub(super) queued: Mutex<Option<NextScan>>,
    /// The next scan's flags, image and features, being computed.
    running: Mutex<Option<Receiver<Ahead<M::Features>>>>,
    /// The same once received, until `register` has taken what it needs.
    received: Mutex<Option<Ahead<M::Features>>>,
}

/// What the next scan's flags and image are made from, owned so that another thread can make them.
pub(super) struct NextScan {
    /// Its points as given.
    points: Vec<[f32; 4]>,
    /// The caller's moving flags, or the network (and its threshold) to find them.
    moving: NextMoving,
    scale: ReflectanceScale,
    min_points: usize,
    cylinder: CylinderConfig,
}

pub(super) enum NextMoving {
    Given(Option<Vec<bool>>),
    Detect(Arc<dyn MovingObjectNetwork + Send + Sync>, f64),
}

/// The next scan as prepared ahead: its points (to recognise it), the network's flags when it ran, and
/// its image and features (`None`: it will not be matched, or a step failed — `register` will say why).
struct Ahead<F> {
    points: Vec<[f32; 4]>,
    flags: Option<Vec<bool>>,
    encoded: Option<Encoded<F>>,
}

struct Encoded<F> {
    image: Vec<f32>,
    features: Result<F>,
}

impl NextScan {
    /// The flags, image and features `register` would compute for this scan.
    fn prepare<M: FrameMatcher>(self, matcher: &M) -> Ahead<M::Features> {
        let (flags, encoded) = match &self.moving {
            NextMoving::Given(given) => (None, self.encoded(matcher, given.as_deref())),
            NextMoving::Detect(network, threshold) => {
                match moving_points(network.as_ref(), &self.points, *threshold) {
                    Ok(flags) => {
                        let encoded = self.encoded(matcher, Some(&flags));
                        (Some(flags), encoded)
                    }
                    // `register` runs the network again and reports its error.
                    Err(_) => (None, None),
                }
            }
        };
        Ahead {
            flags,
            points: self.points,
            encoded,
        }
    }

    fn encoded<M: FrameMatcher>(
        &self,
        matcher: &M,
        moving: Option<&[bool]>,
    ) -> Option<Encoded<M::Features>> {
        let scan = Scan {
            moving,
            ..Scan::new(&self.points)
        };
        let KeptPoints { kept, .. } = kept_points(&scan).ok()?;
        if kept.len() < self.min_points {
            return None;
        }
        let projection = project(&normalised(kept, self.scale), &self.cylinder).ok()?;
        let image = network_input(&projection);
        let features = matcher.encode(&image);
        Some(Encoded { image, features })
    }
}

/// Whether two scans hold the same points, bit for bit (NaN coordinates included).
fn same_points(a: &[[f32; 4]], b: &[[f32; 4]]) -> bool {
    a.len() == b.len()
        && a.iter()
            .zip(b)
            .all(|(p, q)| p.iter().zip(q).all(|(x, y)| x.to_bits() == y.to_bits()))
}

impl<M> EncodeAhead<M>
where
    M: FrameMatcher + Send + Sync + 'static,
    M::Features: Send + 'static,
{
    /// `matcher`, ready to encode ahead.
    pub fn new(matcher: M) -> Self {
        EncodeAhead {
            matcher: Arc::new(matcher),
            queued: Mutex::new(None),
            running: Mutex::new(None),
            received: Mutex::new(None),
        }
    }

    /// The wrapped matcher.
    pub fn matcher(&self) -> &M {
        &self.matcher
    }

    /// Starts the queued scan, if any, on a thread of its own.
    fn start_queued(&self) {
        let Some(next) = locked(&self.queued).take() else {
            return;
        };
        let matcher = Arc::clone(&self.matcher);
        let (sender, receiver) = channel();
        std::thread::spawn(move || {
            // The receiver is gone when the odometry went on without these features.
            let _ = sender.send(next.prepare(matcher.as_ref()));
        });
        *locked(&self.running) = Some(receiver);
    }

    /// What was prepared ahead, waiting for it if need be; `None` when nothing was.
    fn take_ahead(&self) -> Option<Ahead<M::Features>> {
        if let Some(ahead) = locked(&self.received).take() {
            return Some(ahead);
        }
        let running = locked(&self.running).take()?;
        running.recv().ok()
    }
}

/// The lock, whether or not a thread panicked holding it: the slots hold plain data, whole either way.
fn locked<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl<M> FrameMatcher for EncodeAhead<M>
where
    M: FrameMatcher + Send + Sync + 'static,
    M::Features: Send + 'static,
{
    type Features = M::Features;

    fn cylinder(&self) -> &CylinderConfig {
        self.matcher.cylinder()
    }

    fn uses_reflectance(&self) -> bool {
        self.matcher.uses_reflectance()
    }

    fn encode(&self, image: &[f32]) -> Result<M::Features> {
        self.matcher.encode(image)
    }

    /// The features computed ahead when they are this image's (waiting for them if need be), else
    /// encoded now; then the queued scan starts.
    fn encode_scan(&self, image: &[f32]) -> Result<M::Features> {
        let features = match self.take_ahead().and_then(|ahead| ahead.encoded) {
            Some(encoded) if encoded.image == image => encoded.features,
            _ => self.matcher.encode_scan(image),
        };
        self.start_queued();
        features
    }

    /// The network's flags computed ahead when they are these points' (waiting for them if need be).
    fn moving_ahead(&self, points: &[[f32; 4]]) -> Option<Vec<bool>> {
        let ahead = self.take_ahead()?;
        let flags = if same_points(&ahead.points, points) {
            ahead.flags.clone()
        } else {
            None
        };
        *locked(&self.received) = Some(ahead);
        flags
    }

    fn flow(&self, reference: &M::Features, target: &M::Features) -> Result<DenseFlow> {
        self.matcher.flow(reference, target)
    }

    fn flow_of_cells(
        &self,
        reference: &M::Features,
        target: &M::Features,
        cells: &[bool],
    ) -> Result<DenseFlow> {
        self.matcher.flow_of_cells(reference, target, cells)
    }

    fn guided_flow_of_cells(
        &self,
        reference: &M::Features,
        target: &M::Features,
        cells: &[bool],
        expected: &[[f32; 2]],
    ) -> Result<Option<DenseFlow>> {
        self.matcher
            .guided_flow_of_cells(reference, target, cells, expected)
    }

    fn runs_matching_stage(&self, stage: MatchingStage) -> bool {
        self.matcher.runs_matching_stage(stage)
    }

    fn has_wide_window(&self) -> bool {
        self.matcher.has_wide_window()
    }

    fn wide_flow(
        &self,
        reference: &M::Features,
        target: &M::Features,
        target_image: &[f32],
    ) -> Result<DenseFlow> {
        self.matcher.wide_flow(reference, target, target_image)
    }
}

impl<M> Odometry<EncodeAhead<M>>
where
    M: FrameMatcher + Send + Sync + 'static,
    M::Features: Send + 'static,
{
    /// [`Odometry::register`] of `scan`, with `next` — the scan that will be registered after it —
    /// projected and encoded on another thread as soon as `scan`'s own features are in hand, so that
    /// the network's time for `next` overlaps `scan`'s back end. The poses, diagnostics and errors are
    /// `register`'s. `next` is encoded ahead only when its image can be known now: not before the
    /// reflectance scale is chosen (the first scan), not with `deskew.enabled` (the image depends on the
    /// velocity `scan` measures), and not when it would be skipped or switch to the range-only model;
    /// then `register(next)` encodes it as usual. With a moving-object network ([`Odometry::with_moving_objects`])
    /// and no `moving` mask, `next`'s points are flagged on that thread too, before it is encoded.
    pub fn register_ahead(
        &mut self,
        scan: Scan<'_>,
        next: Option<Scan<'_>>,
    ) -> Result<Isometry3<f64>> {
        let queued = next.and_then(|next| self.next_scan(&next));
        *locked(&self.matcher.queued) = queued;
        let result = self.register(scan);
        // Not started when `register` encoded nothing (a skipped scan, an error), and not taken when it
        // stopped between the flags and the features: nothing is left over.
        locked(&self.matcher.queued).take();
        locked(&self.matcher.received).take();
        result
    }

    /// What `next`'s image will be made from, when it can be known before the scan in between is
    /// registered.
    fn next_scan(&self, next: &Scan<'_>) -> Option<NextScan> {
        let scale = self.reflectance?;
        if self.config.deskew.enabled {
            return None;
        }
        let KeptPoints {
            kept,
            finite_reflectance,
            ..
        } = kept_points(next).ok()?;
        let min_points = self.config.min_points as usize;
        if kept.len() < min_points {
            return None;
        }
        let switches = scale != ReflectanceScale::Ignored
            && detect_reflectance(next.has_reflectance.then_some(&finite_reflectance[..])).0
                == ReflectanceScale::Ignored;
        if switches {
            return None;
        }
        let moving = match &self.moving_objects {
            Some(network) if next.moving.is_none() && self.config.moving_objects.detect => {
                NextMoving::Detect(Arc::clone(network), self.config.moving_objects.threshold)
            }
            _ => NextMoving::Given(next.moving.map(<[bool]>::to_vec)),
        };
        Some(NextScan {
            points: next.points.to_vec(),
            moving,
            scale,
            min_points,
            cylinder: self.cylinder,
        })
    }
}
