#![forbid(unsafe_code)]
//! Voxels of the NDT map: integer keys, per-voxel point statistics and the normal distribution fitted to
//! them (Magnusson 2009, §6.1), and the voxel-grid filter used to thin the source scan.

use std::collections::hash_map::Entry;
use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hash, Hasher};

use nalgebra::{Matrix3, Point3, SymmetricEigen, Vector3};
use rayon::prelude::*;

/// Keys beyond this magnitude are refused so that `floor(x / voxel_size)` always fits an `i32`.
const MAX_KEY: f64 = (1u32 << 30) as f64;

/// Integer coordinates of a voxel: the voxel `[k·s, (k+1)·s)` along each axis for voxel size `s`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
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

impl Hash for VoxelKey {
    /// Two words instead of the derived slice hash (a length and 12 single bytes, each a round of the
    /// hasher below): hashing was most of the voxel-grid filter's time.
    fn hash<H: Hasher>(&self, state: &mut H) {
        let [x, y, z] = self.0;
        state.write_u64((u64::from(x as u32) << 32) | u64::from(y as u32));
        state.write_u64(u64::from(z as u32));
    }
}

/// A small fixed hasher for voxel keys (FxHash's multiply-rotate per word, then MurmurHash3's 64-bit
/// finaliser so that every key bit reaches the low bits the table indexes by). The std SipHash is several
/// times slower on three `i32`s, and no result depends on the iteration order of the maps, so a fixed
/// seed is fine.
#[derive(Default, Clone, Copy)]
pub struct VoxelHasher(u64);

impl Hasher for VoxelHasher {
    fn finish(&self) -> u64 {
        let mut h = self.0;
        h ^= h >> 33;
        h = h.wrapping_mul(0xff51_afd7_ed55_8ccd);
        h ^= h >> 33;
        h = h.wrapping_mul(0xc4ce_b9fe_1a85_ec53);
        h ^ (h >> 33)
    }

