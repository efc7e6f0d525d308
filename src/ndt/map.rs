#![forbid(unsafe_code)]
//! The local submap: a sliding window over the most recent scans, voxelised into normal distributions.
//!
//! Updates are incremental. Each inserted scan keeps its own per-voxel statistics; they are added into the
//! map's statistics, and when the window is full the oldest scan's statistics are subtracted again. Only
//! the voxels touched by the new or the evicted scan refit their distribution, so inserting costs
//! O(points of the new scan + voxels of the two scans), independent of the window length.

use std::collections::VecDeque;

use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;

use super::voxel::{voxel_statistics, Distributions, Gaussian, VoxelKey, VoxelMap, VoxelStats};
use crate::{Error, Result};

/// Settings of an [`NdtMap`].
#[derive(Clone, Debug, PartialEq)]
pub struct NdtMapConfig {
    /// Edge length of the cubic voxels, metres. Also the NDT resolution (1–2 m for outdoor LiDAR).
    pub voxel_size: f64,
    /// Voxels with fewer points fit no distribution (at least 3: a covariance needs them).
    pub min_points_per_voxel: usize,
    /// Number of most recent scans the map keeps (the sliding window).
    pub max_scans: usize,
    /// Covariance eigenvalues below this fraction of the largest are raised to it.
    pub min_eigenvalue_ratio: f64,
}

impl Default for NdtMapConfig {
    fn default() -> Self {
        NdtMapConfig {
            voxel_size: 1.0,
            min_points_per_voxel: 5,
            max_scans: 10,
            min_eigenvalue_ratio: 0.01,
        }
    }
}

impl NdtMapConfig {
    /// Checks every field, naming the first that is out of range.
    pub fn validate(&self) -> Result<()> {
        if !(self.voxel_size.is_finite() && self.voxel_size > 0.0) {
            return Err(Error::invalid(
                "voxel_size",
                format!("must be finite and > 0, got {}", self.voxel_size),
            ));
        }
        if self.min_points_per_voxel < 3 {
            return Err(Error::invalid(
                "min_points_per_voxel",
                format!(
                    "must be at least 3 to fit a covariance, got {}",
                    self.min_points_per_voxel
                ),
            ));
        }
        if self.max_scans == 0 {
            return Err(Error::invalid("max_scans", "must be at least 1"));
        }
        if !(self.min_eigenvalue_ratio > 0.0 && self.min_eigenvalue_ratio <= 1.0) {
            return Err(Error::invalid(
                "min_eigenvalue_ratio",
                format!("must lie in (0, 1], got {}", self.min_eigenvalue_ratio),
            ));
        }
        Ok(())
    }
}

/// A voxelised NDT map of the most recent scans (Magnusson's point-to-distribution NDT).
#[derive(Clone, Debug)]
pub struct NdtMap {
    config: NdtMapConfig,
    /// Statistics of every occupied voxel over the window.
    voxels: VoxelMap<VoxelStats>,
    gaussians: Distributions,
    /// Per-scan statistics of the window, oldest first, each in order of first appearance.
    scans: VecDeque<Vec<(VoxelKey, VoxelStats)>>,
}

impl NdtMap {
    /// An empty map; fails when the configuration is out of range.
    pub fn new(config: NdtMapConfig) -> Result<Self> {
        config.validate()?;
        Ok(NdtMap {
            config,
            voxels: VoxelMap::default(),
            gaussians: Distributions::default(),
            scans: VecDeque::new(),
        })
    }

    /// The map's settings.
    pub fn config(&self) -> &NdtMapConfig {
        &self.config
    }

    /// Voxels holding a distribution (enough points that spread).
    pub fn num_voxels(&self) -> usize {
        self.gaussians.len()
    }

    /// Voxels holding at least one point.
    pub fn num_occupied_voxels(&self) -> usize {
        self.voxels.len()
    }

    /// Scans currently in the window.
    pub fn num_scans(&self) -> usize {
        self.scans.len()
    }

