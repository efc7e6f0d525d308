use nalgebra::{Point3, Vector3};

use super::reference::{atan2_lanes, cell_index, ATAN_ERROR_BOUND, LANES};
use super::*;
use crate::error::Error;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[test]
fn fast_arctangent_stays_within_its_bound_and_keeps_libm_signs() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let fast = |y: f64, x: f64| atan2_lanes(&[y; LANES], &[x; LANES])[LANES - 1];
    for _ in 0..200_000 {
        let (y, x) = (
            rng.random_range(-100.0..100.0),
            rng.random_range(-100.0..100.0),
        );
        assert!((fast(y, x) - f64::atan2(y, x)).abs() < ATAN_ERROR_BOUND / 4.0);
    }
    for (y, x) in [
        (0.0, -1.0),
        (-0.0, -1.0),
        (0.0, 1.0),
        (-0.0, 1.0),
        (1.0, 0.0),
        (-1.0, -0.0),
    ] {
        assert!((fast(y, x) - f64::atan2(y, x)).abs() < 1e-12, "({y}, {x})");
        assert_eq!(
            fast(y, x).is_sign_negative(),
            f64::atan2(y, x).is_sign_negative()
        );
    }
    // The origin has no direction: NaN, which `cell_index` hands to libm.
    assert!(fast(0.0, 0.0).is_nan());
    assert_eq!(cell_index(3.0, f64::NAN, 0.0, 0.0, 143.0), 3.0);
}

/// Runs both implementations in a one-thread and a three-thread pool (the two code paths) and
/// requires identical images, indices and counts.
fn assert_same_as_reference(points: &[f32], channels: usize, config: &CylinderConfig) {
    let expected = reference::project_flat(points, channels, config).unwrap();
    for threads in [1, 3] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let got = pool
            .install(|| project_flat(points, channels, config))
            .unwrap();
        if got != expected {
            let differing: Vec<usize> = (0..got.index.len())
                .filter(|&c| got.index[c] != expected.index[c])
                .take(5)
                .collect();
            panic!(
                "{config:?}, {threads} threads: cells {differing:?} differ (got {:?}, expected \
                 {:?}); counts {:?} vs {:?}",
                differing.iter().map(|&c| got.index[c]).collect::<Vec<_>>(),
                differing
                    .iter()
                    .map(|&c| expected.index[c])
                    .collect::<Vec<_>>(),
                (got.num_non_finite, got.num_out_of_view),
                (expected.num_non_finite, expected.num_out_of_view),
            );
        }
    }
}

fn read_scan(path: &std::path::Path) -> Option<Vec<f32>> {
    let bytes = std::fs::read(path).ok()?;
    Some(
        bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect(),
    )
}

/// Configs with every kind of edge: the presets, the full 360° grid (1801 and 1800 columns),
/// fields of view reaching the poles, coarse and odd resolutions (a boundary within 1e-6 rad of
/// ±180°), tiny crops.
fn edge_configs() -> Vec<CylinderConfig> {
    let kitti = CylinderConfig::kitti();
    vec![
        kitti,
        CylinderConfig::argoverse(),
        CylinderConfig {
            height: 68,
            width: 1801,
            ..kitti
        },
        CylinderConfig {
            width: 1800,
            ..kitti
        },
        CylinderConfig {
            fov_up_deg: 90.0,
            fov_down_deg: -90.0,
            vertical_resolution_deg: 1.0,
            horizontal_resolution_deg: 1.0,
            height: 181,
            width: 361,
        },
        CylinderConfig {
            fov_up_deg: 89.9,
            fov_down_deg: -89.7,
            vertical_resolution_deg: 0.7,
            horizontal_resolution_deg: 360.0 / 901.0,
            height: 200,
            width: 901,
        },
        CylinderConfig {
            fov_up_deg: 30.0,
            fov_down_deg: -30.0,
            vertical_resolution_deg: 7.0,
            horizontal_resolution_deg: 45.0,
            height: 9,
            width: 9,
        },
        CylinderConfig {
            fov_up_deg: 10.0,
            fov_down_deg: -10.0,
            vertical_resolution_deg: 20.0,
            horizontal_resolution_deg: 180.0,
            height: 2,
            width: 3,
        },
        CylinderConfig {
            height: 1,
            width: 1,
            ..kitti
        },
    ]
}

