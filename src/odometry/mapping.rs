#![forbid(unsafe_code)]
//! Scan-to-map NDT refinement of every pose over a local map of recent keyframes (§III-D-c), and of a
//! single pair against its reference scan.
//!
//! The network's matches bring each scan within NDT's basin with no initial guess; NDT against several
//! scans in one frame, fitting every point rather than a few hundred matches, takes out the error the
//! matches leave. Beyond the paper: NDT also starts from the constant-velocity prediction when the DMLO
//! pose leaves it far behind (a wrong consensus lies outside NDT's basin); near the newest keyframe its
//! ground rings, which sit at fixed ranges from the sensor, would hold a creeping car in place, so the
//! horizontal motion and heading come from the scan's upright surfaces alone and the height, roll and
//! pitch from the whole scan (LeGO-LOAM's split); a car standing at the keyframe is aligned to it by
//! projective point-to-plane ICP, where NDT's voxels leave millimetres. Farther from it the height, roll
//! and pitch come from a second, short NDT without the far upright surfaces ([`level_points`]), which,
//! seen from the keyframes behind, tilt the scan a little every frame. Poses are 4×4 `T_map_lidar`.

use nalgebra::{Matrix3, Matrix4, Point3};

use super::motion::{pose_difference, rigid_inverse};
use crate::error::{Error, Result};
use crate::ndt::voxel::range_voxel_downsample;
use crate::ndt::{NdtAlignConfig, NdtMap, NdtMapConfig, NdtResult};
use crate::projection::CylinderConfig;
use crate::projective::{point_to_plane, PointToPlaneConfig};
use crate::rigid::isometry_from_matrix;
use crate::surface::{horizontal_votes, steep_to_next_ring};

/// The horizontal part of a surface's normal from which it counts as upright.
pub const UPRIGHT_VOTE: f64 = 0.5;
/// How close to the keyframe (m) a pose must lie for the car to stand …
pub const STANDING_DISTANCE: f64 = 0.02;
/// … and how little turned (°).
pub const STANDING_ANGLE_DEG: f64 = 0.1;
/// Newton steps of the alignment that gives the height, roll and pitch ([`level_points`]): it starts
/// from the pose that fits every point best, a step or two from the one that fits its points best.
pub const LEVEL_NEWTON_STEPS: usize = 2;

/// The local map's settings, the config's `mapping` section (`Default`: its defaults).
#[derive(Debug, Clone, PartialEq)]
pub struct MappingConfig {
    /// NDT voxel edge (m).
    pub voxel_size: f64,
    /// Keyframes the local map keeps.
    pub max_scans: usize,
    /// A scan enters the map once it moved this far (m) from the newest keyframe …
    pub keyframe_distance: f64,
    /// … or turned this much (°).
    pub keyframe_angle_deg: f64,
    /// Within this distance (m) of the newest keyframe the horizontal motion and heading come from the
    /// upright surfaces alone; 0 turns the near-keyframe handling off.
    pub ring_lock_distance: f64,
    /// NDT also starts from the prediction when the DMLO pose lies this far from it (m) …
    pub motion_model_start_distance: f64,
    /// … or this much turned (°).
    pub motion_model_start_angle_deg: f64,
    /// Voxel (m) of the scan aligned to the map within `far_range` of the sensor; 0: every point …
    pub downsample: f64,
    /// … and beyond it.
    pub downsample_far: f64,
    /// Metres from the sensor (limit).
    pub far_range: f64,
    /// The height, roll and pitch come from a second, short NDT that leaves out the upright surfaces beyond
    /// `far_range` ([`level_points`]).
    pub level_without_far_upright: bool,
    /// Newton steps at most.
    pub max_iterations: usize,
    /// NDT's degeneracy threshold of the translations ([`NdtAlignConfig::degeneracy_threshold`]).
    pub degeneracy_threshold: f64,
    /// The same of the rotations.
    pub rotation_degeneracy_threshold: f64,
}

impl Default for MappingConfig {
    /// The odometry config's defaults (`odometry::config`, where every setting is declared).
    fn default() -> Self {
        crate::odometry::config::OdometryConfig::default().mapping_config()
    }
}

impl MappingConfig {
    /// The alignment settings NDT runs with.
    pub fn align_config(&self) -> NdtAlignConfig {
        NdtAlignConfig {
            max_iterations: self.max_iterations,
            source_voxel_size: self.downsample,
            source_far_range: self.far_range,
            source_far_voxel_size: self.downsample_far,
            degeneracy_threshold: self.degeneracy_threshold,
            rotation_degeneracy_threshold: self.rotation_degeneracy_threshold,
            ..Default::default()
        }
    }