    /// True before the first insert and after [`clear`](Self::clear).
    pub fn is_empty(&self) -> bool {
        self.scans.is_empty()
    }

    /// The distributions, keyed by voxel.
    pub fn gaussians(&self) -> &Distributions {
        &self.gaussians
    }

    /// Forgets every scan.
    pub fn clear(&mut self) {
        self.voxels.clear();
        self.gaussians.clear();
        self.scans.clear();
    }

    /// Adds a scan given in map (world) coordinates, evicting the oldest scan when the window is full.
    /// Fails without changing the map when `points_world` is empty or holds a non-finite or huge
    /// coordinate.
    pub fn insert(&mut self, points_world: &[Point3<f64>]) -> Result<()> {
        self.insert_checked(points_world, "points_world")
    }

    /// Adds a scan given in its sensor frame at the pose `map_from_sensor` (`T_map_sensor`): the same map
    /// as [`insert`](Self::insert) of the transformed points, without the caller building that copy (from
    /// Python, a numpy product that large wakes BLAS threads which then spin on the cores the network needs).
    pub fn insert_scan(
        &mut self,
        points_sensor: &[Point3<f64>],
        map_from_sensor: &Isometry3<f64>,
    ) -> Result<()> {
        let points_map: Vec<Point3<f64>> =
            points_sensor.iter().map(|p| map_from_sensor * p).collect();
        self.insert_checked(&points_map, "points")
    }

    fn insert_checked(
        &mut self,
        points_world: &[Point3<f64>],
        argument: &'static str,
    ) -> Result<()> {
        if points_world.is_empty() {
            return Err(Error::invalid(argument, "is empty"));
        }
        let inverse = 1.0 / self.config.voxel_size;
        if let Some(row) = points_world
            .iter()
            .position(|p| VoxelKey::containing(p, inverse).is_none())
        {
            return Err(Error::invalid(
                argument,
                format!(
                    "row {row} is not finite or too far from the origin (in the map): {:?}",
                    points_world[row].coords.as_slice()
                ),
            ));
        }
        let scan = voxel_statistics(points_world, self.config.voxel_size);
        let mut touched: Vec<VoxelKey> = scan.iter().map(|(key, _)| *key).collect();
        for (key, scan_stats) in &scan {
            self.voxels.entry(*key).or_default().merge(scan_stats);
        }
        self.scans.push_back(scan);
        while self.scans.len() > self.config.max_scans {
            let Some(oldest) = self.scans.pop_front() else {
                break;
            };
            for (key, scan_stats) in &oldest {
                if let Some(voxel) = self.voxels.get_mut(key) {
                    voxel.unmerge(scan_stats);
                    if voxel.count == 0 {
                        self.voxels.remove(key);
                    }
                }
                touched.push(*key);
            }
        }
        touched.sort_unstable();
        touched.dedup();
        self.refit(&touched);
        Ok(())
    }

