#![forbid(unsafe_code)]
//! Voxels of the NDT map: integer keys, per-voxel point statistics and the normal distribution fitted to
//! them (Magnusson 2009, §6.1), and the voxel-grid filter used to thin the source scan.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use nalgebra::{Matrix3, Point3, SymmetricEigen, Vector3};

/// Keys beyond this magnitude are refused so that `floor(x / voxel_size)` always fits an `i32`.
const MAX_KEY: f64 = (1u32 << 30) as f64;

/// Integer coordinates of a voxel: the voxel `[k·s, (k+1)·s)` along each axis for voxel size `s`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct VoxelKey(pub [i32; 3]);

impl VoxelKey {
    /// The voxel containing `point`, or `None` when the point is not finite or too far from the origin
    /// for an `i32` key.
    pub fn containing(point: &Point3<f64>, inverse_voxel_size: f64) -> Option<Self> {
        let mut key = [0i32; 3];
        for (axis, slot) in key.iter_mut().enumerate() {
            let scaled = (point[axis] * inverse_voxel_size).floor();
            // NaN is neither less nor greater: refused too.
            if scaled.abs().partial_cmp(&MAX_KEY) != Some(std::cmp::Ordering::Less) {
                return None;
            }
            *slot = scaled as i32;
        }
        Some(VoxelKey(key))
    }

    /// The key shifted by `offset` voxels.
    pub fn offset(self, offset: [i32; 3]) -> Self {
        let [x, y, z] = self.0;
        VoxelKey([x + offset[0], y + offset[1], z + offset[2]])
    }

    /// The voxel's minimum corner: the local origin of its statistics.
    pub fn corner(self, voxel_size: f64) -> Vector3<f64> {
        Vector3::new(self.0[0] as f64, self.0[1] as f64, self.0[2] as f64) * voxel_size
    }
}

/// A small fixed hasher for voxel keys (FxHash's multiply-rotate). The std SipHash is several times slower
/// on three `i32`s, and no result depends on the iteration order of the maps, so a fixed seed is fine.
#[derive(Default, Clone, Copy)]
pub struct VoxelHasher(u64);

impl Hasher for VoxelHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &byte in bytes {
            self.write_u64(u64::from(byte));
        }
    }

    fn write_i32(&mut self, value: i32) {
        self.write_u64(value as u32 as u64);
    }

    fn write_u64(&mut self, value: u64) {
        self.0 = (self.0.rotate_left(5) ^ value).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }
}

/// A hash map keyed by voxel.
pub type VoxelMap<V> = HashMap<VoxelKey, V, BuildHasherDefault<VoxelHasher>>;

/// Sufficient statistics of the points in one voxel: count, sum and sum of outer products, all taken
/// relative to the voxel's corner so that the sums stay well conditioned far from the world origin and
/// survive the subtraction of an evicted scan with no visible loss of precision.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VoxelStats {
    pub count: u64,
    pub sum: Vector3<f64>,
    pub sum_outer: Matrix3<f64>,
}

impl Default for VoxelStats {
    fn default() -> Self {
        VoxelStats {
            count: 0,
            sum: Vector3::zeros(),
            sum_outer: Matrix3::zeros(),
        }
    }
}

impl VoxelStats {
    /// Adds one point given relative to the voxel's corner.
    pub fn add_local(&mut self, local: &Vector3<f64>) {
        self.count += 1;
        self.sum += local;
        self.sum_outer += local * local.transpose();
    }

    /// Adds the statistics of another set of points of the same voxel.
    pub fn merge(&mut self, other: &VoxelStats) {
        self.count += other.count;
        self.sum += other.sum;
        self.sum_outer += other.sum_outer;
    }

    /// Removes statistics previously merged in. The caller guarantees `other` is part of `self`.
    pub fn unmerge(&mut self, other: &VoxelStats) {
        self.count -= other.count;
        self.sum -= other.sum;
        self.sum_outer -= other.sum_outer;
    }

    /// The normal distribution of the voxel, or `None` with fewer than `min_points` points or when the
    /// points do not spread at all. Small eigenvalues of the covariance are raised to
    /// `min_eigenvalue_ratio` times the largest (Magnusson 2009, §6.2; PCL's `min_covar_eigvalue_mult`),
    /// so that points on a plane or a line still give an invertible covariance.
    pub fn gaussian(
        &self,
        corner: &Vector3<f64>,
        min_points: usize,
        min_eigenvalue_ratio: f64,
    ) -> Option<Gaussian> {
        if self.count < min_points as u64 || self.count < 2 {
            return None;
        }
        let n = self.count as f64;
        let local_mean = self.sum / n;
        let covariance = (self.sum_outer - local_mean * self.sum.transpose()) / (n - 1.0);
        let covariance = (covariance + covariance.transpose()) * 0.5;
        let eigen = SymmetricEigen::new(covariance);
        let largest = eigen.eigenvalues.max();
        if !(largest.is_finite() && largest > 1e-12) {
            return None;
        }
        let floor = largest * min_eigenvalue_ratio;
        let inverse_eigenvalues = eigen.eigenvalues.map(|value| 1.0 / value.max(floor));
        let inverse_covariance = eigen.eigenvectors
            * Matrix3::from_diagonal(&inverse_eigenvalues)
            * eigen.eigenvectors.transpose();
        Some(Gaussian {
            mean: Point3::from(corner + local_mean),
            inverse_covariance,
        })
    }
}