    fn write(&mut self, bytes: &[u8]) {
        for &byte in bytes {
            self.write_u64(u64::from(byte));
        }
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

/// The map's distributions: a key → slot table over a dense array, so that the score can remember where a
/// point's neighbours are as four-byte slots.
#[derive(Clone, Debug, Default)]
pub struct Distributions {
    slots: VoxelMap<u32>,
    keys: Vec<VoxelKey>,
    gaussians: Vec<Gaussian>,
}

impl Distributions {
    /// The distribution of voxel `key`, if it has one.
    pub fn get(&self, key: &VoxelKey) -> Option<&Gaussian> {
        self.slot(key).map(|slot| self.by_slot(slot))
    }

    /// Where the distribution of `key` is stored, if it has one; valid until the next change.
    pub fn slot(&self, key: &VoxelKey) -> Option<u32> {
        self.slots.get(key).copied()
    }

    /// The distribution stored at `slot` (from [`slot`](Self::slot)).
    pub fn by_slot(&self, slot: u32) -> &Gaussian {
        &self.gaussians[slot as usize]
    }

    /// Sets (or replaces) the distribution of `key`.
    pub fn insert(&mut self, key: VoxelKey, gaussian: Gaussian) {
        match self.slots.entry(key) {
            Entry::Occupied(entry) => self.gaussians[*entry.get() as usize] = gaussian,
            Entry::Vacant(entry) => {
                let slot = u32::try_from(self.gaussians.len())
                    .expect("fewer than 2³² distributions (a voxel key holds 30 bits per axis)");
                entry.insert(slot);
                self.keys.push(key);
                self.gaussians.push(gaussian);
            }
        }
    }

    /// Removes the distribution of `key` (the last one moves into its slot).
    pub fn remove(&mut self, key: &VoxelKey) {
        let Some(slot) = self.slots.remove(key) else {
            return;
        };
        let slot = slot as usize;
        self.keys.swap_remove(slot);
        self.gaussians.swap_remove(slot);
        if let Some(moved) = self.keys.get(slot) {
            self.slots.insert(*moved, slot as u32);
        }
    }

    pub fn len(&self) -> usize {
        self.gaussians.len()
    }

    pub fn is_empty(&self) -> bool {
        self.gaussians.is_empty()
    }

    pub fn clear(&mut self) {
        self.slots.clear();
        self.keys.clear();
        self.gaussians.clear();
    }

    /// Every voxel with its distribution, in no particular order.
    pub fn iter(&self) -> impl Iterator<Item = (&VoxelKey, &Gaussian)> {
        self.keys.iter().zip(&self.gaussians)
    }
}

impl PartialEq for Distributions {
    /// The same voxels with the same distributions, whatever the order they were inserted in.
    fn eq(&self, other: &Self) -> bool {
        self.len() == other.len()
            && self
                .iter()
                .all(|(key, gaussian)| other.get(key) == Some(gaussian))
    }
}

/// Points per chunk of the parallel accumulation below. Fixed, so the grouping of the sums (and with it
/// every bit of the result) does not depend on the number of threads.
const ACCUMULATION_CHUNK: usize = 16_384;

/// What a voxel accumulates of its points (given relative to the voxel's corner).
trait Accumulator: Default + Send {
    fn add_local(&mut self, local: &Vector3<f64>);
    fn merge(&mut self, other: &Self);
}

impl Accumulator for VoxelStats {
    fn add_local(&mut self, local: &Vector3<f64>) {
        VoxelStats::add_local(self, local);
    }

    fn merge(&mut self, other: &Self) {
        VoxelStats::merge(self, other);
    }
}

/// Count and sum only: all the voxel-grid filter needs (the outer products would double its cost).
#[derive(Default)]
struct Centroid {
    count: u64,
    sum: Vector3<f64>,
}

impl Accumulator for Centroid {
    fn add_local(&mut self, local: &Vector3<f64>) {
        self.count += 1;
        self.sum += local;
    }

    fn merge(&mut self, other: &Self) {
        self.count += other.count;
        self.sum += other.sum;
    }
}

/// What each voxel accumulated, in the order its first point came (`values[i]` is `keys[i]`'s), and where
/// each key's value lies: merged and read by index, no voxel is looked up by key once it is in.
struct Accumulated<A> {
    keys: Vec<VoxelKey>,
    values: Vec<A>,
    slots: VoxelMap<usize>,
}

impl<A: Accumulator> Accumulated<A> {
    fn new() -> Self {
        Accumulated {
            keys: Vec::new(),
            values: Vec::new(),
            slots: VoxelMap::default(),
        }
    }

    /// The accumulator of `key`, appended (empty) when the key is new.
    fn entry(&mut self, key: VoxelKey) -> &mut A {
        let index = match self.slots.entry(key) {
            Entry::Occupied(slot) => *slot.get(),
            Entry::Vacant(slot) => {
                slot.insert(self.values.len());
                self.keys.push(key);
                self.values.push(A::default());
                self.values.len() - 1
            }
        };
        &mut self.values[index]
    }

    /// Adds what another part of the points accumulated for `key`.
    fn merge(&mut self, key: VoxelKey, value: A) {
        match self.slots.entry(key) {
            Entry::Occupied(slot) => self.values[*slot.get()].merge(&value),
            Entry::Vacant(slot) => {
                slot.insert(self.values.len());
                self.keys.push(key);
                self.values.push(value);
            }
        }
    }

    fn into_pairs(self) -> impl Iterator<Item = (VoxelKey, A)> {
        self.keys.into_iter().zip(self.values)
    }
}

fn accumulate_chunk<A: Accumulator>(points: &[Point3<f64>], voxel_size: f64) -> Accumulated<A> {
    let inverse = 1.0 / voxel_size;
    let mut accumulated = Accumulated::<A>::new();
    for point in points {
        let Some(key) = VoxelKey::containing(point, inverse) else {
            continue;
        };
        let local = point.coords - key.corner(voxel_size);
        accumulated.entry(key).add_local(&local);
    }
    accumulated
}

/// Chunks accumulated in parallel, then merged in chunk order: the keys keep the order in which a single
/// pass would first have met them, whatever the number of threads.
fn accumulate<A: Accumulator>(points: &[Point3<f64>], voxel_size: f64) -> Accumulated<A> {
    let mut chunks = points
        .par_chunks(ACCUMULATION_CHUNK)
        .map(|chunk| accumulate_chunk::<A>(chunk, voxel_size))
        .collect::<Vec<_>>()
        .into_iter();
    let Some(mut accumulated) = chunks.next() else {
        return Accumulated::new();
    };
    for chunk in chunks {
        for (key, value) in chunk.into_pairs() {
            accumulated.merge(key, value);
        }
    }
    accumulated
}

/// Per-voxel statistics of a set of points, each voxel once, in order of first appearance so that
/// anything iterating over the result is deterministic. Parallel over chunks of points; the result does
/// not depend on the number of threads.
pub fn voxel_statistics(points: &[Point3<f64>], voxel_size: f64) -> Vec<(VoxelKey, VoxelStats)> {
    accumulate(points, voxel_size).into_pairs().collect()
}

/// Voxel-grid filter: the centroid of the points in each occupied voxel, in order of first appearance.
/// A `voxel_size` of zero returns the points unchanged. Parallel like [`voxel_statistics`].
pub fn voxel_downsample(points: &[Point3<f64>], voxel_size: f64) -> Vec<Point3<f64>> {
    if voxel_size <= 0.0 {
        return points.to_vec();
    }
    accumulate::<Centroid>(points, voxel_size)
        .into_pairs()
        .map(|(key, centroid)| {
            Point3::from(key.corner(voxel_size) + centroid.sum / centroid.count as f64)
        })
        .collect()
}

/// [`voxel_downsample`] by a voxel of `near_size` within `range` of the origin and of `far_size` beyond
/// it: the near points' centroids first, then the far points'. An infinite `range` is `voxel_downsample`
/// by `near_size`.
pub fn range_voxel_downsample(
    points: &[Point3<f64>],
    near_size: f64,
    range: f64,
    far_size: f64,
) -> Vec<Point3<f64>> {
    if range.is_infinite() {
        return voxel_downsample(points, near_size);
    }
    let (near, far): (Vec<Point3<f64>>, Vec<Point3<f64>>) = points
        .iter()
        .partition(|point| point.coords.norm() <= range);
    let mut thinned = voxel_downsample(&near, near_size);
    thinned.extend(voxel_downsample(&far, far_size));
    thinned
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
        let stats = voxel_statistics(&points, 1.0);
        assert_eq!(stats.len(), 1);
        let (key, voxel) = &stats[0];
        let gaussian = voxel.gaussian(&key.corner(1.0), 5, 1e-9).unwrap();
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
        let stats = voxel_statistics(&points, 1.0);
        let (key, voxel) = &stats[0];
        let gaussian = voxel.gaussian(&key.corner(1.0), 5, 0.01).unwrap();
        assert!(gaussian.inverse_covariance.iter().all(|v| v.is_finite()));
        assert!(voxel.gaussian(&key.corner(1.0), 11, 0.01).is_none());
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

    fn distribution(value: f64) -> Gaussian {
        Gaussian {
            mean: Point3::new(value, 0.0, 0.0),
            inverse_covariance: Matrix3::identity() * value,
        }
    }

    #[test]
    fn distributions_keep_every_key_right_through_replacements_and_removals() {
        let key = |i: i32| VoxelKey([i, -i, 2 * i]);
        let mut forwards = Distributions::default();
        for i in 0..6 {
            forwards.insert(key(i), distribution(f64::from(i)));
        }
        forwards.insert(key(2), distribution(20.0));
        // Removing the first, a middle and the last slot moves others into the holes.
        for i in [0, 3, 5, 9] {
            forwards.remove(&key(i));
        }
        assert_eq!(forwards.len(), 3);
        for (i, expected) in [
            (1, Some(1.0)),
            (2, Some(20.0)),
            (4, Some(4.0)),
            (0, None),
            (3, None),
            (5, None),
        ] {
            assert_eq!(forwards.get(&key(i)).map(|g| g.mean.x), expected, "key {i}");
        }
        let mut backwards = Distributions::default();
        for (i, value) in [(4, 4.0), (2, 20.0), (1, 1.0)] {
            backwards.insert(key(i), distribution(value));
        }
        assert_eq!(forwards, backwards, "equality ignores the insertion order");
        backwards.insert(key(4), distribution(5.0));
        assert_ne!(forwards, backwards);
        backwards.clear();
        assert!(backwards.is_empty() && backwards.get(&key(1)).is_none());
    }

    #[test]
    fn statistics_in_parallel_chunks_match_one_sequential_pass() {
        // More points than one chunk, in an order that revisits voxels across chunk boundaries.
        let points: Vec<Point3<f64>> = (0..3 * ACCUMULATION_CHUNK + 17)
            .map(|i| {
                let t = i as f64;
                Point3::new(
                    (t * 0.731) % 9.0 - 4.5,
                    (t * 0.377) % 7.0,
                    (t * 0.193) % 3.0 - 40.0,
                )
            })
            .collect();
        let stats = voxel_statistics(&points, 0.8);
        let sequential: Vec<(VoxelKey, VoxelStats)> = accumulate_chunk::<VoxelStats>(&points, 0.8)
            .into_pairs()
            .collect();
        assert_eq!(stats.len(), sequential.len());
        for ((key, a), (sequential_key, b)) in stats.iter().zip(&sequential) {
            assert_eq!(key, sequential_key, "first-seen order");
            assert_eq!(a.count, b.count);
            assert!((a.sum - b.sum).norm() < 1e-9 && (a.sum_outer - b.sum_outer).norm() < 1e-9);
        }
        let thinned = voxel_downsample(&points, 0.8);
        assert_eq!(thinned.len(), sequential.len());
        for (point, (key, voxel)) in thinned.iter().zip(&sequential) {
            let centroid = key.corner(0.8) + voxel.sum / voxel.count as f64;
            assert!((point.coords - centroid).norm() < 1e-12);
        }
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

    #[test]
    fn range_downsample_thins_near_and_far_points_by_their_own_voxels() {
        // Along a ray in the x-y plane, 0.1 m apart, from 0.05 to 19.95 m out.
        let direction = Vector3::new(0.6, 0.8, 0.0);
        let points: Vec<Point3<f64>> = (0..200)
            .map(|i| Point3::from(direction * (0.05 + 0.1 * i as f64)))
            .collect();
        let thinned = range_voxel_downsample(&points, 2.0, 10.0, 0.5);
        let (near, far): (Vec<Point3<f64>>, Vec<Point3<f64>>) =
            thinned.iter().partition(|p| p.coords.norm() <= 10.0);
        assert_eq!(near, voxel_downsample(&points[..100], 2.0));
        assert_eq!(far, voxel_downsample(&points[100..], 0.5));
        assert!(
            far.len() > 2 * near.len(),
            "{} far, {} near",
            far.len(),
            near.len()
        );
        assert_eq!(
            range_voxel_downsample(&points, 2.0, f64::INFINITY, 0.5),
            voxel_downsample(&points, 2.0)
        );
    }
}
