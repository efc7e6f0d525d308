//! # dmlo_rs — the geometry core of DMLO (Deep Matching LiDAR Odometry)
//!
//! Everything geometric and hot in the DMLO pipeline (Li & Wang), usable from Rust without Python:
//!
//! | module | paper | what |
//! |---|---|---|
//! | [`projection`] | Eq. 1, 4 | cylinder image of a scan and its inverse Φ⁻¹ |
//! | [`ground_truth`] | Eq. 5–8 | per-cell training flow and validity for a pair with known motion |
//! | [`dense_match`] | Eq. 2, 3, 11 | the network's matching stage on cached features (CPU) |
//! | [`matches`](mod@matches) | §III-D | network output (flow + confidence) → 3D point pairs |
//! | [`coherence`] | — | confidence weighted by how well a match agrees with its neighbours |
//! | [`deskew`] | — | motion compensation of a spinning sensor's sweep (constant velocity) |
//! | [`nms`] | §III-D-a | greedy non-maximum suppression on the cylinder grid |
//! | [`rigid`] | Eq. 12–14 | closed-form weighted rigid solve (faer SVD, reflection fixed) |
//! | [`surface`] | — | the tilt of the surface under a match: its vote for a horizontal motion |
//! | [`projective`] | — | projective point-to-plane ICP of a pair that barely moved |
//! | [`pair`] | §III-D | one pair's motion from the flow: coherence, decoding with NMS, votes, RANSAC |
//! | [`ransac`] | §III-D-b | seeded RANSAC with rayon-parallel hypothesis scoring |
//! | [`ray_noise`] | — | Gauss–Newton refit weighing each match by its ray's bearing and range noise |
//! | [`ndt`] | §III-D-c | scan-to-map NDT refinement |
//! | [`odometry`] | §III | the odometry's loop over scans (`Odometry`), its config, the frame clock, the motion model and its judgement, the local map |
//! | [`raycast`] | — | the LiDAR simulator's ray casting |
//! | [`scan_file`] | — | KITTI's `.bin` scans read from disk |
//! | `inference` | §III-C | the network's encoder run by tract (feature `inference`) or onnxruntime (feature `onnxruntime`), and the learned matcher |
//!
//! Conventions: LiDAR frame x forward, y left, z up; a scan is `N×4` `f32` (x, y, z, reflectance);
//! transforms are named by frames, `T_tgt_ref` maps reference points into the target frame
//! (`p_t = T p_r`, Eq. 7). Angles in public configs are degrees.
//!
//! The Python bindings (`import dmlo_rs`) live in the `python` module behind the `python` cargo
//! feature, which maturin enables.

pub mod coherence;
pub mod dense_match;
pub mod deskew;
pub mod error;
pub mod ground_truth;
pub mod inference;
pub mod matches;
pub mod ndt;
pub mod nms;
pub mod odometry;
pub mod pair;
pub mod projection;
pub mod projective;
pub mod ransac;
pub mod ray_noise;
pub mod raycast;
pub mod rigid;
pub mod scan_file;
pub mod surface;
#[cfg(test)]
mod test_scenes;

pub use error::{Error, Result};

#[cfg(feature = "python")]
mod python;
