#![forbid(unsafe_code)]
//! The odometry: its loop over scans ([`pipeline::Odometry`], over any [`pipeline::FrameMatcher`]), its
//! settings, declared once ([`config`]), and the per-frame state the loop runs on: the
//! frame clock that counts missing scans from the timestamps ([`clock`]), the constant-velocity motion model
//! with the judgement of every pair's motion against it (§III-D-c, [`motion`]), and the local map that
//! refines every pose by scan-to-map NDT (§III-D-c, [`mapping`]), and the moving-object network's rule for the
//! points it leaves out ([`moving`]).
//!
//! ```
//! use dmlo_rs::odometry::motion::{MotionLimits, MotionModel, PairEvidence};
//! use nalgebra::Matrix4;
//!
//! let mut model = MotionModel::new(MotionLimits::default());
//! let mut step = Matrix4::identity();
//! step[(0, 3)] = -1.0; // T_tgt_ref of a car driving 1 m forward a frame
//! let judged = model.judge(&PairEvidence::new(step, 200, None, &[], &[]), &model.predicted(1), 1);
//! assert!(judged.fallback.is_none()); // no velocity measured yet: nothing to judge against
//! let pose = step.try_inverse().unwrap();
//! model.update(&Matrix4::identity(), &pose, 1);
//! assert_eq!(model.predicted(2)[(0, 3)], -2.0);
//! ```

pub mod clock;
pub mod config;
pub mod mapping;
pub mod motion;
pub mod moving;
pub mod pipeline;

pub use config::OdometryConfig;
pub use motion::Fallback;
pub use moving::MovingObjectNetwork;
pub use pipeline::{
    EncodeAhead, FrameDiagnostics, FrameMatcher, Notice, Odometry, RegisteredPair, Scan,
};

#[cfg(test)]
mod tests;