/// Points on and within a few float32 steps of every cell boundary and corner of `config`, plus
/// the poles, the origin, ±0 and the ±180° ray, huge, tiny and non-finite values.
fn adversarial_points(config: &CylinderConfig, rng: &mut ChaCha8Rng) -> Vec<f32> {
    let row0 = config.row_of_zero_elevation();
    let col0 = config.col_of_zero_azimuth();
    let d_phi = config.vertical_resolution_deg.to_radians();
    let d_theta = config.horizontal_resolution_deg.to_radians();
    let rows: Vec<f64> = (-1..=config.height as i64 + 1)
        .map(|k| (row0 + 0.5 - k as f64) * d_phi)
        .collect();
    let cols: Vec<f64> = (-1..=config.width as i64 + 1)
        .map(|k| (col0 + 0.5 - k as f64) * d_theta)
        .collect();
    let nudge = |v: f32, steps: i32| -> f32 {
        let mut v = v;
        for _ in 0..steps.abs() {
            v = if steps > 0 {
                v.next_up()
            } else {
                v.next_down()
            };
        }
        v
    };
    let mut points = Vec::new();
    let push = |p: [f32; 3], points: &mut Vec<f32>| {
        points.extend_from_slice(&[p[0], p[1], p[2], 0.5]);
    };
    for _ in 0..4000 {
        // A boundary of one axis (or both), random position along the other, a few ulps off.
        let elevation = if rng.random_bool(0.5) {
            rows[rng.random_range(0..rows.len())]
        } else {
            rng.random_range(-1.6..1.6)
        };
        let azimuth = if rng.random_bool(0.7) {
            cols[rng.random_range(0..cols.len())]
        } else {
            rng.random_range(-3.2..3.2)
        };
        let range = [1e-3, 0.7, 13.0, 80.0, 1e6][rng.random_range(0..5)];
        let (se, ce) = f64::sin_cos(elevation);
        let (sa, ca) = f64::sin_cos(azimuth);
        let base = [
            (range * ce * ca) as f32,
            (range * ce * sa) as f32,
            (range * se) as f32,
        ];
        for _ in 0..3 {
            let p = [
                nudge(base[0], rng.random_range(-2..=2)),
                nudge(base[1], rng.random_range(-2..=2)),
                nudge(base[2], rng.random_range(-2..=2)),
            ];
            push(p, &mut points);
        }
    }
    let specials = [
        0.0f32,
        -0.0,
        1.0,
        -1.0,
        1e-45,
        -1e-45,
        1e-38,
        3e38,
        -3e38,
        1e19,
        f32::MAX,
        f32::MIN_POSITIVE,
    ];
    for &x in &specials {
        for &y in &specials {
            for &z in &specials {
                push([x, y, z], &mut points);
            }
        }
    }
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        push([bad, 1.0, 1.0], &mut points);
        push([1.0, bad, 1.0], &mut points);
        push([1.0, 1.0, bad], &mut points);
        points.extend_from_slice(&[1.0, 1.0, 1.0, bad]);
    }
    // Duplicates and equal ranges in one cell: the tie rule.
    for _ in 0..3 {
        push([5.0, 0.01, -0.3], &mut points);
        push([5.0, -0.01, -0.3], &mut points);
    }
    points
}

/// A flat N×4 scan as N×3: the same points given without reflectance.
fn without_reflectance(points: &[f32]) -> Vec<f32> {
    points
        .chunks_exact(4)
        .flat_map(|p| [p[0], p[1], p[2]])
        .collect()
}