/// The normal distribution fitted to the points of one voxel, as the score needs it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Gaussian {
    /// Mean in map coordinates.
    pub mean: Point3<f64>,
    /// Inverse of the regularised covariance.
    pub inverse_covariance: Matrix3<f64>,
}

/// Per-voxel statistics of a set of points, plus the voxel keys in order of first appearance so that
/// anything iterating over the result is deterministic.
pub fn voxel_statistics(
    points: &[Point3<f64>],
    voxel_size: f64,
) -> (Vec<VoxelKey>, VoxelMap<VoxelStats>) {
    let inverse = 1.0 / voxel_size;
    let mut order = Vec::new();
    let mut stats: VoxelMap<VoxelStats> = VoxelMap::default();
    for point in points {
        let Some(key) = VoxelKey::containing(point, inverse) else {
            continue;
        };
        let local = point.coords - key.corner(voxel_size);
        stats
            .entry(key)
            .or_insert_with(|| {
                order.push(key);
                VoxelStats::default()
            })
            .add_local(&local);
    }
    (order, stats)
}

/// Voxel-grid filter: the centroid of the points in each occupied voxel, in order of first appearance.
/// A `voxel_size` of zero returns the points unchanged.
pub fn voxel_downsample(points: &[Point3<f64>], voxel_size: f64) -> Vec<Point3<f64>> {
    if voxel_size <= 0.0 {
        return points.to_vec();
    }
    let (order, stats) = voxel_statistics(points, voxel_size);
    order
        .iter()
        .map(|key| {
            let voxel = &stats[key];
            Point3::from(key.corner(voxel_size) + voxel.sum / voxel.count as f64)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_floor_negative_coordinates() {
        assert_eq!(
            VoxelKey::containing(&Point3::new(-0.1, 0.0, 1.99), 1.0),
            Some(VoxelKey([-1, 0, 1]))
        );
        assert_eq!(
            VoxelKey::containing(&Point3::new(f64::NAN, 0.0, 0.0), 1.0),
            None
        );
        assert_eq!(
            VoxelKey::containing(&Point3::new(1e12, 0.0, 0.0), 1.0),
            None
        );
    }

    #[test]
    fn gaussian_matches_direct_mean_and_covariance_far_from_origin() {
        let offset = Vector3::new(1.0e5, -2.0e5, 30.0);
        let locals = [
            [0.1, 0.2, 0.3],
            [0.9, 0.1, 0.5],
            [0.4, 0.8, 0.2],
            [0.5, 0.5, 0.9],
            [0.2, 0.3, 0.6],
        ];
        let points: Vec<Point3<f64>> = locals
            .iter()
            .map(|p| Point3::from(Vector3::new(p[0], p[1], p[2]) + offset))
            .collect();
        let (order, stats) = voxel_statistics(&points, 1.0);
        assert_eq!(order.len(), 1);
        let gaussian = stats[&order[0]]
            .gaussian(&order[0].corner(1.0), 5, 1e-9)
            .unwrap();
        let mean = points
            .iter()
            .fold(Vector3::zeros(), |acc, p| acc + p.coords)
            / 5.0;
        let mut covariance = Matrix3::zeros();
        for p in &points {
            let d = p.coords - mean;
            covariance += d * d.transpose() / 4.0;
        }
        assert!((gaussian.mean.coords - mean).norm() < 1e-9);
        let identity = gaussian.inverse_covariance * covariance;
        assert!((identity - Matrix3::identity()).norm() < 1e-6, "{identity}");
    }

    #[test]
    fn planar_voxel_is_regularised_and_sparse_voxel_skipped() {
        let points: Vec<Point3<f64>> = (0..10)
            .map(|i| Point3::new(0.05 + 0.09 * i as f64, 0.5 + 0.04 * (i % 3) as f64, 0.5))
            .collect();
        let (order, stats) = voxel_statistics(&points, 1.0);
        let voxel = &stats[&order[0]];
        let gaussian = voxel.gaussian(&order[0].corner(1.0), 5, 0.01).unwrap();
        assert!(gaussian.inverse_covariance.iter().all(|v| v.is_finite()));
        assert!(voxel.gaussian(&order[0].corner(1.0), 11, 0.01).is_none());
    }

    #[test]
    fn unmerge_restores_statistics() {
        let mut a = VoxelStats::default();
        a.add_local(&Vector3::new(0.1, 0.2, 0.3));
        let mut b = VoxelStats::default();
        b.add_local(&Vector3::new(0.7, 0.4, 0.9));
        let mut total = a;
        total.merge(&b);
        total.unmerge(&a);
        assert_eq!(total.count, 1);
        assert!((total.sum - b.sum).norm() < 1e-15);
    }

    #[test]
    fn downsample_returns_centroids_in_first_seen_order() {
        let points = [
            Point3::new(1.2, 0.1, 0.1),
            Point3::new(0.2, 0.2, 0.2),
            Point3::new(1.4, 0.3, 0.3),
        ];
        let thinned = voxel_downsample(&points, 1.0);
        assert_eq!(thinned.len(), 2);
        assert!((thinned[0] - Point3::new(1.3, 0.2, 0.2)).norm() < 1e-12);
        assert!((thinned[1] - points[1]).norm() < 1e-12);
    }
}
