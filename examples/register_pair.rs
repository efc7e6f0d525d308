//! Registers two KITTI `.bin` scans with the `dmlo_rs` core alone (no Python, no network).
//!
//! ```text
//! cargo run --release --example register_pair -- A.bin B.bin [--move-b YAW_DEG TX TY TZ]
//! ```
//!
//! Without the learned matcher, a stand-in makes the per-cell flow and confidence the network would:
//! each cell of A, moved by the current motion estimate, is matched to the nearest 3D point among the
//! cells of B in a window around where it lands (±2 rows, ±24 columns). The flow is decoded into 3D
//! matches, thinned by NMS and solved by RANSAC + the SVD rigid solve, for 24 ICP-like rounds from
//! the identity. This stand-in has ICP's small basin (it recovers 1° of yaw and 0.3 m, not 3° and
//! 1 m); the learned matcher is what makes DMLO global.
//! `--move-b` first moves B's points by a known motion (yaw about z, then translation), so the printed
//! estimate can be checked against it (for two scans of a standing car it should equal that motion).

use std::process::ExitCode;

use dmlo_rs::matches::{decode_matches, DecodeConfig};
use dmlo_rs::nms::nms;
use dmlo_rs::projection::{project, CylinderConfig, Projection};
use dmlo_rs::ransac::{ransac_rigid, RansacConfig};
use nalgebra::{Isometry3, Point3, Vector3};
use rayon::prelude::*;

/// The matcher's stand-in: per cell of A, `(flow [2·H·W], confidence [H·W])` towards the cell of B whose
/// point is nearest to `t_b_a · p'_A` within the search window; a pseudo-random confidence above 0.5
/// for a match within `gate` metres, 0 otherwise.
fn nearest_cell_flow(
    a: &Projection,
    b: &Projection,
    t_b_a: &Isometry3<f64>,
    config: &CylinderConfig,
    gate: f64,
) -> (Vec<f32>, Vec<f32>) {
    let (h, w) = (config.height as i64, config.width as i64);
    let points_b: Vec<Option<Point3<f64>>> = (0..b.range.len())
        .map(|i| {
            let range = b.range[i] as f64;
            (range > 0.0).then(|| config.unproject((i as i64 / w) as f64, (i as i64 % w) as f64, range))
        })
        .collect();
    let per_cell: Vec<(f32, f32, f32)> = (0..a.range.len())
        .into_par_iter()
        .map(|i| {
            let (row, col) = (i as i64 / w, i as i64 % w);
            if a.range[i] <= 0.0 {
                return (0.0, 0.0, 0.0);
            }
            let moved = t_b_a * config.unproject(row as f64, col as f64, a.range[i] as f64);
            let Some((row_p, col_p)) = config.locate(&moved) else { return (0.0, 0.0, 0.0) };
            let (row_p, col_p) = (row_p.round() as i64, col_p.round() as i64);
            let mut best = (gate * gate, None);
            for r in (row_p - 2).max(0)..=(row_p + 2).min(h - 1) {
                for c in (col_p - 24).max(0)..=(col_p + 24).min(w - 1) {
                    if let Some(q) = points_b[(r * w + c) as usize] {
                        let d = (q - moved).norm_squared();
                        if d < best.0 {
                            best = (d, Some((r, c)));
                        }
                    }
                }
            }
            match best {
                // A pseudo-random confidence in (0.5, 1] (a hash of the cell): NMS then thins the
                // matches uniformly instead of favouring the first rows.
                (_, Some((r, c))) => {
                    let hash = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40;
                    ((r - row) as f32, (c - col) as f32, 0.5 + 0.5 * (hash as f32 + 1.0) / (1u64 << 24) as f32)
                }
                _ => (0.0, 0.0, 0.0),
            }
        })
        .collect();
    let mut flow: Vec<f32> = per_cell.iter().map(|c| c.0).collect();
    flow.extend(per_cell.iter().map(|c| c.1));
    (flow, per_cell.iter().map(|c| c.2).collect())
}

fn read_scan(path: &str) -> Result<Vec<[f32; 4]>, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{path}: {e}"))?;
    if bytes.len() % 16 != 0 {
        return Err(format!("{path}: {} bytes is not a whole number of 16-byte points (truncated?)", bytes.len()));
    }
    Ok(bytes
        .chunks_exact(16)
        .map(|p| {
            let value = |k: usize| f32::from_le_bytes([p[4 * k], p[4 * k + 1], p[4 * k + 2], p[4 * k + 3]]);
            [value(0), value(1), value(2), value(3)]
        })
        .collect())
}