    /// Names the first setting out of its range.
    pub fn validate(&self) -> Result<()> {
        let limits = [
            ("keyframe_distance", self.keyframe_distance),
            ("keyframe_angle_deg", self.keyframe_angle_deg),
            ("ring_lock_distance", self.ring_lock_distance),
            (
                "motion_model_start_distance",
                self.motion_model_start_distance,
            ),
            (
                "motion_model_start_angle_deg",
                self.motion_model_start_angle_deg,
            ),
            ("far_range", self.far_range),
        ];
        for (name, value) in limits {
            if value.is_nan() || value < 0.0 {
                return Err(Error::invalid(name, format!("must be ≥ 0, got {value}")));
            }
        }
        for (name, value) in [
            ("downsample", self.downsample),
            ("downsample_far", self.downsample_far),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return Err(Error::invalid(
                    name,
                    format!("must be finite and ≥ 0, got {value}"),
                ));
            }
        }
        self.map_config().validate()?;
        self.align_config().validate()
    }

    fn map_config(&self) -> NdtMapConfig {
        NdtMapConfig {
            voxel_size: self.voxel_size,
            max_scans: self.max_scans,
            ..Default::default()
        }
    }
}

/// How a scan next to a keyframe (or a pair's reference) is aligned.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NearKeyframe {
    /// The car has not moved: projective point-to-plane ICP against the keyframe's point image.
    Standing,
    /// Within `ring_lock_distance`: the upright surfaces give the horizontal motion and heading.
    Near,
}

/// How a scan at `pose` is aligned next to a keyframe at `keyframe`: one decision for the drive and the
/// single pair; `None` beyond `config.ring_lock_distance` (NDT of the whole scan).
pub fn near_keyframe_alignment(
    keyframe: &Matrix4<f64>,
    pose: &Matrix4<f64>,
    config: &MappingConfig,
) -> Option<NearKeyframe> {
    if pose_difference(keyframe, pose).0 >= config.ring_lock_distance {
        return None;
    }
    Some(if standing(keyframe, pose) {
        NearKeyframe::Standing
    } else {
        NearKeyframe::Near
    })
}

/// Whether `pose` lies within [`STANDING_DISTANCE`] and [`STANDING_ANGLE_DEG`] of `keyframe`.
pub fn standing(keyframe: &Matrix4<f64>, pose: &Matrix4<f64>) -> bool {
    let (moved, turned) = pose_difference(keyframe, pose);
    moved < STANDING_DISTANCE && turned < STANDING_ANGLE_DEG
}

/// The first of `cells` (in their order) in each `voxel` (m) of a point image, the voxels in the order of
/// their keys.
fn one_cell_a_voxel(points: &[f32], cells: &[usize], voxel: f64) -> Vec<usize> {
    // One integer a voxel, as the odometry's Python side keyed them: voxels a million apart may share it.
    let size = voxel as f32;
    // Wrapping, as numpy's int64 arithmetic wraps for coordinates thousands of kilometres out.
    let key = |cell: usize| -> i64 {
        let k =
            |axis: usize| ((points[3 * cell + axis] / size).floor() as i64).wrapping_add(1 << 20);
        k(0).wrapping_shl(42)
            .wrapping_add(k(1).wrapping_shl(21))
            .wrapping_add(k(2))
    };
    let mut keyed: Vec<(i64, usize)> = cells.iter().map(|&cell| (key(cell), cell)).collect();
    keyed.sort_by_key(|&(key, _)| key); // stable: the first cell of each voxel leads it
    keyed.dedup_by_key(|&mut (key, _)| key);
    keyed.into_iter().map(|(_, cell)| cell).collect()
}

