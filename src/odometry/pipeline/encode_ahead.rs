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

use nalgebra::Matrix4;

use super::reflectance::{detect_reflectance, normalised};
use super::scan_points::{kept_points, KeptPoints};
use super::{network_input, FrameMatcher, Odometry, Scan};
use crate::dense_match::DenseFlow;
use crate::error::Result;
use crate::odometry::config::{MatchingStage, ReflectanceScale};
use crate::projection::{project, CylinderConfig};

/// A matcher that can encode the next scan ahead, on another thread ([`Odometry::register_ahead`]).
/// Everything else is the wrapped matcher's.
pub struct EncodeAhead<M: FrameMatcher> {
    matcher: Arc<M>,
    /// The next scan, waiting for this scan's features to be taken before it starts.
    pub(super) queued: Mutex<Option<NextScan>>,
    /// The next scan's image and features, being computed.
    running: Mutex<Option<Running<M::Features>>>,
}

/// What the next scan's image is made from, owned so that another thread can make it.
pub(super) struct NextScan {
    /// Its kept points, reflectance on the model's scale.
    cloud: Vec<[f32; 4]>,
    cylinder: CylinderConfig,
}

/// The next scan being encoded: its image and features when done (`None`: its projection failed, and
/// `register` will report why).
type Running<F> = Receiver<Option<Encoded<F>>>;

struct Encoded<F> {
    image: Vec<f32>,
    features: Result<F>,
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
            let encoded = project(&next.cloud, &next.cylinder).ok().map(|projection| {
                let image = network_input(&projection);
                let features = matcher.encode(&image);
                Encoded { image, features }
            });
            // The receiver is gone when the odometry went on without these features.
            let _ = sender.send(encoded);
        });
        *locked(&self.running) = Some(receiver);
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
        let ahead = locked(&self.running)
            .take()
            .and_then(|running| running.recv().ok().flatten());
        let features = match ahead {
            Some(encoded) if encoded.image == image => encoded.features,
            _ => self.matcher.encode_scan(image),
        };
        self.start_queued();
        features
    }

    fn flow(&self, reference: &M::Features, target: &M::Features) -> Result<DenseFlow> {
        self.matcher.flow(reference, target)
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
    /// velocity `scan` measures), not when the moving-object network is to flag its points (give `next`
    /// its `moving` mask to have it encoded ahead), and not when it would be skipped or switch to the
    /// range-only model; then `register(next)` encodes it as usual.
    pub fn register_ahead(
        &mut self,
        scan: Scan<'_>,
        next: Option<Scan<'_>>,
    ) -> Result<Matrix4<f64>> {
        let queued = next.and_then(|next| self.next_scan(&next));
        *locked(&self.matcher.queued) = queued;
        let result = self.register(scan);
        // Not started when `register` encoded nothing (a skipped scan, an error): nothing is left over.
        locked(&self.matcher.queued).take();
        result
    }

    /// What `next`'s image will be made from, when it can be known before the scan in between is
    /// registered.
    fn next_scan(&self, next: &Scan<'_>) -> Option<NextScan> {
        let scale = self.reflectance?;
        if self.config.deskew.enabled {
            return None;
        }
        if self.moving_objects.is_some()
            && next.moving.is_none()
            && self.config.moving_objects.detect
        {
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
            && detect_reflectance(&finite_reflectance).0 == ReflectanceScale::Ignored;
        if switches {
            return None;
        }
        Some(NextScan {
            cloud: normalised(kept, scale),
            cylinder: self.cylinder,
        })
    }
}
