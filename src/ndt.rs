#![forbid(unsafe_code)]
//! Scan-to-map NDT refinement (paper §III-D-c: "we maintain a local submap accumulated by previous scans
//! and refine the pose by a scan-to-map NDT").
//!
//! Magnusson's point-to-distribution NDT (*The Three-Dimensional Normal-Distributions Transform*, 2009):
//!
//! - [`NdtMap`] — the local submap: a sliding window over the most recent `max_scans` scans (world
//!   coordinates), voxelised into normal distributions with regularised covariances, updated
//!   incrementally on every [`NdtMap::insert`] ([`map`]).
//! - [`NdtMap::align`] — Newton's method on the NDT score with its analytic gradient and Hessian
//!   ([`score`]), a step-length limit and a backtracking line search ([`align`]); the source scan is
//!   thinned by a voxel-grid filter first ([`voxel`]). Directions the map does not constrain (found by an
//!   eigen-analysis of the information at the initial pose) keep their initial value (Zhang, Kaess &
//!   Singh 2016). Returns `T_map_source` in an [`NdtResult`].
//!
//! ```
//! use dmlo_rs::ndt::{NdtAlignConfig, NdtMap, NdtMapConfig};
//! use nalgebra::{Isometry3, Point3, Vector3};
//!
//! // A corner of three walls, sampled on a grid, as the map …
//! let mut wall = Vec::new();
//! for i in 0..60 {
//!     for j in 0..60 {
//!         let (u, v) = (0.05 + i as f64 * 0.1, 0.05 + j as f64 * 0.1);
//!         wall.extend([Point3::new(u, v, 0.3), Point3::new(u, 0.3, v), Point3::new(0.3, u, v)]);
//!     }
//! }
//! let mut map = NdtMap::new(NdtMapConfig::default())?;
//! map.insert(&wall)?;
//! // … and the same walls seen from a sensor moved by 10 cm.
//! let truth = Isometry3::new(Vector3::new(0.1, 0.0, 0.0), Vector3::zeros());
//! let scan: Vec<Point3<f64>> = wall.iter().map(|p| truth.inverse_transform_point(p)).collect();
//! let result = map.align(&scan, &Isometry3::identity(), &NdtAlignConfig::default())?;
//! assert!((result.transform.translation.vector - truth.translation.vector).norm() < 0.01);
//! # Ok::<(), dmlo_rs::Error>(())
//! ```

pub mod align;
pub mod map;
pub mod score;
pub mod voxel;

pub use align::{isometry_from_matrix4, NdtAlignConfig, NdtResult};
pub use map::{NdtMap, NdtMapConfig};
pub use score::NeighbourSearch;