/// The upright surfaces of a scan's point image `points` (`H × W × 3`, NaN where empty): each kept
/// point whose surface's normal is mostly horizontal ([`horizontal_votes`]: walls, poles, trunks, car
/// bodies), one cell per `voxel` (m; 0: every cell), the first in row-major order of each voxel, the
/// voxels in the order of their keys: a plane fit for every cell would cost more than NDT.
pub fn upright_points(
    points: &[f32],
    cylinder: &CylinderConfig,
    voxel: f64,
) -> Result<Vec<Point3<f64>>> {
    if !(voxel.is_finite() && voxel >= 0.0) {
        return Err(Error::invalid(
            "voxel",
            format!("must be finite and ≥ 0, got {voxel}"),
        ));
    }
    let cells = point_image_cells(points, cylinder)?;
    let mut kept: Vec<usize> = (0..cells)
        .filter(|&cell| points[3 * cell].is_finite())
        .collect();
    if voxel > 0.0 {
        kept = one_cell_a_voxel(points, &kept, voxel);
    }
    let upright = upright_cells(points, cylinder, &kept)?;
    Ok(kept
        .iter()
        .zip(upright)
        .filter(|&(_, upright)| upright)
        .map(|(&cell, _)| cell_point(points, cell))
        .collect())
}

/// The points of a point image (`H × W × 3`, NaN where empty) that [`LocalMap::refine`] takes the height,
/// roll and pitch from: every point within `range` of the sensor, and beyond it those not on an upright
/// surface ([`steep_to_next_ring`]: the ground, roofs), thinned to one a `voxel`. Seen from the keyframes
/// behind, the far walls, poles and trees tilt the scan nose-down a little every frame, while the far
/// ground does not (docs/measurements.md).
pub fn level_points(
    points: &[f32],
    cylinder: &CylinderConfig,
    voxel: f64,
    range: f64,
) -> Result<Vec<Point3<f64>>> {
    let cells = point_image_cells(points, cylinder)?;
    let mut near = Vec::new();
    let mut far_cells = Vec::new();
    for cell in (0..cells).filter(|&cell| points[3 * cell].is_finite()) {
        let point = cell_point(points, cell);
        if point.coords.norm() <= range {
            near.push(point);
        } else {
            far_cells.push(cell);
        }
    }
    let upright = steep_to_next_ring(
        points,
        cylinder,
        &grid_cells(&far_cells, cylinder),
        UPRIGHT_VOTE,
    )?;
    let mut far_ground: Vec<usize> = far_cells
        .into_iter()
        .zip(upright)
        .filter(|&(_, upright)| !upright)
        .map(|(cell, _)| cell)
        .collect();
    if voxel > 0.0 {
        far_ground = one_cell_a_voxel(points, &far_ground, voxel);
    }
    near.extend(far_ground.into_iter().map(|cell| cell_point(points, cell)));
    Ok(near)
}

/// The number of cells of a point image, or an error naming `points` when its length does not fit.
fn point_image_cells(points: &[f32], cylinder: &CylinderConfig) -> Result<usize> {
    let cells = cylinder.height * cylinder.width;
    if points.len() != 3 * cells {
        return Err(Error::invalid(
            "points",
            format!(
                "expected {} values (H × W × 3), got {}",
                3 * cells,
                points.len()
            ),
        ));
    }
    Ok(cells)
}

/// Row-major cell indices of a point image as `[row, col]`.
fn grid_cells(cells: &[usize], cylinder: &CylinderConfig) -> Vec<[usize; 2]> {
    cells
        .iter()
        .map(|&cell| [cell / cylinder.width, cell % cylinder.width])
        .collect()
}

fn cell_point(points: &[f32], cell: usize) -> Point3<f64> {
    let p = &points[3 * cell..3 * cell + 3];
    Point3::new(p[0] as f64, p[1] as f64, p[2] as f64)
}

/// Whether each of `cells` lies on an upright surface ([`horizontal_votes`] of at least [`UPRIGHT_VOTE`]).
fn upright_cells(points: &[f32], cylinder: &CylinderConfig, cells: &[usize]) -> Result<Vec<bool>> {
    let votes = horizontal_votes(
        points,
        cylinder,
        &grid_cells(cells, cylinder),
        UPRIGHT_VOTE / 2.0,
    )?;
    Ok(votes.into_iter().map(|vote| vote >= UPRIGHT_VOTE).collect())
}