#[test]
fn table_lookup_equals_the_arctangent_reference_on_adversarial_points() {
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    for config in edge_configs() {
        config.validate().unwrap();
        let points = adversarial_points(&config, &mut rng);
        assert_same_as_reference(&points, 4, &config);
        let xyz = without_reflectance(&points);
        assert_same_as_reference(&xyz, 3, &config);
    }
}

#[test]
fn table_lookup_equals_the_arctangent_reference_on_real_scans() {
    let data = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data");
    let scans: Vec<Vec<f32>> = [
        "kitti_raw_static/0000000000.bin",
        "kitti_raw_static/0000000005.bin",
        "semantickitti_08_pair/000720.bin",
        "semantickitti_08_pair/001500.bin",
    ]
    .iter()
    .filter_map(|name| read_scan(&data.join(name)))
    .collect();
    if scans.is_empty() {
        eprintln!("no KITTI scans under {}: skipped", data.display());
        return;
    }
    for scan in &scans {
        for config in edge_configs() {
            assert_same_as_reference(scan, 4, &config);
        }
    }
}

#[test]
fn fast_floor_equals_floor() {
    for x in [
        -2.5,
        -1.0,
        -0.5,
        -0.0,
        0.0,
        0.3,
        1.0,
        1.5,
        1e15,
        -1e15 - 0.5,
        1e300,
        f64::INFINITY,
    ] {
        assert_eq!(floor_fast(x), x.floor(), "{x}");
    }
    assert!(floor_fast(f64::NAN).is_nan());
}

#[test]
fn kitti_preset_matches_the_paper() {
    let config = CylinderConfig::kitti();
    assert_eq!((config.full_height(), config.full_width()), (68, 1801));
    assert_eq!((config.height, config.width), (64, 1792));
    assert_eq!((config.crop_top(), config.crop_left()), (2, 4));
    // Row 0 is the highest elevation: +2.0° top beam → full row 0, cropped row −2 → +1.2° at row 0.
    assert_eq!(config.row_of_zero_elevation(), 3.0);
    assert_eq!(config.col_of_zero_azimuth(), 896.0);
    assert!(!config.wraps_azimuth());
    assert_eq!(config.column_period(), None);
    let full = CylinderConfig {
        height: 68,
        width: 1801,
        ..config
    };
    assert_eq!(full.column_period(), Some(1800));
    let argoverse = CylinderConfig::argoverse();
    assert_eq!(
        (argoverse.full_height(), argoverse.full_width()),
        (68, 1801)
    );
    argoverse.validate().unwrap();
}

#[test]
fn cell_centres_stand_for_the_documented_angles() {
    let config = CylinderConfig::kitti();
    // Straight ahead at zero elevation: column col₀, row row₀.
    let (row, col) = config.locate(&Point3::new(10.0, 0.0, 0.0)).unwrap();
    assert_eq!((row, col), (3.0, 896.0));
    // Looking left (+y) is azimuth +90° → 450 columns to the left of forward.
    let (_, col) = config.locate(&Point3::new(0.0, 5.0, 0.0)).unwrap();
    assert!((col - (896.0 - 450.0)).abs() < 1e-9);
    // Upwards is a lower row.
    let (row, _) = config.locate(&Point3::new(10.0, 0.0, 1.0)).unwrap();
    assert!(row < 3.0);
}

