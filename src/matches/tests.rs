use super::*;

#[test]
fn direction_table_equals_the_inverse_projection() {
    let config = CylinderConfig::kitti();
    let table = DirectionTable::new(&config);
    for (row, col) in [
        (0.0, 0.0),
        (3.0, 896.0),
        (10.3, 5.7),
        (63.49, 1791.49),
        (-0.4, 100.25),
        (70.2, -30.7),
    ] {
        let exact = config.unproject(row, col, 1.0).coords;
        assert!(
            (table.at(row, col) - exact).norm() < 1e-14,
            "({row}, {col})"
        );
    }
}

#[test]
fn zero_flow_on_identical_images_gives_identical_points() {
    let config = CylinderConfig::kitti();
    let n = config.height * config.width;
    let range: Vec<f32> = (0..n)
        .map(|i| {
            if i % 7 == 0 {
                0.0
            } else {
                5.0 + (i % 13) as f32 * 0.01
            }
        })
        .collect();
    let flow = vec![0.0f32; 2 * n];
    let confidence: Vec<f32> = (0..n).map(|i| (i % 10) as f32 / 10.0).collect();
    let decoded = decode_matches(
        &range,
        &range,
        &flow,
        &confidence,
        None,
        &config,
        &DecodeConfig {
            min_confidence: 0.5,
            ..Default::default()
        },
    )
    .unwrap();
    let expected = (0..n)
        .filter(|&i| i % 7 != 0 && confidence[i] >= 0.5)
        .count();
    assert_eq!(decoded.len(), expected);
    for i in 0..decoded.len() {
        assert!((decoded.source[i] - decoded.target[i]).norm() < 1e-12);
        let [row, col] = decoded.cells[i];
        assert!(confidence[row * config.width + col] >= 0.5);
    }
    let mut mask = vec![false; n];
    mask[..n / 2].fill(true);
    let masked = decode_matches(
        &range,
        &range,
        &flow,
        &confidence,
        Some(&mask),
        &config,
        &DecodeConfig::default(),
    )
    .unwrap();
    assert!(masked
        .cells
        .iter()
        .all(|&[row, col]| row * config.width + col >= n / 2));
}

#[test]
fn fused_selection_equals_decoding_then_nms() {
    // Cropped (no wrap) and the full 360° grid (wraps: NMS across the seam).
    let full = CylinderConfig {
        height: 68,
        width: 1801,
        ..CylinderConfig::kitti()
    };
    for config in [CylinderConfig::kitti(), full] {
        fused_selection_equals_decoding_then_nms_for(config);
    }
}

fn fused_selection_equals_decoding_then_nms_for(config: CylinderConfig) {
    let n = config.height * config.width;
    let mut state = 12345u64;
    let mut random = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 33) as f32 / (1u64 << 31) as f32
    };
    // Holes in both images and flows that leave the image make many cells undecodable.
    let mut range_image = |holes: f32| -> Vec<f32> {
        (0..n)
            .map(|_| {
                if random() < holes {
                    0.0
                } else {
                    5.0 + 20.0 * random()
                }
            })
            .collect()
    };
    let ref_range = range_image(0.3);
    let tgt_range = range_image(0.5);
    let flow: Vec<f32> = (0..2 * n).map(|_| (random() - 0.5) * 8.0).collect();
    // Coarse confidences: many ties.
    let confidence: Vec<f32> = (0..n).map(|_| (random() * 20.0).floor() / 20.0).collect();
    let decode = DecodeConfig {
        min_confidence: 0.2,
        ..Default::default()
    };
    let all = decode_matches(
        &ref_range,
        &tgt_range,
        &flow,
        &confidence,
        None,
        &config,
        &decode,
    )
    .unwrap();
    for (radius, top_n) in [(1, 1000), (2, 300), (0, 50_000), (1, 10)] {
        let rows: Vec<i64> = all.cells.iter().map(|c| c[0] as i64).collect();
        let cols: Vec<i64> = all.cells.iter().map(|c| c[1] as i64).collect();
        let kept = crate::nms::nms_wrapping(
            &rows,
            &cols,
            &all.confidence,
            radius,
            Some(top_n),
            config.column_period(),
        )
        .unwrap();
        let fused = select_matches(
            &ref_range,
            &tgt_range,
            &flow,
            &confidence,
            None,
            &config,
            &decode,
            radius,
            top_n,
        )
        .unwrap();
        assert_eq!(fused.len(), kept.len());
        for (k, &i) in kept.iter().enumerate() {
            assert_eq!(fused.cells[k], all.cells[i]);
            assert_eq!(fused.source[k], all.source[i]);
            assert_eq!(fused.target[k], all.target[i]);
        }
    }
}

#[test]
fn range_sampling_does_not_blend_across_depth_edges() {
    let config = CylinderConfig {
        height: 2,
        width: 2,
        ..CylinderConfig::kitti()
    };
    // Smooth patch: bilinear.
    let smooth = [10.0, 10.4, 10.2, 10.6];
    let r = sample_range(&smooth, 0.5, 0.5, &config, 0.1).unwrap();
    assert!((r - 10.3).abs() < 1e-6);
    // Depth edge: the nearest valid corner, never an average.
    let edge = [10.0, 30.0, 10.0, 30.0];
    assert_eq!(sample_range(&edge, 0.2, 0.7, &config, 0.1), Some(30.0));
    assert_eq!(sample_range(&edge, 0.2, 0.3, &config, 0.1), Some(10.0));
    // Holes: nearest valid corner; all empty → None.
    let holes = [0.0, 0.0, 0.0, 7.0];
    assert_eq!(sample_range(&holes, 0.1, 0.1, &config, 0.1), Some(7.0));
    assert_eq!(sample_range(&[0.0; 4], 0.5, 0.5, &config, 0.1), None);
    // Outside the image.
    assert_eq!(sample_range(&smooth, -0.6, 0.0, &config, 0.1), None);
    assert_eq!(sample_range(&smooth, 0.0, 1.6, &config, 0.1), None);
}

#[test]
fn known_flow_gives_the_moved_points() {
    // A flow of +2 columns on a constant-range image: targets are the reference points yawed by
    // −2·Δθ (columns grow as azimuth falls).
    let config = CylinderConfig::kitti();
    let n = config.height * config.width;
    let range = vec![12.0f32; n];
    let mut flow = vec![0.0f32; 2 * n];
    flow[n..].fill(2.0);
    let decoded = decode_matches(
        &range,
        &range,
        &flow,
        &vec![1.0; n],
        None,
        &config,
        &DecodeConfig::default(),
    )
    .unwrap();
    assert_eq!(decoded.len(), config.height * (config.width - 2));
    let yaw =
        nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), -(2.0 * 0.2f64).to_radians());
    for i in (0..decoded.len()).step_by(997) {
        assert!((yaw * decoded.source[i] - decoded.target[i]).norm() < 1e-9);
    }
    assert!(decode_matches(
        &range,
        &range,
        &flow[1..],
        &vec![1.0; n],
        None,
        &config,
        &DecodeConfig::default()
    )
    .is_err());
}