fn parse_motion(args: &[String]) -> Result<Option<Isometry3<f64>>, String> {
    match args {
        [] => Ok(None),
        [flag, values @ ..] if flag == "--move-b" && values.len() == 4 => {
            let v: Vec<f64> = values
                .iter()
                .map(|s| s.parse::<f64>().map_err(|e| format!("--move-b: {s:?}: {e}")))
                .collect::<Result<_, _>>()?;
            Ok(Some(Isometry3::new(Vector3::new(v[1], v[2], v[3]), Vector3::z() * v[0].to_radians())))
        }
        _ => Err("usage: register_pair A.bin B.bin [--move-b YAW_DEG TX TY TZ]".into()),
    }
}

fn run(args: &[String]) -> Result<(), Box<dyn std::error::Error>> {
    let [a_path, b_path, rest @ ..] = args else {
        return Err("usage: register_pair A.bin B.bin [--move-b YAW_DEG TX TY TZ]".into());
    };
    let known_motion = parse_motion(rest)?;
    let scan_a = read_scan(a_path)?;
    let mut scan_b = read_scan(b_path)?;
    if let Some(motion) = &known_motion {
        for p in scan_b.iter_mut() {
            let q = motion * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            *p = [q.x as f32, q.y as f32, q.z as f32, p[3]];
        }
    }

    let config = CylinderConfig::kitti();
    let image_a = project(&scan_a, &config)?;
    let image_b = project(&scan_b, &config)?;
    println!(
        "A: {} points → {} cells; B: {} points → {} cells",
        scan_a.len(),
        image_a.num_valid(),
        scan_b.len(),
        image_b.num_valid()
    );

    let cells = config.height * config.width;
    let mut t_b_a = Isometry3::identity();
    // Like ICP, the association improves with the estimate: many rounds, the gate shrinking from 1 m
    // to 0.2 m.
    let gates = [1.0; 12].into_iter().chain([0.5; 6]).chain([0.2; 6]);
    for (round, gate) in gates.enumerate() {
        let (flow, confidence) = nearest_cell_flow(&image_a, &image_b, &t_b_a, &config, gate);
        let decode = DecodeConfig { min_confidence: f32::MIN_POSITIVE, ..Default::default() };
        let matches = decode_matches(&image_a.range, &image_b.range, &flow, &confidence, None, &config, &decode)?;
        let rows: Vec<i64> = matches.cells.iter().map(|c| c[0] as i64).collect();
        let cols: Vec<i64> = matches.cells.iter().map(|c| c[1] as i64).collect();
        let kept = nms(&rows, &cols, &matches.confidence, 1, Some(3000))?;
        let src: Vec<Point3<f64>> = kept.iter().map(|&i| matches.source[i]).collect();
        let dst: Vec<Point3<f64>> = kept.iter().map(|&i| matches.target[i]).collect();
        let result = ransac_rigid(&src, &dst, &RansacConfig { threshold: (gate / 2.0).max(0.1), ..Default::default() })?;
        t_b_a = result.transform;
        println!(
            "round {round}: {} of {} cells matched, {} after NMS, {} inliers, rmse {:.3} m, {} hypotheses",
            matches.len(),
            cells,
            src.len(),
            result.num_inliers,
            result.rmse,
            result.iterations
        );
    }

    println!("T_B_A (p_B = T · p_A):\n{}", t_b_a.to_homogeneous());
    let (roll, pitch, yaw) = t_b_a.rotation.euler_angles();
    println!(
        "translation {:.4} {:.4} {:.4} m, roll/pitch/yaw {:.4}/{:.4}/{:.4} deg",
        t_b_a.translation.x,
        t_b_a.translation.y,
        t_b_a.translation.z,
        roll.to_degrees(),
        pitch.to_degrees(),
        yaw.to_degrees()
    );
    if let Some(motion) = known_motion {
        let error = motion.inverse() * t_b_a;
        println!(
            "vs the applied motion: {:.4} m, {:.4} deg",
            error.translation.vector.norm(),
            error.rotation.angle().to_degrees()
        );
    }
    Ok(())
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match run(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {error}");
            ExitCode::FAILURE
        }
    }
}