/// A pose with the horizontal position and heading (yaw) of `horizontal` and the height, roll and pitch
/// (Z-Y-X angles) of `level`.
pub fn heading_and_level(horizontal: &Matrix4<f64>, level: &Matrix4<f64>) -> Matrix4<f64> {
    let angles = |m: &Matrix4<f64>| {
        let yaw = m[(1, 0)].atan2(m[(0, 0)]);
        let pitch = -m[(2, 0)].clamp(-1.0, 1.0).asin();
        let roll = m[(2, 1)].atan2(m[(2, 2)]);
        (yaw, pitch, roll)
    };
    let (yaw, _, _) = angles(horizontal);
    let (_, pitch, roll) = angles(level);
    let (cy, sy, cp, sp, cr, sr) = (
        yaw.cos(),
        yaw.sin(),
        pitch.cos(),
        pitch.sin(),
        roll.cos(),
        roll.sin(),
    );
    let rotation = Matrix3::new(cy, -sy, 0.0, sy, cy, 0.0, 0.0, 0.0, 1.0)
        * Matrix3::new(cp, 0.0, sp, 0.0, 1.0, 0.0, -sp, 0.0, cp)
        * Matrix3::new(1.0, 0.0, 0.0, 0.0, cr, -sr, 0.0, sr, cr);
    let mut pose = Matrix4::identity();
    pose.fixed_view_mut::<3, 3>(0, 0).copy_from(&rotation);
    pose[(0, 3)] = horizontal[(0, 3)];
    pose[(1, 3)] = horizontal[(1, 3)];
    pose[(2, 3)] = level[(2, 3)];
    pose
}

/// [`align_near_keyframe`]'s pose, the directions the map left open, and whether the horizontal motion
/// and heading came from the upright surfaces alone (false: the car stands).
#[derive(Debug, Clone, PartialEq)]
pub struct NearAlignment {
    /// `T_map_lidar`.
    pub pose: Matrix4<f64>,
    /// Directions NDT kept at their start.
    pub degenerate_directions: usize,
    /// The upright surfaces gave the horizontal motion and heading.
    pub split: bool,
}

/// NDT near a keyframe, whose ground rings would hold a creeping car in place (module docs): the
/// `upright` surfaces alone from `start`, then the whole `cloud` from there; `align(points, start)`
/// aligns to the map. A scan that `start` or the upright surfaces put at the keyframe stands and takes
/// the whole scan's alignment. `None` when an alignment fails, does not converge, or there are no upright
/// surfaces to align. Errors are a wrong argument of `align`'s.
pub fn align_near_keyframe(
    mut align: impl FnMut(&[Point3<f64>], &Matrix4<f64>) -> Result<NdtResult>,
    cloud: &[Point3<f64>],
    upright: &[Point3<f64>],
    start: &Matrix4<f64>,
    keyframe: &Matrix4<f64>,
) -> Result<Option<NearAlignment>> {
    // The upright surfaces alone fix the pose less well than the whole scan (fewer points, a corridor's
    // walls): a car the DMLO estimate already puts at the keyframe is not moved by them.
    let horizontal_pose = if standing(keyframe, start) {
        *start
    } else {
        if upright.is_empty() {
            return Ok(None);
        }
        match solvable(align(upright, start))? {
            Some(result) if result.converged => result.transform.to_homogeneous(),
            _ => return Ok(None),
        }
    };
    let whole = match solvable(align(cloud, &horizontal_pose))? {
        Some(result) if result.converged => result,
        _ => return Ok(None),
    };
    let whole_pose = whole.transform.to_homogeneous();
    let split = !standing(keyframe, &horizontal_pose);
    Ok(Some(NearAlignment {
        pose: if split {
            heading_and_level(&horizontal_pose, &whole_pose)
        } else {
            whole_pose
        },
        degenerate_directions: whole.degenerate_directions,
        split,
    }))
}

/// A solve's result, `None` when its data admit no solution (too few correspondences, degenerate
/// points); a wrong argument stays an error.
fn solvable<T>(result: Result<T>) -> Result<Option<T>> {
    match result {
        Ok(value) => Ok(Some(value)),
        Err(Error::TooFewPoints { .. } | Error::Degenerate(_)) => Ok(None),
        Err(other) => Err(other),
    }
}

/// Which start NDT's pose came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MapStart {
    /// The DMLO pose.
    Dmlo,
    /// The constant-velocity prediction (DMLO's pose was off).
    MotionModel,
    /// The car stood at the newest keyframe and was aligned to it by point-to-plane ICP.
    Standing,
}

impl MapStart {
    /// The name the diagnostics give it (`ndt_start`).
    pub fn name(self) -> &'static str {
        match self {
            MapStart::Dmlo => "dmlo",
            MapStart::MotionModel => "motion_model",
            MapStart::Standing => "standing",
        }
    }
}