    /// Refits the distributions of `keys` (in parallel; each voxel is independent).
    fn refit(&mut self, keys: &[VoxelKey]) {
        let config = &self.config;
        let voxels = &self.voxels;
        let fitted: Vec<Option<Gaussian>> = keys
            .par_iter()
            .map(|key| {
                voxels.get(key).and_then(|stats| {
                    stats.gaussian(
                        &key.corner(config.voxel_size),
                        config.min_points_per_voxel,
                        config.min_eigenvalue_ratio,
                    )
                })
            })
            .collect();
        for (key, gaussian) in keys.iter().zip(fitted) {
            match gaussian {
                Some(gaussian) => {
                    self.gaussians.insert(*key, gaussian);
                }
                None => {
                    self.gaussians.remove(key);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn block(offset: f64, count: usize) -> Vec<Point3<f64>> {
        (0..count)
            .map(|i| {
                let t = i as f64;
                Point3::new(
                    offset + (t * 0.37) % 1.0,
                    (t * 0.61) % 1.0,
                    (t * 0.23) % 1.0,
                )
            })
            .collect()
    }

    #[test]
    fn window_evicts_oldest_scan_and_matches_a_rebuild() {
        let config = NdtMapConfig {
            max_scans: 2,
            ..NdtMapConfig::default()
        };
        let mut sliding = NdtMap::new(config.clone()).unwrap();
        sliding.insert(&block(0.0, 20)).unwrap();
        sliding.insert(&block(0.1, 20)).unwrap();
        sliding.insert(&block(5.0, 20)).unwrap();
        assert_eq!(sliding.num_scans(), 2);
        let mut rebuilt = NdtMap::new(config).unwrap();
        rebuilt.insert(&block(0.1, 20)).unwrap();
        rebuilt.insert(&block(5.0, 20)).unwrap();
        assert_eq!(sliding.num_voxels(), rebuilt.num_voxels());
        assert_eq!(sliding.num_occupied_voxels(), rebuilt.num_occupied_voxels());
        for (key, gaussian) in rebuilt.gaussians().iter() {
            let other = sliding.gaussians().get(key).unwrap();
            assert!((other.mean - gaussian.mean).norm() < 1e-9);
            assert!((other.inverse_covariance - gaussian.inverse_covariance).norm() < 1e-6);
        }
    }

    #[test]
    fn a_scan_placed_by_its_pose_builds_the_map_of_its_transformed_points() {
        let pose = Isometry3::new(
            nalgebra::Vector3::new(3.0, -2.0, 0.5),
            nalgebra::Vector3::new(0.02, -0.01, 0.7),
        );
        let scan = block(0.0, 60);
        let mut placed = NdtMap::new(NdtMapConfig::default()).unwrap();
        placed.insert_scan(&scan, &pose).unwrap();
        let moved: Vec<Point3<f64>> = scan.iter().map(|p| pose * p).collect();
        let mut reference = NdtMap::new(NdtMapConfig::default()).unwrap();
        reference.insert(&moved).unwrap();
        assert!(reference.num_voxels() > 0);
        assert_eq!(
            placed.num_occupied_voxels(),
            reference.num_occupied_voxels()
        );
        assert_eq!(placed.gaussians(), reference.gaussians());
        let mut bad = scan.clone();
        bad[7] = Point3::new(f64::INFINITY, 0.0, 0.0);
        let refused = placed.insert_scan(&bad, &pose);
        assert!(
            matches!(&refused, Err(Error::InvalidArgument { argument: "points", reason }) if reason.starts_with("row 7 "))
        );
        assert_eq!(
            placed.num_scans(),
            1,
            "a refused scan leaves the map as it was"
        );
    }

    #[test]
    fn bad_points_and_configs_are_refused() {
        let mut map = NdtMap::new(NdtMapConfig::default()).unwrap();
        assert!(matches!(
            map.insert(&[]),
            Err(Error::InvalidArgument {
                argument: "points_world",
                ..
            })
        ));
        let bad = [Point3::new(0.0, f64::NAN, 0.0)];
        assert!(matches!(
            map.insert(&bad),
            Err(Error::InvalidArgument {
                argument: "points_world",
                ..
            })
        ));
        assert!(map.is_empty());
        for (config, argument) in [
            (
                NdtMapConfig {
                    voxel_size: 0.0,
                    ..Default::default()
                },
                "voxel_size",
            ),
            (
                NdtMapConfig {
                    voxel_size: f64::NAN,
                    ..Default::default()
                },
                "voxel_size",
            ),
            (
                NdtMapConfig {
                    min_points_per_voxel: 2,
                    ..Default::default()
                },
                "min_points_per_voxel",
            ),
            (
                NdtMapConfig {
                    max_scans: 0,
                    ..Default::default()
                },
                "max_scans",
            ),
            (
                NdtMapConfig {
                    min_eigenvalue_ratio: 0.0,
                    ..Default::default()
                },
                "min_eigenvalue_ratio",
            ),
        ] {
            match NdtMap::new(config) {
                Err(Error::InvalidArgument { argument: got, .. }) => assert_eq!(got, argument),
                other => panic!("expected an error naming {argument}, got {other:?}"),
            }
        }
    }
}