#[test]
fn round_trip_stays_within_the_cells_angular_bound() {
    let config = CylinderConfig::kitti();
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let points: Vec<[f32; 4]> = (0..20_000)
        .map(|_| {
            let azimuth = rng.random_range(-180.0f64..180.0).to_radians();
            let elevation = rng.random_range(-24.0f64..1.2).to_radians();
            let range = rng.random_range(1.0f64..80.0);
            [
                (range * elevation.cos() * azimuth.cos()) as f32,
                (range * elevation.cos() * azimuth.sin()) as f32,
                (range * elevation.sin()) as f32,
                rng.random::<f32>(),
            ]
        })
        .collect();
    let projection = project(&points, &config).unwrap();
    let half_diagonal =
        (config.vertical_resolution_deg.powi(2) + config.horizontal_resolution_deg.powi(2)).sqrt()
            / 2.0;
    let mut checked = 0;
    for cell in 0..projection.index.len() {
        let index = projection.index[cell];
        if index < 0 {
            continue;
        }
        let (row, col) = (cell / config.width, cell % config.width);
        let p = points[index as usize];
        let original = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        let back = config
            .unproject(row as f64, col as f64, projection.range[cell] as f64)
            .coords;
        assert!((back.norm() - original.norm()).abs() < 1e-4);
        let angle = original.angle(&back).to_degrees();
        assert!(
            angle <= half_diagonal + 1e-4,
            "angle {angle} beyond {half_diagonal}"
        );
        assert_eq!(projection.reflectance[cell], p[3]);
        checked += 1;
    }
    assert!(checked > 10_000);
}

#[test]
fn closest_point_wins_and_bad_points_are_counted() {
    let config = CylinderConfig::kitti();
    let points = [
        [10.0, 0.0, 0.0, 0.1],
        [5.0, 0.0, 0.0, 0.2],
        [7.0, 0.0, 0.0, 0.3],
        [f32::NAN, 0.0, 0.0, 0.0],
        [1.0, 0.0, f32::INFINITY, 0.0],
        [0.0, 0.0, 0.0, 0.0],
        [0.0, 0.0, 10.0, 0.0],  // straight up: outside the field of view
        [-10.0, 0.0, 0.0, 0.0], // straight back: cropped away
    ];
    let projection = project(&points, &config).unwrap();
    assert_eq!(projection.num_non_finite, 2);
    assert_eq!(projection.num_out_of_view, 3);
    assert_eq!(projection.num_valid(), 1);
    let cell = 3 * config.width + 896;
    assert_eq!(projection.index[cell], 1);
    assert_eq!(projection.range[cell], 5.0);
    assert_eq!(projection.reflectance[cell], 0.2);
}

#[test]
fn empty_scan_gives_an_empty_image_and_bad_configs_are_rejected() {
    let config = CylinderConfig::kitti();
    let projection = project(&[], &config).unwrap();
    assert_eq!(projection.num_valid(), 0);
    assert!(projection.range.iter().all(|&r| r == 0.0));
    let too_wide = CylinderConfig {
        width: 1802,
        ..config
    };
    assert!(matches!(
        too_wide.validate(),
        Err(Error::InvalidArgument {
            argument: "width",
            ..
        })
    ));
    let bad = CylinderConfig {
        vertical_resolution_deg: 0.0,
        ..config
    };
    assert!(bad.validate().is_err());
    assert!(project_flat(&[1.0; 10], 4, &config).is_err());
    assert!(project_flat(&[1.0; 10], 5, &config).is_err());
    // Images too large to allocate are refused by the validation, naming the setting, before any
    // function allocates them.
    let huge = CylinderConfig {
        fov_up_deg: 0.5,
        fov_down_deg: -0.5,
        vertical_resolution_deg: 0.001,
        horizontal_resolution_deg: 1e-4,
        height: 1000,
        width: 3_600_000,
    };
    let too_many_cells = Err(Error::InvalidArgument {
        argument: "height * width",
        reason: "1000 * 3600000 cells, more than the 67108864 (2^26) an image may have".into(),
    });
    assert_eq!(huge.validate(), too_many_cells);
    assert!(matches!(
        project_flat(&[], 4, &huge),
        Err(Error::InvalidArgument {
            argument: "height * width",
            ..
        })
    ));
    let wide = CylinderConfig {
        horizontal_resolution_deg: 1e-5,
        width: 30_000_000,
        ..config
    };
    assert!(matches!(
        wide.validate(),
        Err(Error::InvalidArgument {
            argument: "height * width",
            ..
        })
    ));
    for (vertical, horizontal, at_fault) in [
        (0.4, 1e-9, "horizontal_resolution_deg"),
        (1e-300, 0.2, "vertical_resolution_deg"),
        (0.4, 5e-324, "horizontal_resolution_deg"),
    ] {
        let fine = CylinderConfig {
            vertical_resolution_deg: vertical,
            horizontal_resolution_deg: horizontal,
            ..config
        };
        assert!(
            matches!(fine.validate(), Err(Error::InvalidArgument { argument, .. }) if argument == at_fault),
            "{vertical} x {horizontal}: {:?}",
            fine.validate()
        );
    }
    // Up to the cap, a large image is fine.
    let largest = CylinderConfig {
        horizontal_resolution_deg: 0.01,
        width: 36_001,
        height: 64,
        ..config
    };
    largest.validate().unwrap();
}