/// What the map made of a pose.
#[derive(Debug, Clone, PartialEq)]
pub struct MapRefinement {
    /// `T_map_lidar`: the refined pose, or the one given when no alignment converged.
    pub pose: Matrix4<f64>,
    /// Whether an alignment converged.
    pub converged: bool,
    /// Pose directions the map did not constrain (kept as given); `None` when no alignment ran.
    pub degenerate_directions: Option<usize>,
    /// Near the newest keyframe: the horizontal motion and heading came from the upright surfaces.
    pub upright_only: bool,
    /// The start whose alignment won; `None` when none converged.
    pub start: Option<MapStart>,
}

/// The local map: the most recent keyframes' NDT distributions, and the newest keyframe's pose and point
/// image.
#[derive(Debug, Clone)]
pub struct LocalMap {
    config: MappingConfig,
    map: NdtMap,
    keyframe: Option<(Matrix4<f64>, Vec<f32>)>,
}

impl LocalMap {
    /// An empty map with these settings (checked).
    pub fn new(config: MappingConfig) -> Result<Self> {
        config.validate()?;
        let map = NdtMap::new(config.map_config())?;
        Ok(LocalMap {
            config,
            map,
            keyframe: None,
        })
    }

    /// Its settings.
    pub fn config(&self) -> &MappingConfig {
        &self.config
    }

    /// Empties the map: no keyframe, no scan.
    pub fn clear(&mut self) {
        self.map.clear();
        self.keyframe = None;
    }

    /// The newest keyframe's pose.
    pub fn last_keyframe(&self) -> Option<&Matrix4<f64>> {
        self.keyframe.as_ref().map(|(pose, _)| pose)
    }

    /// Keyframes in the map.
    pub fn num_scans(&self) -> usize {
        self.map.num_scans()
    }

    /// Whether a scan at `pose` moved or turned far enough from the newest keyframe to enter the map:
    /// scans drawn from nearly the same place add the same ground rings again and again, all behind the
    /// next scan, and NDT then pulls its rings back onto them.
    pub fn is_keyframe(&self, pose: &Matrix4<f64>) -> bool {
        let Some((keyframe, _)) = &self.keyframe else {
            return true;
        };
        let (moved, turned) = pose_difference(keyframe, pose);
        moved >= self.config.keyframe_distance || turned >= self.config.keyframe_angle_deg
    }

    /// Adds a scan (`cloud` in its sensor frame, `points` its point image) at `pose` as the newest
    /// keyframe; the oldest beyond `max_scans` leaves.
    pub fn insert(
        &mut self,
        cloud: &[Point3<f64>],
        pose: &Matrix4<f64>,
        points: &[f32],
    ) -> Result<()> {
        let isometry = isometry_from_matrix(pose, "pose")?;
        self.map.insert_scan(cloud, &isometry)?;
        self.keyframe = Some((*pose, points.to_vec()));
        Ok(())
    }

    /// Empties the map and starts it again from one scan.
    pub fn restart(
        &mut self,
        cloud: &[Point3<f64>],
        pose: &Matrix4<f64>,
        points: &[f32],
    ) -> Result<()> {
        self.map.clear();
        self.keyframe = None;
        self.insert(cloud, pose, points)
    }

    fn align(&self, points: &[Point3<f64>], start: &Matrix4<f64>) -> Result<NdtResult> {
        self.map
            .align_matrix(points, start, &self.config.align_config())
    }

