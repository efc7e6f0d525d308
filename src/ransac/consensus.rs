#![forbid(unsafe_code)]
//! A hypothesis's consensus: the matches in structure-of-arrays form, scored in `f32` lanes, the
//! minimal solve on three of them, and the order in which hypotheses win.

use std::cmp::Ordering;

use nalgebra::{Isometry3, Matrix3, Point3, Vector3};

use crate::rigid::{isometry_from_parts, Svd3};

/// Matches in structure-of-arrays form. Hypotheses are scored in `f32` in independent lanes, so the
/// loop vectorises; the minimal solves, the final refit and the RMSE use the `f64` points.
///
/// The `f32` columns hold each point relative to a reference point of its own set (`src_origin`,
/// `dst_origin`), and hypotheses are moved into that frame before scoring: `f32` rounds coordinates
/// in the millions of metres (georeferenced clouds, UTM) to whole metres, far above the threshold,
/// while the spread of the matches around their reference point stays small.
pub(super) struct Matches {
    src: [Vec<f32>; 3],
    dst: [Vec<f32>; 3],
    src_origin: Vector3<f64>,
    dst_origin: Vector3<f64>,
    pub(super) src64: Vec<Vector3<f64>>,
    pub(super) dst64: Vec<Vector3<f64>>,
    /// Each match's vote in a hypothesis's score; `None`: one each.
    votes: Option<Vec<f32>>,
}

/// The per-axis median of `points`: a reference point inside the bulk of the cloud that a few far
/// outliers do not drag away, as a mean would. `points` is not empty.
fn median_point(points: &[Point3<f64>]) -> Vector3<f64> {
    let middle = points.len() / 2;
    Vector3::from_fn(|k, _| {
        let mut values: Vec<f64> = points.iter().map(|p| p[k]).collect();
        *values.select_nth_unstable_by(middle, f64::total_cmp).1
    })
}

/// Lanes of the scoring loop.
const LANES: usize = 8;

/// A hypothesis as the scoring loop uses it: row-major rotation, then translation.
struct Hypothesis32 {
    r: [f32; 9],
    t: [f32; 3],
}

impl Hypothesis32 {
    /// `transform` (`dst ≈ T·src`) in the frame where source points are taken relative to
    /// `src_origin` and target points relative to `dst_origin`: the same rotation, the translation
    /// `R·src_origin + t − dst_origin` (formed in `f64`, so it is small and exact enough for `f32`).
    fn new(
        transform: &Isometry3<f64>,
        src_origin: &Vector3<f64>,
        dst_origin: &Vector3<f64>,
    ) -> Self {
        let r = transform.rotation.to_rotation_matrix().into_inner();
        let t = r * src_origin + transform.translation.vector - dst_origin;
        Hypothesis32 {
            r: [0, 1, 2, 3, 4, 5, 6, 7, 8].map(|k| r[(k / 3, k % 3)] as f32),
            t: [t.x as f32, t.y as f32, t.z as f32],
        }
    }

    #[inline(always)]
    fn distance_sq(&self, s: [f32; 3], d: [f32; 3]) -> f32 {
        let r = &self.r;
        let ex = r[0] * s[0] + r[1] * s[1] + r[2] * s[2] + self.t[0] - d[0];
        let ey = r[3] * s[0] + r[4] * s[1] + r[5] * s[2] + self.t[1] - d[1];
        let ez = r[6] * s[0] + r[7] * s[1] + r[8] * s[2] + self.t[2] - d[2];
        ex * ex + ey * ey + ez * ez
    }
}

impl Matches {
    /// `src` and `dst` are not empty.
    pub(super) fn new(src: &[Point3<f64>], dst: &[Point3<f64>], votes: Option<&[f64]>) -> Self {
        let (src_origin, dst_origin) = (median_point(src), median_point(dst));
        let column = |points: &[Point3<f64>], origin: &Vector3<f64>, k: usize| {
            points
                .iter()
                .map(|p| (p[k] - origin[k]) as f32)
                .collect::<Vec<f32>>()
        };
        Matches {
            src: [0, 1, 2].map(|k| column(src, &src_origin, k)),
            dst: [0, 1, 2].map(|k| column(dst, &dst_origin, k)),
            src_origin,
            dst_origin,
            src64: src.iter().map(|p| p.coords).collect(),
            dst64: dst.iter().map(|p| p.coords).collect(),
            votes: votes.map(|v| v.iter().map(|&w| w as f32).collect()),
        }
    }

    fn hypothesis32(&self, transform: &Isometry3<f64>) -> Hypothesis32 {
        Hypothesis32::new(transform, &self.src_origin, &self.dst_origin)
    }

    fn at(&self, i: usize) -> ([f32; 3], [f32; 3]) {
        (
            [self.src[0][i], self.src[1][i], self.src[2][i]],
            [self.dst[0][i], self.dst[1][i], self.dst[2][i]],
        )
    }

