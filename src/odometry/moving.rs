#![forbid(unsafe_code)]
//! Points on moving objects found without labels: the learned moving-object network beside the model
//! (`moving.onnx`, exported by `dmlo export`), as the odometry runs it.
//!
//! Vehicles keeping pace with the ego car, or passing it, can outnumber the static scene's matches and
//! capture the consensus: the odometry then follows them, not the road. The network predicts, cell by
//! cell of the scan's cylinder image, the probability of a moving object from two images — the range of
//! each cell's kept point and its height `z` — and every point in a cell above the threshold is left out
//! of matching and of the map, as a caller's `moving` mask would leave it ([`super::pipeline::Scan`]).
//! Training makes its images with [`network_images`] too, so the network sees at run time what it was
//! trained on. The runtime is the caller's: `dmlo_rs::inference` runs the graph in tract or
//! onnxruntime (features `inference` / `onnxruntime`).

use crate::error::{Error, Result};
use crate::projection::{point_cells, project_flat, CylinderConfig};

/// A moving-object network: a scan's range and height images in, each cell's probability of a moving
/// object out.
pub trait MovingObjectNetwork {
    /// The cylinder image the network takes.
    fn cylinder(&self) -> &CylinderConfig;
    /// The probability of every cell (`H × W`, row-major) from the range image (m, 0 where empty) and the
    /// height image (`z` of each cell's kept point, m, 0 where empty), both `H × W`.
    fn probability(&self, range: &[f32], height: &[f32]) -> Result<Vec<f32>>;
}

/// The network's two input images of a flat `N × channels` scan (3 or 4 values a point, as
/// [`project_flat`] takes it): the range of each cell's kept point (Eq. 1) and its height `z`, both
/// `H × W` with 0 where a cell is empty.
pub fn network_images(
    points: &[f32],
    channels: usize,
    cylinder: &CylinderConfig,
) -> Result<(Vec<f32>, Vec<f32>)> {
    let projection = project_flat(points, channels, cylinder)?;
    let height = projection
        .index
        .iter()
        .map(|&i| usize::try_from(i).map_or(0.0, |i| points[i * channels + 2]))
        .collect();
    Ok((projection.range, height))
}

/// The points of `points` (one flag each) that `network` puts on moving objects: every point whose cell's
/// probability exceeds `threshold`. Points outside the image, at the origin or non-finite are not flagged.
pub fn moving_points<N: MovingObjectNetwork + ?Sized>(
    network: &N,
    points: &[[f32; 4]],
    threshold: f64,
) -> Result<Vec<bool>> {
    moving_points_and_fill(network, points, threshold).map(|(flags, _)| flags)
}

/// [`moving_points`], and the fraction of the image's cells that the whole scan fills (0 for an empty
/// scan): its range image is made for the network anyway.
pub fn moving_points_and_fill<N: MovingObjectNetwork + ?Sized>(
    network: &N,
    points: &[[f32; 4]],
    threshold: f64,
) -> Result<(Vec<bool>, f64)> {
    if points.is_empty() {
        return Ok((Vec::new(), 0.0));
    }
    let cylinder = network.cylinder();
    let points = points.as_flattened();
    let (range, height) = network_images(points, 4, cylinder)?;
    let filled = range.iter().filter(|&&r| r > 0.0).count() as f64 / range.len() as f64;
    let probability = network.probability(&range, &height)?;
    Ok((
        flagged_points(points, 4, &probability, cylinder, threshold)?,
        filled,
    ))
}

/// The points of a flat `N × channels` scan (3 or 4 values a point) in cells whose `probability` (`H × W`,
/// the network's answer for [`network_images`]) exceeds `threshold`: the rule of [`moving_points`], for a
/// network run elsewhere.
pub fn flagged_points(
    points: &[f32],
    channels: usize,
    probability: &[f32],
    cylinder: &CylinderConfig,
    threshold: f64,
) -> Result<Vec<bool>> {
    if probability.len() != cylinder.height * cylinder.width {
        return Err(Error::Model(format!(
            "the moving-object network gave {} probabilities for a {} × {} image",
            probability.len(),
            cylinder.height,
            cylinder.width
        )));
    }
    // Compared in float32, as the network answers.
    let threshold = threshold as f32;
    let cells = point_cells(points, channels, cylinder)?;
    Ok(cells
        .iter()
        .map(|&cell| usize::try_from(cell).is_ok_and(|cell| probability[cell] > threshold))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A stand-in network: cells whose kept point stands higher than `above` are moving.
    struct TallThings {
        cylinder: CylinderConfig,
        above: f32,
    }

    impl MovingObjectNetwork for TallThings {
        fn cylinder(&self) -> &CylinderConfig {
            &self.cylinder
        }

        fn probability(&self, range: &[f32], height: &[f32]) -> Result<Vec<f32>> {
            Ok(range
                .iter()
                .zip(height)
                .map(|(&r, &z)| if r > 0.0 && z > self.above { 0.9 } else { 0.1 })
                .collect())
        }
    }

    #[test]
    fn points_in_cells_the_network_flags_are_moving_and_the_rest_are_not() {
        let network = TallThings {
            cylinder: CylinderConfig::kitti(),
            above: 0.0,
        };
        let points = [
            [10.0, 0.0, -1.5, 0.3],   // ground ahead
            [10.0, 5.0, 0.2, 0.3],    // something tall beside it
            [10.0, 5.0, 0.2001, 0.3], // behind it in the same cell: flagged with it
            [f32::NAN, 0.0, 0.0, 0.3],
            [0.0, 0.0, 0.0, 0.3], // the origin: in no cell
        ];
        let moving = moving_points(&network, &points, 0.5).unwrap();
        assert_eq!(moving, [false, true, true, false, false]);
        assert!(moving_points(&network, &[], 0.5).unwrap().is_empty());
    }

    #[test]
    fn the_images_hold_each_cells_kept_point() {
        let cylinder = CylinderConfig::kitti();
        let points = [[10.0, 0.0, -1.5, 0.3], [20.0, 0.0, -3.0, 0.3]]; // the same ray: the nearer one is kept
        let (range, height) = network_images(points.as_flattened(), 4, &cylinder).unwrap();
        let filled: Vec<usize> = (0..range.len()).filter(|&i| range[i] > 0.0).collect();
        assert_eq!(filled.len(), 1);
        assert!((range[filled[0]] - (100.0f32 + 2.25).sqrt()).abs() < 1e-5);
        assert_eq!(height[filled[0]], -1.5);
        assert_eq!(height.iter().filter(|&&z| z != 0.0).count(), 1);
    }

    #[test]
    fn a_network_giving_the_wrong_number_of_cells_is_an_error() {
        struct Short(CylinderConfig);
        impl MovingObjectNetwork for Short {
            fn cylinder(&self) -> &CylinderConfig {
                &self.0
            }
            fn probability(&self, _: &[f32], _: &[f32]) -> Result<Vec<f32>> {
                Ok(vec![0.0; 3])
            }
        }
        let error = moving_points(
            &Short(CylinderConfig::kitti()),
            &[[10.0, 0.0, 0.0, 0.0]],
            0.5,
        )
        .unwrap_err();
        assert!(error.to_string().contains("3 probabilities"), "{error}");
    }
}