    /// The pose `pose` of a scan (`cloud`, its point image `points`) refined against the map (module
    /// docs); `prediction`: the constant-velocity pose, when one is measured and within its horizon.
    pub fn refine(
        &self,
        cloud: &[Point3<f64>],
        points: &[f32],
        pose: &Matrix4<f64>,
        prediction: Option<&Matrix4<f64>>,
        cylinder: &CylinderConfig,
    ) -> Result<MapRefinement> {
        isometry_from_matrix(pose, "pose")?;
        if let Some(predicted) = prediction {
            isometry_from_matrix(predicted, "prediction")?;
        }
        if let Some(near) = self.refine_near_keyframe(cloud, points, pose, cylinder)? {
            return Ok(near);
        }
        let mut starts = vec![(MapStart::Dmlo, *pose)];
        if let Some(predicted) = prediction {
            // Before any velocity is measured the prediction is "standing still", and the map's ground
            // rings, which move with the sensor, would score that wrong start highly: the caller gives none.
            let (moved, turned) = pose_difference(pose, predicted);
            if moved > self.config.motion_model_start_distance
                || turned > self.config.motion_model_start_angle_deg
            {
                starts.push((MapStart::MotionModel, *predicted));
            }
        }
        // The level alignment's points need no pose: thinned beside the first alignment, on a core it
        // leaves idle part of the time.
        let (aligned, level_cloud) = rayon::join(
            || {
                starts
                    .into_iter()
                    .map(|(name, start)| (name, self.align(cloud, &start)))
                    .collect::<Vec<_>>()
            },
            || self.level_cloud(points, cylinder),
        );
        let mut dmlo_degenerate = None;
        let mut best: Option<(MapStart, NdtResult)> = None;
        for (name, result) in aligned {
            let Some(result) = solvable(result)? else {
                continue;
            };
            if name == MapStart::Dmlo {
                dmlo_degenerate = Some(result.degenerate_directions);
            }
            let better = best
                .as_ref()
                .is_none_or(|(_, kept)| result.score > kept.score);
            if result.converged && better {
                best = Some((name, result));
            }
        }
        Ok(match best {
            None => MapRefinement {
                pose: *pose,
                converged: false,
                degenerate_directions: dmlo_degenerate,
                upright_only: false,
                start: None,
            },
            Some((name, result)) => MapRefinement {
                pose: self.level(&result.transform.to_homogeneous(), level_cloud?)?,
                converged: true,
                degenerate_directions: Some(result.degenerate_directions),
                upright_only: false,
                start: Some(name),
            },
        })
    }

    /// The points the level alignment fits ([`level`](Self::level)), thinned as the alignment would
    /// thin them: the scan's points within `far_range` and the far ones off upright surfaces
    /// ([`level_points`]); `None` when `level_without_far_upright` is off or `far_range` is infinite.
    fn level_cloud(
        &self,
        points: &[f32],
        cylinder: &CylinderConfig,
    ) -> Result<Option<Vec<Point3<f64>>>> {
        if !self.config.level_without_far_upright || self.config.far_range.is_infinite() {
            return Ok(None);
        }
        let level = level_points(
            points,
            cylinder,
            self.config.downsample_far,
            self.config.far_range,
        )?;
        let thinning = self.config.align_config();
        Ok(Some(range_voxel_downsample(
            &level,
            thinning.source_voxel_size,
            thinning.source_far_range,
            thinning.source_far_voxel_size,
        )))
    }

    /// `pose` with its height, roll and pitch from [`LEVEL_NEWTON_STEPS`] of NDT of the level cloud
    /// ([`level_cloud`](Self::level_cloud), already thinned), started from it; unchanged without a level
    /// cloud or when that alignment fails.
    fn level(
        &self,
        pose: &Matrix4<f64>,
        level_cloud: Option<Vec<Point3<f64>>>,
    ) -> Result<Matrix4<f64>> {
        let Some(level_cloud) = level_cloud else {
            return Ok(*pose);
        };
        let config = NdtAlignConfig {
            max_iterations: LEVEL_NEWTON_STEPS,
            // Thinned already: a voxel of zero keeps every point.
            source_voxel_size: 0.0,
            source_far_range: f64::INFINITY,
            ..self.config.align_config()
        };
        // So few steps seldom meet the convergence tolerances; the line search takes each only where it
        // improves the fit.
        Ok(
            match solvable(self.map.align_matrix(&level_cloud, pose, &config))? {
                Some(level) => heading_and_level(pose, &level.transform.to_homogeneous()),
                None => *pose,
            },
        )
    }