    /// (summed votes of the inliers, their count, their summed squared distance).
    pub(super) fn score(&self, transform: &Isometry3<f64>, threshold_sq: f64) -> Score {
        let h = self.hypothesis32(transform);
        let threshold_sq = threshold_sq as f32;
        let n = self.src[0].len();
        let full = n - n % LANES;
        let mut counts = [0u32; LANES];
        let mut sums = [0.0f32; LANES];
        let mut errors = [0.0f32; LANES];
        let [sx, sy, sz] = &self.src;
        let [dx, dy, dz] = &self.dst;
        let no_votes = [1.0f32; LANES];
        for base in (0..full).step_by(LANES) {
            let (sx, sy, sz) = (
                &sx[base..base + LANES],
                &sy[base..base + LANES],
                &sz[base..base + LANES],
            );
            let (dx, dy, dz) = (
                &dx[base..base + LANES],
                &dy[base..base + LANES],
                &dz[base..base + LANES],
            );
            let votes = self
                .votes
                .as_ref()
                .map_or(&no_votes[..], |v| &v[base..base + LANES]);
            for l in 0..LANES {
                let d = h.distance_sq([sx[l], sy[l], sz[l]], [dx[l], dy[l], dz[l]]);
                let inlier = d < threshold_sq;
                counts[l] += inlier as u32;
                sums[l] += if inlier { votes[l] } else { 0.0 };
                errors[l] += if inlier { d } else { 0.0 };
            }
        }
        let mut count = counts.iter().map(|&c| c as usize).sum::<usize>();
        let mut votes = sums.iter().map(|&v| v as f64).sum::<f64>();
        let mut error = errors.iter().map(|&e| e as f64).sum::<f64>();
        for i in full..n {
            let (s, d) = self.at(i);
            let d = h.distance_sq(s, d);
            if d < threshold_sq {
                count += 1;
                votes += self.votes.as_ref().map_or(1.0, |v| v[i] as f64);
                error += d as f64;
            }
        }
        Score {
            votes,
            count,
            error,
        }
    }

    /// The inlier mask, decided exactly as [`Matches::score`] counts.
    pub(super) fn inlier_mask(&self, transform: &Isometry3<f64>, threshold_sq: f64) -> Vec<bool> {
        let h = self.hypothesis32(transform);
        (0..self.src[0].len())
            .map(|i| {
                let (s, d) = self.at(i);
                h.distance_sq(s, d) < threshold_sq as f32
            })
            .collect()
    }

    /// The inlier mask of [`Refit::RayNoise`](super::Refit::RayNoise): `(a/τ)² + (c/τ_c)² < 1` for
    /// the error's components `a` along the target's ray and `c` across it, `τ = threshold`,
    /// `τ_c = max(τ, r·bearing_tan)`.
    pub(super) fn ray_inlier_mask(
        &self,
        transform: &Isometry3<f64>,
        threshold: f64,
        bearing_tan: f64,
    ) -> Vec<bool> {
        self.src64
            .iter()
            .zip(&self.dst64)
            .map(|(p, q)| {
                let error = (transform * Point3::from(*p)).coords - q;
                let range = q.norm();
                let along = error.dot(q) / range;
                let across_sq = (error.norm_squared() - along * along).max(0.0);
                let across_threshold = threshold.max(range * bearing_tan);
                (along / threshold).powi(2) + across_sq / (across_threshold * across_threshold)
                    < 1.0
            })
            .collect()
    }

    fn point(&self, i: usize) -> (Vector3<f64>, Vector3<f64>) {
        (self.src64[i], self.dst64[i])
    }

    /// The rigid solve on three matches; `None` when they are (nearly) collinear.
    pub(super) fn minimal_solve(
        &self,
        sample: [usize; 3],
        svd: &mut Svd3,
    ) -> Option<Isometry3<f64>> {
        let pairs = sample.map(|i| self.point(i));
        let p_mean = (pairs[0].0 + pairs[1].0 + pairs[2].0) / 3.0;
        let q_mean = (pairs[0].1 + pairs[1].1 + pairs[2].1) / 3.0;
        let mut h = Matrix3::zeros();
        for (p, q) in &pairs {
            h += (p - p_mean) * (q - q_mean).transpose();
        }
        let rotation = svd.rotation_from_cross_covariance(&h)?;
        Some(isometry_from_parts(
            &rotation,
            &(q_mean - rotation * p_mean),
        ))
    }
}

/// A hypothesis's consensus: the summed votes of its inliers (their count when matches carry no votes),
/// how many they are, and their summed squared distance.
#[derive(Debug, Clone, Copy)]
pub(super) struct Score {
    pub(super) votes: f64,
    pub(super) count: usize,
    error: f64,
}

/// (score, hypothesis index): `a` better than `b`? More votes, then a lower error, then the earlier.
pub(super) fn is_better(a: (Score, usize), b: (Score, usize)) -> bool {
    match a.0.votes.total_cmp(&b.0.votes) {
        Ordering::Greater => true,
        Ordering::Less => false,
        Ordering::Equal => match a.0.error.total_cmp(&b.0.error) {
            Ordering::Less => true,
            Ordering::Greater => false,
            Ordering::Equal => a.1 < b.1,
        },
    }
}
