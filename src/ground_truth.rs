#![forbid(unsafe_code)]
//! Training ground truth (paper Eq. 5–8, §III-C-c): where every reference cell lands in the target
//! image under a known motion `T_tgt_ref`.
//!
//! For each valid reference cell `c_r` (range `D_r > 0`): the virtual point `p'_r = Φ⁻¹(c_r, D_r)` at the
//! cell centre, `p_t = T_tgt_ref · p'_r`, the sub-pixel `c_t = Φ(p_t)`. The pair is kept only if the
//! cell nearest to `c_t` lies inside the (cropped) target image, is valid, and
//! `|D_t(c_t) − ‖p_t‖| < max_range_error` (the paper's 0.1 m). The flow is `c_t − c_r` in cropped-image
//! pixels, the column difference taken the short way round (within half a turn). When the image covers
//! the full circle ([`CylinderConfig::wraps_azimuth`]) that path wraps around the image's edge;
//! otherwise a `c_t` whose path leaves the crop is invalid (even if it would re-enter at the far side).

use nalgebra::Isometry3;
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::projection::CylinderConfig;

/// Per-cell ground-truth flow and validity of a pair.
#[derive(Debug, Clone, PartialEq)]
pub struct GroundTruthFlow {
    /// Rows of the image.
    pub height: usize,
    /// Columns of the image.
    pub width: usize,
    /// `2 × height × width`, channel-major: channel 0 Δrow, channel 1 Δcol (pixels); 0 where invalid.
    pub flow: Vec<f32>,
    /// `height × width`, row-major: true where the flow is a valid training target.
    pub valid: Vec<bool>,
}

/// Checks that a range image has the config's size and only finite, non-negative values.
pub(crate) fn check_range_image(
    argument: &'static str,
    range: &[f32],
    config: &CylinderConfig,
) -> Result<()> {
    check_non_negative_image(
        argument,
        range,
        config,
        "ranges must be finite and >= 0; 0 = empty",
    )
}

/// Checks that an image of `config` has its size and only finite, non-negative values (`rule` says so
/// in the error).
pub(crate) fn check_non_negative_image(
    argument: &'static str,
    values: &[f32],
    config: &CylinderConfig,
    rule: &str,
) -> Result<()> {
    if values.len() != config.height * config.width {
        return Err(Error::invalid(
            argument,
            format!(
                "has {} cells, the config's image is {}x{} = {}",
                values.len(),
                config.height,
                config.width,
                config.height * config.width
            ),
        ));
    }
    if let Some(i) = values.iter().position(|r| !(r.is_finite() && *r >= 0.0)) {
        return Err(Error::invalid(
            argument,
            format!("cell {i} holds {} ({rule})", values[i]),
        ));
    }
    Ok(())
}