    /// Near the newest keyframe ([`near_keyframe_alignment`]): a standing car by point-to-plane ICP
    /// against the keyframe's point image, else [`align_near_keyframe`] of its upright surfaces; `None`
    /// farther away or when the alignments fail (the whole scan is aligned then).
    fn refine_near_keyframe(
        &self,
        cloud: &[Point3<f64>],
        points: &[f32],
        pose: &Matrix4<f64>,
        cylinder: &CylinderConfig,
    ) -> Result<Option<MapRefinement>> {
        let Some((keyframe, keyframe_points)) = &self.keyframe else {
            return Ok(None);
        };
        let Some(alignment) = near_keyframe_alignment(keyframe, pose, &self.config) else {
            return Ok(None);
        };
        if alignment == NearKeyframe::Standing {
            // Only then: a car creeping in a queue that the moving-object network missed would be held in
            // place by the cars around it, which stand still in its frame.
            let start = isometry_from_matrix(&(rigid_inverse(pose) * keyframe), "pose")?;
            let refined = point_to_plane(
                keyframe_points,
                points,
                cylinder,
                &start,
                &PointToPlaneConfig::default(),
            )?;
            if let Some(refined) = refined {
                return Ok(Some(MapRefinement {
                    pose: keyframe * refined.inverse().to_homogeneous(),
                    converged: true,
                    degenerate_directions: Some(0),
                    upright_only: false,
                    start: Some(MapStart::Standing),
                }));
            }
        }
        let upright = upright_points(points, cylinder, self.config.downsample)?;
        let near = align_near_keyframe(
            |points, start| self.align(points, start),
            cloud,
            &upright,
            pose,
            keyframe,
        )?;
        Ok(near.map(|near| MapRefinement {
            pose: near.pose,
            converged: true,
            degenerate_directions: Some(near.degenerate_directions),
            upright_only: near.split,
            start: Some(MapStart::Dmlo),
        }))
    }
}

/// `T_tgt_ref` of a consecutive pair refined by NDT of `target` against a map of `reference` alone
/// (both in their own sensor frames) with the local map's settings; with the target's upright surfaces
/// (`target_upright`: the caller found the pair near, [`near_keyframe_alignment`]) by
/// [`align_near_keyframe`]. `None` when NDT finds too few correspondences or does not converge.
pub fn refine_pair(
    reference: &[Point3<f64>],
    target: &[Point3<f64>],
    t_tgt_ref: &Matrix4<f64>,
    config: &MappingConfig,
    target_upright: Option<&[Point3<f64>]>,
) -> Result<Option<Matrix4<f64>>> {
    config.validate()?;
    isometry_from_matrix(t_tgt_ref, "t_tgt_ref")?;
    let mut one_scan = NdtMap::new(NdtMapConfig {
        max_scans: 1,
        ..config.map_config()
    })?;
    one_scan.insert(reference)?;
    let align_config = config.align_config();
    let align = |points: &[Point3<f64>], start: &Matrix4<f64>| {
        one_scan.align_matrix(points, start, &align_config)
    };
    // The map is the reference's frame: the target's pose in it.
    let start = rigid_inverse(t_tgt_ref);
    let pose = match target_upright {
        Some(upright) => align_near_keyframe(align, target, upright, &start, &Matrix4::identity())?
            .map(|near| near.pose),
        None => match solvable(align(target, &start))? {
            Some(result) if result.converged => Some(result.transform.to_homogeneous()),
            _ => None,
        },
    };
    Ok(pose.map(|pose| rigid_inverse(&pose)))
}

/// `t_tgt_ref` of a consecutive pair refined against its reference alone, one decision with the drive's
/// ([`near_keyframe_alignment`] of the target's pose in the reference's frame): a pair that stands by
/// projective point-to-plane ICP of the point images (NDT's voxels leave millimetres where the planes
/// are exact; a scan with itself is the identity), a pair within `ring_lock_distance` by
/// [`refine_pair`] with the target's upright surfaces (the reference's rings would hold it together),
/// any other by [`refine_pair`] of the whole target. `None` when the alignment fails.
pub fn refine_consecutive_pair(
    reference: &[Point3<f64>],
    target: &[Point3<f64>],
    reference_points: &[f32],
    target_points: &[f32],
    t_tgt_ref: &Matrix4<f64>,
    config: &MappingConfig,
    cylinder: &CylinderConfig,
) -> Result<Option<Matrix4<f64>>> {
    isometry_from_matrix(t_tgt_ref, "t_tgt_ref")?;
    let target_pose = rigid_inverse(t_tgt_ref);
    match near_keyframe_alignment(&Matrix4::identity(), &target_pose, config) {
        Some(NearKeyframe::Standing) => {
            let start = isometry_from_matrix(t_tgt_ref, "t_tgt_ref")?;
            let refined = point_to_plane(
                reference_points,
                target_points,
                cylinder,
                &start,
                &PointToPlaneConfig::default(),
            )?;
            Ok(refined.map(|pose| pose.to_homogeneous()))
        }
        Some(NearKeyframe::Near) => {
            let upright = upright_points(target_points, cylinder, config.downsample)?;
            refine_pair(reference, target, t_tgt_ref, config, Some(&upright))
        }
        None => refine_pair(reference, target, t_tgt_ref, config, None),
    }
}

#[cfg(test)]
mod tests;