#[test]
fn unproject_many_checks_its_input() {
    let config = CylinderConfig::kitti();
    let points = unproject_many(&[3.0], &[896.0], &[2.0], &config).unwrap();
    assert!((points[0] - Point3::new(2.0, 0.0, 0.0)).norm() < 1e-12);
    assert!(unproject_many(&[3.0], &[], &[2.0], &config).is_err());
    assert!(unproject_many(&[3.0], &[1.0], &[f64::NAN], &config).is_err());
}

/// `point_cells` agrees with the reference projection: every kept point lies in its own cell, every
/// point in a cell is no closer than the one kept there, and exactly the dropped points get −1.
fn assert_cells_agree_with_reference(points: &[f32], channels: usize, config: &CylinderConfig) {
    let image = reference::project_flat(points, channels, config).unwrap();
    let cells = point_cells(points, channels, config).unwrap();
    assert_eq!(cells.len(), points.len() / channels);
    for (cell, &kept) in image.index.iter().enumerate() {
        if kept >= 0 {
            assert_eq!(
                cells[kept as usize], cell as i64,
                "{config:?}: kept point {kept}"
            );
        }
    }
    let range = |i: usize| {
        let p = &points[i * channels..i * channels + 3];
        let (x, y, z) = (f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
        (x * x + y * y + z * z).sqrt()
    };
    for (i, &cell) in cells.iter().enumerate() {
        if cell >= 0 {
            let kept = image.index[cell as usize];
            assert!(
                kept >= 0,
                "{config:?}: point {i} in cell {cell}, which the projection left empty"
            );
            // The projection compares float32 ranges: equal within their rounding.
            assert!(
                range(kept as usize) <= range(i) * (1.0 + 1e-6),
                "{config:?}: point {i} closer than cell {cell}'s"
            );
        }
    }
    let dropped = cells.iter().filter(|&&c| c < 0).count();
    assert_eq!(
        dropped,
        image.num_non_finite + image.num_out_of_view,
        "{config:?}"
    );
}

#[test]
fn point_cells_follow_the_projection_on_adversarial_points() {
    let mut rng = ChaCha8Rng::seed_from_u64(23);
    for config in edge_configs() {
        let points = adversarial_points(&config, &mut rng);
        assert_cells_agree_with_reference(&points, 4, &config);
        let xyz = without_reflectance(&points);
        assert_cells_agree_with_reference(&xyz, 3, &config);
    }
}

#[test]
fn point_cells_refuse_what_the_projection_refuses() {
    let config = CylinderConfig::kitti();
    assert!(point_cells(&[1.0, 2.0, 3.0, 0.5, 1.0], 4, &config).is_err());
    assert!(point_cells(&[1.0, 2.0], 2, &config).is_err());
    let huge = CylinderConfig {
        horizontal_resolution_deg: 1e-5,
        width: 30_000_000,
        ..config
    };
    assert!(point_cells(&[1.0, 2.0, 3.0], 3, &huge).is_err());
    assert!(point_cells(&[], 3, &config).unwrap().is_empty());
}