/// Computes the ground-truth flow (Eq. 5–8) from the reference to the target range image under
/// `t_tgt_ref` (`p_t = T p_r`). Both images are row-major `config.height × config.width`, 0 = empty.
/// Parallel over rows in the caller's rayon pool.
pub fn ground_truth_flow(
    ref_range: &[f32],
    tgt_range: &[f32],
    t_tgt_ref: &Isometry3<f64>,
    config: &CylinderConfig,
    max_range_error: f64,
) -> Result<GroundTruthFlow> {
    config.validate()?;
    check_range_image("ref_range", ref_range, config)?;
    check_range_image("tgt_range", tgt_range, config)?;
    if !(max_range_error.is_finite() && max_range_error > 0.0) {
        return Err(Error::invalid(
            "max_range_error",
            format!("must be finite and > 0, got {max_range_error}"),
        ));
    }
    let (height, width) = (config.height, config.width);
    let wraps = config.wraps_azimuth();
    let period = config.columns_per_turn();

    let mut flow = vec![0.0f32; 2 * height * width];
    let mut valid = vec![false; height * width];
    let (flow_rows, flow_cols) = flow.split_at_mut(height * width);
    flow_rows
        .par_chunks_mut(width)
        .zip(flow_cols.par_chunks_mut(width))
        .zip(valid.par_chunks_mut(width))
        .enumerate()
        .for_each(|(row, ((d_rows, d_cols), valid_row))| {
            for col in 0..width {
                let range = ref_range[row * width + col];
                if range <= 0.0 {
                    continue;
                }
                let virtual_point = config.unproject(row as f64, col as f64, range as f64);
                let p_t = t_tgt_ref * virtual_point;
                let Some((row_t, col_t)) = config.locate(&p_t) else {
                    continue;
                };
                // The short way round: a point crossing the back of the sensor moves a few columns,
                // not a whole turn. In a cropped image that path may leave the crop (→ invalid).
                let d_col = (col_t - col as f64 + period / 2.0).rem_euclid(period) - period / 2.0;
                let mut col_t = col as f64 + d_col;
                if wraps {
                    col_t = (col_t + 0.5).rem_euclid(period) - 0.5;
                }
                let Some((cell_row, cell_col)) = config.cell_of(row_t, col_t) else {
                    continue;
                };
                let range_t = tgt_range[cell_row * width + cell_col];
                if range_t <= 0.0 || (range_t as f64 - p_t.coords.norm()).abs() >= max_range_error {
                    continue;
                }
                d_rows[col] = (row_t - row as f64) as f32;
                d_cols[col] = d_col as f32;
                valid_row[col] = true;
            }
        });
    Ok(GroundTruthFlow {
        height,
        width,
        flow,
        valid,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::projection::project;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A closed room of walls, floor and ceiling: every direction sees a surface.
    fn room_scan(rng: &mut ChaCha8Rng, n: usize) -> Vec<[f32; 4]> {
        (0..n)
            .map(|_| {
                let azimuth = rng.random_range(-180.0f64..180.0).to_radians();
                let elevation = rng.random_range(-24.0f64..1.5).to_radians();
                let d = Vector3::new(
                    elevation.cos() * azimuth.cos(),
                    elevation.cos() * azimuth.sin(),
                    elevation.sin(),
                );
                // Box |x| <= 20, |y| <= 12, z >= -1.7.
                let mut t = f64::INFINITY;
                for (component, limit) in [(d.x, 20.0), (d.y, 12.0)] {
                    if component.abs() > 1e-9 {
                        t = t.min(limit / component.abs());
                    }
                }
                if d.z < -1e-9 {
                    t = t.min(1.7 / -d.z);
                }
                let p = d * t;
                [p.x as f32, p.y as f32, p.z as f32, 0.5]
            })
            .collect()
    }

    #[test]
    fn identity_motion_gives_zero_flow_everywhere_valid() {
        let config = CylinderConfig::kitti();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let scan = room_scan(&mut rng, 150_000);
        let image = project(&scan, &config).unwrap();
        let gt = ground_truth_flow(
            &image.range,
            &image.range,
            &Isometry3::identity(),
            &config,
            0.1,
        )
        .unwrap();
        let valid_cells = image.range.iter().filter(|&&r| r > 0.0).count();
        assert_eq!(gt.valid.iter().filter(|&&v| v).count(), valid_cells);
        assert!(gt.flow.iter().all(|f| f.abs() < 1e-3));
    }

    #[test]
    fn a_pure_yaw_shifts_columns_and_wraps_in_a_full_circle() {
        // Full-circle image: p_t = R p_r with R a yaw of +2° raises every azimuth by 2°, i.e. moves it
        // 10 columns to the left (Δcol = −10), wrapping around the back.
        let config = CylinderConfig {
            width: 1801,
            height: 64,
            ..CylinderConfig::kitti()
        };
        assert!(config.wraps_azimuth());
        let mut range = vec![0.0f32; config.height * config.width];
        for cell in range.iter_mut() {
            *cell = 10.0;
        }
        let yaw = Isometry3::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 2.0f64.to_radians()),
        );
        let gt = ground_truth_flow(&range, &range, &yaw, &config, 0.1).unwrap();
        let n = config.height * config.width;
        assert!(gt.valid.iter().all(|&v| v));
        assert!(
            gt.flow[n..].iter().all(|&d| (d + 10.0).abs() < 1e-3),
            "Δcol must be −10 everywhere"
        );
        assert!(gt.flow[..n].iter().all(|&d| d.abs() < 1e-3));

        // The cropped image loses the cells that leave it through the back.
        let cropped = CylinderConfig::kitti();
        let range = vec![10.0f32; cropped.height * cropped.width];
        let gt = ground_truth_flow(&range, &range, &yaw, &cropped, 0.1).unwrap();
        for row in 0..cropped.height {
            assert!(!gt.valid[row * cropped.width]);
            assert!(!gt.valid[row * cropped.width + 9]);
            assert!(gt.valid[row * cropped.width + 10]);
        }
    }

    #[test]
    fn known_translation_lands_where_the_equations_say() {
        let config = CylinderConfig::kitti();
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let scan_ref = room_scan(&mut rng, 200_000);
        let t_tgt_ref = Isometry3::new(Vector3::new(-0.8, 0.1, 0.0), Vector3::new(0.0, 0.0, 0.02));
        let scan_tgt: Vec<[f32; 4]> = room_scan(&mut rng, 200_000)
            .into_iter()
            .map(|p| {
                // The same room seen from the moved sensor: target points = T · (room points).
                let q = t_tgt_ref * nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
                [q.x as f32, q.y as f32, q.z as f32, p[3]]
            })
            .collect();
        let image_ref = project(&scan_ref, &config).unwrap();
        let image_tgt = project(&scan_tgt, &config).unwrap();
        let gt = ground_truth_flow(&image_ref.range, &image_tgt.range, &t_tgt_ref, &config, 0.1)
            .unwrap();
        let n = config.height * config.width;
        let mut checked = 0;
        for cell in 0..n {
            if !gt.valid[cell] {
                continue;
            }
            let (row, col) = ((cell / config.width) as f64, (cell % config.width) as f64);
            let p = config.unproject(row, col, image_ref.range[cell] as f64);
            let (row_t, col_t) = config.locate(&(t_tgt_ref * p)).unwrap();
            assert!((gt.flow[cell] as f64 - (row_t - row)).abs() < 1e-3);
            assert!((gt.flow[n + cell] as f64 - (col_t - col)).abs() < 1e-3);
            checked += 1;
        }
        assert!(checked > n / 4, "only {checked} valid cells");
    }

    #[test]
    fn bad_images_are_rejected() {
        let config = CylinderConfig::kitti();
        let good = vec![1.0f32; config.height * config.width];
        let mut nan = good.clone();
        nan[5] = f32::NAN;
        let id = Isometry3::identity();
        assert!(matches!(
            ground_truth_flow(&good[1..], &good, &id, &config, 0.1),
            Err(Error::InvalidArgument {
                argument: "ref_range",
                ..
            })
        ));
        assert!(matches!(
            ground_truth_flow(&good, &nan, &id, &config, 0.1),
            Err(Error::InvalidArgument {
                argument: "tgt_range",
                ..
            })
        ));
        assert!(ground_truth_flow(&good, &good, &id, &config, 0.0).is_err());
    }
}
